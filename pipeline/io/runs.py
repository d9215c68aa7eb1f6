"""Reading and writing chamber runs, whatever the layout (docs/log-format.md).

:func:`read_run` opens a ``*.mcap`` file (:mod:`pipeline.io.mcap`) or a Parquet run directory
(:mod:`pipeline.io.parquet`) and returns the one in-memory form, :class:`pipeline.run.Run`; :func:`read_units` reads a
run of one or several units (log-format.md, "Runs with several units") as a :class:`pipeline.run.UnitRuns`, one
``Run`` per unit sharing the chamber and fixture tables. :func:`write_run` writes
either layout; :func:`read_run_meta` reads only the metadata. The checks both layouts share are in
:mod:`pipeline.io.checks`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import orjson
from mcap.reader import make_reader

from pipeline.errors import RunFormatError, ThermocalError
from pipeline.io.files import open_regular, read_regular_bytes
from pipeline.io.mcap import MAGIC, read_mcap_units, write_mcap
from pipeline.io.parquet import META_FILE, read_parquet_units, write_parquet_run
from pipeline.run import Run, RunMeta, UnitRuns, listed_units, unit_meta_values

FORMATS = ("mcap", "parquet")


def run_format(path: str | Path) -> str:
    """``"mcap"`` for a ``*.mcap`` file, ``"parquet"`` for a directory; :class:`RunFormatError` otherwise."""
    p = Path(path)
    if p.is_dir():
        return "parquet"
    if p.suffix.lower() == ".mcap":
        if not p.exists():
            raise RunFormatError("no such file", path=str(p))
        return "mcap"
    if not p.exists():
        raise RunFormatError("no such file or directory", path=str(p))
    raise RunFormatError("not a run: expected a .mcap file or a Parquet run directory", path=str(p))


def read_run(path: str | Path, unit: str | None = None) -> Run:
    """Read one unit's chamber run from a ``*.mcap`` file or a Parquet run directory: the run's only unit, or
    ``unit`` of a run with several (only its streams and the shared ones are decoded). RunFormatError when the run
    holds several units and none is named, or when the named unit failed its input checks (its reason)."""
    return read_units(path, None if unit is None else [unit]).one(unit)


def read_units(path: str | Path, units: list[str] | None = None) -> UnitRuns:
    """Read a run of one or several units as a :class:`UnitRuns` (the streams decoded once; each unit's ``Run``
    shares the chamber and fixture tables). ``units``: only these serials of a run with several units (an unknown
    one is a RunFormatError naming the units the run holds)."""
    only = set(units) if units else None
    fmt = run_format(path)
    got = read_mcap_units(path, only) if fmt == "mcap" else read_parquet_units(path, only)
    if units and got.several:
        missing = [u for u in units if u not in got.units and u not in got.failed]
        if missing:
            held = listed_units(got.meta_values) or []
            raise RunFormatError(
                f"no unit {', '.join(missing)} in this run (units: {', '.join(held)})", path=str(path), where="--unit"
            )
        return got
    return got.select(units)


def write_run(run: Run | UnitRuns, path: str | Path, fmt: str = "mcap", **opts: Any) -> Path:
    """Write ``run`` as an MCAP file (``fmt="mcap"``) or a Parquet run directory (``fmt="parquet"``).

    ``opts`` go to :func:`pipeline.io.mcap.write_mcap` (block size, chunk size, compression, summary). Returns the
    path written. The file or directory appears complete or not at all (written aside, then renamed); a place it
    cannot be written is a one-line :class:`ThermocalError`. A :class:`UnitRuns` read from a single-unit run (not
    ``several``) is written as that run, so what :func:`read_units` read is written back in the layout it came in.
    """
    if isinstance(run, UnitRuns) and not run.several and len(run.units) == 1:
        (run,) = run.units.values()  # streams with a unit column and no 'units' key: a file no reader accepts
    if fmt not in FORMATS:
        raise RunFormatError(f"unknown run format {fmt!r}; expected one of {', '.join(FORMATS)}", path=str(path))
    if fmt == "parquet" and opts:
        raise RunFormatError(f"options {sorted(opts)} do not apply to the parquet format", path=str(path))
    try:
        return write_mcap(run, path, **opts) if fmt == "mcap" else write_parquet_run(run, path)
    except OSError as e:
        raise ThermocalError(f"cannot write the run ({e.strerror or e})", path=str(path)) from None


# --- checks shared by the readers and writers -------------------------------------------------------------------


def read_run_meta(path: str | os.PathLike) -> RunMeta:
    """A single-unit run's metadata without reading its samples (about a millisecond); RunFormatError if it cannot
    be had, or if the run holds several units (:func:`read_units_meta`).
    """
    metas, _ = read_units_meta(path)
    if len(metas) != 1:
        raise RunFormatError(
            f"the run holds {len(metas)} units ({', '.join(m.unit_serial for m in metas)}): name one with --unit",
            path=str(path),
        )
    return metas[0]


def read_units_meta(path: str | os.PathLike) -> tuple[list[RunMeta], bool]:
    """The metadata of each unit of a run (one for a single-unit run; per unit of a run with several, its shared
    keys with its ``<serial>.<key>`` overrides), and whether the run has the layout of several units (its metadata
    lists ``units``), without reading its samples; RunFormatError if it cannot be had.

    MCAP: the ``run`` metadata record, through the summary's metadata index (files without a summary: read from
    the start up to that record, which thermocal's writer puts before the data). Parquet: ``run.json``. For a
    precise account of what is wrong with a bad run, read it with :func:`read_run`.
    """
    p = Path(path)
    try:
        if run_format(p) == "parquet":
            values = orjson.loads(
                read_regular_bytes(p / META_FILE, what="run metadata", limit=16 << 20, error=RunFormatError)
            )
        else:
            with open_regular(p) as f:
                if f.read(len(MAGIC)) != MAGIC:
                    raise RunFormatError("not an MCAP file (it does not start with the MCAP magic bytes)", path=str(p))
                f.seek(0)
                records = [dict(m.metadata) for m in make_reader(f).iter_metadata() if m.name == "run"]
                if len(records) > 1:
                    raise RunFormatError(
                        "two 'run' metadata records: a run has exactly one", path=str(p), stream="metadata"
                    )
                values = records[0] if records else None
    except RunFormatError:
        raise
    except Exception as exc:
        raise RunFormatError(
            f"cannot read the run metadata ({type(exc).__name__}: {exc})", path=str(p), stream="metadata"
        ) from None
    if values is None:
        raise RunFormatError("no run metadata (an MCAP metadata record named 'run')", path=str(p), stream="metadata")
    try:
        serials = listed_units(values) if isinstance(values, dict) else None
    except RunFormatError as e:
        raise RunFormatError(e.message, path=str(p), stream="metadata") from None
    if serials is None:
        return [RunMeta.from_strings(values, path=str(p))], False
    return [RunMeta.from_strings(unit_meta_values(values, s, serials), path=str(p)) for s in serials], True
