"""Fleet recalibration without Prefect: find the runs under a folder, group them by unit, skip what is done,
calibrate one unit's group while isolating a bad run.

- :func:`discover_runs`: every run under a folder, both layouts (``*.mcap`` files; Parquet run directories, i.e.
  directories holding ``voltmeter.parquet`` or ``run.json``); hidden names (writers' temp files) are ignored.
- :func:`pipeline.io.runs.read_run_meta`: a run's metadata only (the MCAP ``run`` record through the summary's metadata
  index; a Parquet run's ``run.json``), to group runs by unit without reading their samples.
- :func:`plan_fleet`: groups by unit serial; a group whose identity (the content hashes of its runs and the
  settings, :func:`pipeline.passport.registry.identity_key`) is already in the registry is skipped ("already
  processed"). Metadata and hashes are read in a few threads (hashing releases the GIL); the hashes travel with the
  groups, so the calibration does not read the runs a second time to hash them (unless a run changed since, by its
  :func:`pipeline.passport.provenance.file_signature`).
- :func:`calibrate_group`: the calibration of one unit from all its runs (TP runs and the VP runs that verify them)
  by any method (the registry ``pipeline.calibrate.methods``; a method that uses a base passport starts from
  the unit's passport in the registry, :func:`pipeline.calibrate.methods.base_passport_of`). A run that cannot be
  read is dropped and reported; the others are one recording of the unit
  (:func:`pipeline.calibrate.inputs.join_runs`), calibrated together. Never raises for a bad input: failures come
  back as ``{"run", "reason"}`` rows with the one-line reason.

The Prefect flow (``flows/fleet.py``) runs :func:`plan_fleet` once and :func:`calibrate_group` as one task per unit.

A run holding several units (log-format.md) counts once per unit: each of its units is grouped with that unit's
other runs, and its passport's provenance names the run and the unit; a unit of it whose data is bad fails alone.
The units whose only run it is are calibrated together, as ``thermocal calibrate RUN`` calibrates them
(:func:`compute_run`: the run read once, segmented once by the consensus of its units,
:func:`pipeline.segment_units.segment_units`), so the passports are the same whichever command made them
(:meth:`FleetPlan.batches`). So are the units whose runs are the same pieces of such a run (one run_id, cut into
files): each unit's pieces joined, the joined units segmented together, as ``calibrate PART1 PART2`` does. A unit
with a run of its own beside them is one recording of all its files, its own streams read from the runs
(``read_run(path, unit)``) and segmented alone, as ``calibrate`` does with the same files.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.calibrate.inputs import (
    RunInput,
    absent_from_pieces,
    folder_warning,
    join_runs,
    joined_recordings,
    recordings_by_files,
    resolve_run_ids,
    select_runs,
    units_span_ns,
)
from pipeline.calibrate.methods import all_methods, base_passport_of, by_name, default_base_passport, resolve_auto
from pipeline.calibrate.publish import publish, recorded_settings
from pipeline.calibrate.result import CalibrationResult, base_reference
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import CalibrationError, ThermocalError
from pipeline.io.files import NOT_REGULAR, special_kind
from pipeline.io.parquet import META_FILE as PARQUET_META_FILE
from pipeline.io.runs import (  # noqa: F401  (read_run_meta: part of this API)
    read_run,
    read_run_meta,
    read_units,
    read_units_meta,
    run_format,
)
from pipeline.passport.document import Passport
from pipeline.passport.provenance import RunDigest, hash_run
from pipeline.passport.registry import Registry, identity_key
from pipeline.run import Run, RunMeta
from pipeline.segment import Segmentation

#: A directory holding one of these is a Parquet run directory (docs/log-format.md).
PARQUET_RUN_MARKERS = ("voltmeter.parquet", PARQUET_META_FILE)
MCAP_SUFFIX = ".mcap"
ALREADY_PROCESSED = "already processed"
#: where a fleet's unit calibrations run locally (``fleet --pool``): ``auto`` picks by unit count
POOLS = ("auto", "process", "thread")
#: Threads reading runs' metadata and hashing them while planning.
PLAN_THREADS = min(4, os.cpu_count() or 1)


@dataclass(frozen=True)
class UnitGroup:
    """The runs of one unit to calibrate together (absolute paths), the identity their passport will have, the
    runs' hashes by path, the base passport of a method that needs one (for :func:`calibrate_group`) and, for the
    runs that hold several units, ``{"unit", "run_id"}`` by path (``within``)."""

    unit: str
    runs: tuple[str, ...]
    identity: str
    digests: dict[str, RunDigest] = field(default_factory=dict, compare=False)
    base_passport: Passport | None = field(default=None, compare=False)
    within: dict[str, dict] = field(default_factory=dict, compare=False)
    #: warnings about the unit's inputs found while planning (a piece of its run it is missing from), put first in
    #: its calibration's warnings, as ``calibrate`` puts them
    warnings: tuple[str, ...] = field(default=(), compare=False)

    @property
    def shared_runs(self) -> tuple[str, ...] | None:
        """This unit's runs, sorted, when every one of them holds several units (the run, or the pieces of one
        recording cut into files: its segmentation is made with the other units of the same files,
        :func:`compute_run`), else None."""
        return tuple(sorted(self.runs)) if self.runs and all(r in self.within for r in self.runs) else None


@dataclass
class FleetPlan:
    """What a fleet job will do: ``groups`` to calibrate, runs ``skipped`` ({run, why, ...}), runs ``failed``
    before calibration ({run, reason}: metadata or file unreadable, a second file with a run_id) and ``warnings``
    ({run, warning}: a folder name naming another unit)."""

    root: str
    groups: list[UnitGroup] = field(default_factory=list)
    skipped: list[dict] = field(default_factory=list)
    failed: list[dict] = field(default_factory=list)
    warnings: list[dict] = field(default_factory=list)

    @property
    def runs_found(self) -> int:
        return sum(len(g.runs) for g in self.groups) + len(self.skipped) + len(self.failed)

    def batches(self) -> list[list[UnitGroup]]:
        """The groups as the fleet's tasks calibrate them: the units whose runs are the same files, all holding
        several units (one run, or the pieces of one), together, one batch a set of files (:func:`compute_run`: the
        files read and segmented once, as ``calibrate``), every other unit alone (:func:`compute_group`); in the
        order of :attr:`groups`."""
        out: list[list[UnitGroup]] = []
        by_run: dict[tuple[str, ...], list[UnitGroup]] = {}
        for g in self.groups:
            run = g.shared_runs
            if run is None:
                out.append([g])
            elif run in by_run:
                by_run[run].append(g)
            else:
                by_run[run] = [g]
                out.append(by_run[run])
        return out


@dataclass
class UnitOutcome:
    """The result of :func:`calibrate_group`: ``result`` is the ``calibrate --json`` object (None if the unit
    could not be calibrated); ``failed`` the runs dropped or failed, with their one-line reasons; ``compute_s``
    the wall time spent in the calibration itself (for the fleet's overhead figures)."""

    unit: str
    runs: list[str]
    result: dict | None
    failed: list[dict]
    compute_s: float

    @property
    def used_runs(self) -> list[str]:
        bad = {f["run"] for f in self.failed}
        return [r for r in self.runs if r not in bad]


def reason_of(exc: BaseException) -> str:
    """The one-line reason reported for a failed run: the ThermocalError's line, else ``internal error: ...``."""
    if isinstance(exc, ThermocalError):
        return exc.one_line()
    return f"internal error: {type(exc).__name__}: {' '.join(str(exc).split())}"


# ---------------------------------------------------------------------------------------------------------------
# discovery and metadata


def discover_runs(root: str | os.PathLike) -> list[Path]:
    """Every run under ``root`` (recursively), sorted: ``*.mcap`` files and Parquet run directories (not descended
    into). Names starting with ``.`` are skipped: writers put their temp files there
    (``pipeline.io.runs.write_run``)."""
    root = Path(root)
    if not root.is_dir():
        raise ThermocalError("not a directory (fleet expects a folder of runs)", path=str(root))
    found: list[Path] = []

    def walk_error(exc: OSError) -> None:
        raise ThermocalError(f"cannot list the folder ({exc.strerror})", path=exc.filename)

    for dirpath, dirnames, filenames in os.walk(root, onerror=walk_error):
        if any(m in filenames for m in PARQUET_RUN_MARKERS):
            found.append(Path(dirpath))
            dirnames[:] = []
            continue
        dirnames[:] = [d for d in dirnames if not d.startswith(".")]
        found += [Path(dirpath) / f for f in filenames if f.lower().endswith(MCAP_SUFFIX) and not f.startswith(".")]
    return sorted(found)


def _meta_of(path: Path) -> tuple[list[RunMeta], bool]:
    """The metadata of each unit of a run, and whether the run holds several units (its metadata lists
    ``units``): read alone, or, if that fails, from reading the whole run (which raises the reader's precise
    one-line error for a bad run)."""
    try:
        return read_units_meta(path)
    except Exception:
        got = read_units(path)
        return [r.meta for r in got.units.values()], got.several


# ---------------------------------------------------------------------------------------------------------------
# planning


def plan_fleet(
    root: str | os.PathLike,
    registry: str | os.PathLike | Registry,
    settings: CalibrationSettings = CalibrationSettings(),
    method: str = "tilt",
) -> FleetPlan:
    """Group the runs under ``root`` by unit and decide what to calibrate (by ``method``; ``auto``: as
    ``calibrate --method auto``, the method each unit's first run supports, chosen when it is calibrated).

    A run whose metadata or bytes cannot be read is ``failed``; a second copy of a run (same content hash as
    another run of the unit) is ``skipped`` as a duplicate; files with one run_id count no sample twice
    (:func:`pipeline.calibrate.inputs.resolve_run_ids`: a truncated copy is ``skipped`` once, ``{"run", "why":
    "truncated copy of PATH", "units": [the units it holds]}``, and the complete file used,
    the pieces of one recording all used, or ``skipped`` as "part of" the file holding the recording whole beside
    them, two recordings under one id both ``failed``); a run whose folder names
    another unit is filed by its metadata, with a warning; a unit whose group identity (its runs' content hashes +
    ``settings``) is already in ``registry`` has all its runs ``skipped`` as "already processed". A file skipped
    is listed once (per why, and version), with ``"units"``: every unit it is skipped for. Paths in the
    plan are absolute, as in the passports' provenance.
    """
    reg = registry if isinstance(registry, Registry) else Registry(registry)
    plan = FleetPlan(root=str(root))
    by_unit: dict[str, list[dict]] = {}
    paths = []
    for p in discover_runs(root):
        kind = special_kind(p)
        if kind is not None:  # a FIFO or a device named like a run: never opened (it would hang the fleet)
            plan.skipped.append({"run": str(p.resolve()), "why": f"{kind}, {NOT_REGULAR}"})
        else:
            paths.append(p.resolve())
    with ThreadPoolExecutor(max_workers=PLAN_THREADS) as pool:
        inspected = list(pool.map(_inspect_run, paths))
    pieces: list[tuple[str, str, list[str]]] = []  # the runs holding several units: (path, run_id, serials)
    for path, (found, digest) in zip(paths, inspected):
        if isinstance(digest, BaseException):  # one bad run must not stop the fleet
            plan.failed.append({"run": str(path), "reason": reason_of(digest)})
            continue
        assert found is not None  # _inspect_run gives None only beside the exception
        metas, several = found
        if several and metas:
            pieces.append((str(path), metas[0].run_id, [m.unit_serial for m in metas]))
        for meta in metas:
            unit = meta.unit_serial
            warning = None if several else folder_warning(path, unit, Path(root).resolve())
            if warning:
                plan.warnings.append({"run": str(path), "warning": warning})
            by_unit.setdefault(unit, []).append(
                {
                    "path": str(path),
                    "sha256": digest.sha256,
                    "digest": digest,
                    "run_id": meta.run_id,
                    "several": several,
                }
            )
    absent = absent_from_pieces(pieces, _span_ns)  # a unit missing from one of the files its run was cut into
    candidates = all_methods() if method == "auto" else [by_name(method)]
    per_file: dict[tuple[str, str, int | None], dict] = {}  # (run, why, version) -> its skipped row

    def skip(run: str, why: str, unit: str, version: int | None = None) -> None:
        """A run skipped for ``unit``: one row per file (and why, and version), listing every unit it is skipped for."""
        row = per_file.setdefault((run, why, version), {"run": run, "why": why, "units": []})
        row["units"].append(unit)
        if version is not None:
            row["version"] = version

    for unit, inputs in sorted(by_unit.items()):
        unique: dict[str, dict] = {}
        for item in inputs:
            first = unique.setdefault(item["sha256"], item)
            if first is not item:
                skip(item["path"], f"duplicate of {first['path']}", unit)
        kept = list(unique.values())
        usable, dropped = resolve_run_ids([RunInput(i["path"], unit, i["run_id"]) for i in kept], _unit_reader(unit))
        if dropped:
            for f in dropped:  # a piece of the whole file beside it, or a copy the complete file is used in place of
                if "part_of" in f or "copy_of" in f:
                    skip(f["run"], f"part of {f['part_of']}" if "part_of" in f else f["copy_of"], unit)
            plan.failed += [{**f, "unit": unit} for f in dropped if "part_of" not in f and "copy_of" not in f]
            paths_kept = {u.path for u in usable}
            kept = [i for i in kept if i["path"] in paths_kept]
            if not kept:
                continue

        def identities(base: Passport | None, uses_base: bool, kept: list[dict] = kept) -> list[str]:
            return [
                identity_key(
                    kept,
                    recorded_settings(settings, m.passport_method, base_reference(base) if base is not None else {}),
                )
                for m in candidates
                if m.uses_base_passport == uses_base
            ]

        try:
            if method != "auto":
                uses_base = candidates[0].uses_base_passport
                base = base_passport_of(reg, unit)[0] if uses_base else None
                identity = identities(base, uses_base)[0]
                done = reg.find(unit, identity)
            else:  # done by whichever method it picks; the base only for a unit not done yet
                plain = identities(None, False)
                identity, base = plain[0], None
                done = reg.find(unit, *plain)
                if done is None:
                    base = default_base_passport(reg, unit)[0]
                    done = reg.find(unit, *identities(base, True))
        except ThermocalError as exc:  # e.g. a unit serial that cannot be a registry name
            plan.failed += [{"run": i["path"], "reason": exc.one_line()} for i in kept]
            continue
        if done is not None:
            for i in kept:
                skip(i["path"], ALREADY_PROCESSED, unit, done.version)
            continue
        plan.groups.append(
            UnitGroup(
                unit=unit,
                runs=tuple(i["path"] for i in kept),
                identity=identity,
                digests={i["path"]: i["digest"] for i in kept},
                base_passport=base,
                within={i["path"]: {"unit": unit, "run_id": i["run_id"]} for i in kept if i["several"]},
                warnings=tuple(absent.get(unit, [])),
            )
        )
    plan.skipped += per_file.values()
    return plan


def _span_ns(path: str) -> tuple[int, int] | None:
    """The first and last voltmeter ns of a run's units (read only for a piece a unit is missing from); None when
    it cannot be read (the reading reports why elsewhere)."""
    try:
        got = read_units(path)
    except Exception:
        return None
    return units_span_ns(got)


def _unit_reader(unit: str) -> Callable[[str], Run]:
    """Reads ``unit``'s run from a path (its own streams, in a run holding several units)."""

    def read(path: str) -> Run:
        return read_run(path, unit)

    return read


def _inspect_run(path: Path) -> tuple[tuple[list[RunMeta], bool] | None, RunDigest | Exception]:
    """A run's units' metadata (:func:`_meta_of`) and :func:`pipeline.passport.provenance.hash_run`; or (None, the
    exception) if unreadable."""
    try:
        return _meta_of(path), hash_run(path)
    except Exception as exc:
        return None, exc


# ---------------------------------------------------------------------------------------------------------------
# one unit


def prepare_worker() -> None:
    """Import what calibrating a unit needs (both run readers, every method of the registry, which ``--method
    auto`` judges a recording by, matplotlib's Agg canvas) and draw one tiny figure to memory (matplotlib's fonts
    and Pillow's image plugins load on the first figure), so that a fresh worker process (the initializer of the
    fleet's process pool, the local server's warm worker) pays for it before its first unit, not in it."""
    import io

    # the scalar and differential fits import these where they run (judging a recording needs neither)
    import scipy.linalg
    import scipy.optimize  # noqa: F401
    from matplotlib import patches  # noqa: F401
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from pipeline import plots  # noqa: F401
    from pipeline.calibrate import recording  # noqa: F401
    from pipeline.io import mcap, parquet  # noqa: F401

    all_methods()

    fig = Figure(figsize=(1, 1), dpi=20)
    fig.subplots().set_title("warm-up", fontsize=7)
    FigureCanvasAgg(fig).print_png(io.BytesIO())


@dataclass
class ComputedUnit:
    """What :func:`compute_group` computed for one unit, for :func:`publish_group` to publish: the calibration (None
    when the unit could not be calibrated), the runs it used (``good``) and those dropped or failed (``failed``,
    one-line reasons), and the seconds it took. Nothing in it was signed or written: a worker computes, the station
    publishes."""

    unit: str
    runs: list[str]
    calibration: CalibrationResult | None
    good: list[str]
    failed: list[dict]
    compute_s: float
    #: the segmentation's run-level warnings (:func:`pipeline.segment_units.segment_units`) naming a unit not
    #: calibrated from it (a unit with a file of its own beside the run, segmented with that file): its own
    #: passport cannot carry them, so the fleet reports them by run ({"run", "warning"}); on one unit of a batch
    run_warnings: list[dict] = field(default_factory=list)


def compute_group(
    unit: str,
    runs: list[str] | tuple[str, ...],
    settings: CalibrationSettings = CalibrationSettings(),
    method: str = "tilt",
    base_passport: Passport | None = None,
    within: Mapping[str, dict] | None = None,
) -> ComputedUnit:
    """Calibrate ``unit`` from ``runs`` by ``method`` (``base_passport``: the differential method's starting
    passport, :attr:`UnitGroup.base_passport`; ``within``: :attr:`UnitGroup.within`, the runs holding several
    units, of which the unit's own streams are read), writing nothing: the part of a fleet that runs on its workers
    (a local process pool or dask workers, which may sit on other machines with other keys and other working
    folders: they never sign or write a passport, :func:`publish_group` does, on the station).

    Runs that cannot be read, or belong to another unit, are dropped (listed in ``failed``); the rest are one
    recording of the unit (:func:`pipeline.calibrate.inputs.join_runs`), calibrated together. If the unit cannot be
    calibrated at all, every remaining run is listed in ``failed`` with the reason and ``calibration`` is None. Bad
    inputs never raise. A unit whose only run holds several units is calibrated from the run's segmentation, as
    ``calibrate`` does (:func:`compute_run`), and so is a unit whose runs all hold several units (the pieces of one
    such run); a unit with a run of its own beside them is one recording of its files, segmented alone, as
    ``calibrate`` does with those files.
    """
    t0 = time.perf_counter()
    runs = [str(r) for r in runs]
    if runs and all(r in (within or {}) for r in runs):  # its runs hold several units: their consensus
        return compute_run(runs, {unit: base_passport}, settings, method)[0]
    failed: list[dict] = []
    good: list[str] = []
    calibration = None
    try:
        if method != "auto":
            by_name(method)
    except CalibrationError as exc:
        failed = [{"run": p, "reason": reason_of(exc)} for p in runs]
        return ComputedUnit(unit, runs, None, [], failed, time.perf_counter() - t0)
    read = []
    for path in runs:
        try:
            run = read_run(path, unit) if path in (within or {}) else read_run(path)
            if run.meta.unit_serial != unit:
                raise CalibrationError(f"run is of unit {run.meta.unit_serial!r}, not {unit!r}", path=path)
        except Exception as exc:
            failed.append({"run": path, "reason": reason_of(exc)})
            continue
        read.append(run)
        good.append(path)
    if good:
        try:
            holder = [join_runs(read)]  # the unit's files are one recording
            read.clear()
            calibration = _calibrate_recording(holder, None, settings, method, base_passport)
        except Exception as exc:
            reason = reason_of(exc)
            failed += [{"run": p, "reason": reason} for p in good]
            good = []
    return ComputedUnit(unit, runs, calibration, good, failed, time.perf_counter() - t0)


def _calibrate_recording(
    holder: list[Run], seg: Segmentation | None, settings: CalibrationSettings, method: str, base: Passport | None
) -> CalibrationResult:
    """One unit's recording (``holder``: a list holding its run, emptied once it is observed, so that its samples
    go then) calibrated by ``method`` (``auto``: the method it supports, :func:`resolve_auto`) from ``seg`` (its
    segmentation when already made: the run's consensus for a unit of a run with several, else None: segmented
    here): the steps of the calibrate flow's ``_calibrate_unit`` past its reading."""
    run = holder.pop()
    if method == "auto":  # the method the unit's recording supports
        method, base, seg, _ = resolve_auto(run, settings, base, seg)
    chosen = by_name(method)
    observed = [chosen.observe(run, settings, base_passport=base, segmentation=seg)]
    del run
    return chosen.calibrate_observed(observed, settings, base_passport=base)


def compute_run(
    paths: str | Sequence[str],
    bases: Mapping[str, Passport | None],
    settings: CalibrationSettings = CalibrationSettings(),
    method: str = "tilt",
) -> list[ComputedUnit]:
    """The units ``bases`` (serial -> the base passport a method may start from, :attr:`UnitGroup.base_passport`)
    of ``paths``, a run holding several units (or the files one such run was cut into, one run_id) that are each of
    these units' only runs, calibrated as ``thermocal calibrate PATHS`` calibrates them, writing nothing: each file
    read once with all its units (:func:`pipeline.io.runs.read_units`); of several files, each unit's pieces joined
    (:func:`pipeline.calibrate.inputs.joined_recordings`); segmented once when two or more units pass the input
    checks (:func:`pipeline.segment_units.segment_units`: the still times by the consensus of all the units of the
    same files, also those not calibrated here; a unit whose signal disagrees is named in its warnings), then each
    unit chosen, observed and fitted from its own segmentation. So a unit's passport is the one ``calibrate`` makes
    from the same files (constants bit-identical). A unit that fails the input checks, or its calibration, fails
    alone with its one-line reason; a file that cannot be read or segmented fails every unit of ``bases``. Never
    raises for bad input. Each unit's ``compute_s`` is its own calibration plus its share of the reading and
    segmentation."""
    from pipeline.segment_units import segment_units

    t0 = time.perf_counter()
    paths = [paths] if isinstance(paths, str) else [str(p) for p in paths]
    units = list(bases)
    warnings: dict[str, list[str]] = {}
    try:
        if method != "auto":
            by_name(method)
        read = [read_units(p) for p in paths]
        if len(paths) == 1:
            got = read[0]
            segs, run_lines = segment_units(got.units, settings.segment) if len(got.units) > 1 else ({}, [])
            mine = {u: got.units.pop(u) for u in units if u in got.units}
            failed_why = dict(got.failed)
        else:  # the pieces of one recording: each unit's joined, the units of the same files segmented together
            by_unit: dict[str, list[tuple[str, Run]]] = {}
            for p, got in zip(paths, read):
                for serial, run in got.units.items():
                    by_unit.setdefault(serial, []).append((p, run))
            failed_why = {u: why for got in read for u, why in got.failed.items()}
            joined = joined_recordings(by_unit)
            for got in read:
                got.units.clear()
            by_unit.clear()
            whole = frozenset(paths)
            together = recordings_by_files(joined).get(whole, [])
            segs, run_lines = (
                segment_units({s: joined[s][0] for s in together}, settings.segment) if len(together) > 1 else ({}, [])
            )
            mine = {}
            for u in units:
                if u in joined and frozenset(joined[u][1]) == whole:
                    mine[u], warnings[u] = joined[u][0], joined[u][2]
                elif u not in failed_why:
                    failed_why[u] = _unjoined_reason(u, paths)
            joined.clear()
    except Exception as exc:
        share = (time.perf_counter() - t0) / max(1, len(units))
        reason = reason_of(exc)
        return [
            ComputedUnit(u, list(paths), None, [], [{"run": p, "reason": reason} for p in paths], share) for u in units
        ]
    share = (time.perf_counter() - t0) / max(1, len(units))
    out = []
    for unit in units:
        t1 = time.perf_counter()
        calibration, failed = None, []
        if unit not in mine:
            why = failed_why.get(unit) or f"{_names(paths)}: no unit {unit} in this run"
            failed = [{"run": p, "reason": why} for p in paths]
        else:
            try:
                calibration = _calibrate_recording([mine.pop(unit)], segs.get(unit), settings, method, bases[unit])
                calibration.warnings[:0] = warnings.get(unit, [])
            except Exception as exc:
                failed = [{"run": p, "reason": reason_of(exc)} for p in paths]
        good = list(paths) if calibration is not None else []
        out.append(ComputedUnit(unit, list(paths), calibration, good, failed, share + time.perf_counter() - t1))
    lost = [w for w in run_lines if not any(w.startswith(f"unit {u}: ") for u in units)]
    if out and lost:  # the unit it names is calibrated elsewhere: said by run, once
        out[0].run_warnings = [{"run": " + ".join(paths), "warning": w} for w in lost]
    return out


def _names(paths: Sequence[str]) -> str:
    return ", ".join(os.path.basename(p) for p in paths)


def _unjoined_reason(unit: str, paths: Sequence[str]) -> str:
    """Why ``unit``'s pieces in ``paths`` are not one recording of them all: :func:`select_runs` and
    :func:`join_runs`'s one-line error on the unit's own streams, read again (only on this failure)."""
    try:
        runs, _ = select_runs([read_run(p, unit) for p in paths])
        if len(runs) < len(paths):
            return f"{_names(paths)}: unit {unit}'s files are not one recording of them all"
        join_runs(runs)
    except Exception as exc:
        return reason_of(exc)
    return f"{_names(paths)}: unit {unit}'s files are not one recording of them all"


def publish_group(
    registry: str | os.PathLike,
    computed: ComputedUnit,
    settings: CalibrationSettings = CalibrationSettings(),
    figure: bool = True,
    digests: Mapping[str, RunDigest] | None = None,
    within: Mapping[str, dict] | None = None,
) -> UnitOutcome:
    """Publish what :func:`compute_group` computed into ``registry``, signed with this station's key (the one place
    a fleet signs and appends: :func:`pipeline.calibrate.publish.publish`, as ``thermocal calibrate``). ``figure``:
    the PNG of the VP errors beside a new passport (~0.1 s of CPU); ``digests``: the runs' hashes from the
    planning, :attr:`UnitGroup.digests`, reused for the runs unchanged since; ``within``: :attr:`UnitGroup.within`
    (the provenance names the unit within a run of several). A registry that refuses (a chain that does not verify,
    a full disk) fails the unit's runs with its one-line reason; never raises for that."""
    failed = list(computed.failed)
    result = None
    if computed.calibration is not None:
        try:
            result = publish(
                registry,
                computed.calibration,
                input_paths=computed.good,
                settings=settings,
                figure=figure,
                input_digests=digests,
                input_units=within,
            )
        except Exception as exc:
            reason = reason_of(exc)
            failed += [{"run": p, "reason": reason} for p in computed.good]
    return UnitOutcome(computed.unit, computed.runs, result, failed, computed.compute_s)


def calibrate_group(
    unit: str,
    runs: list[str] | tuple[str, ...],
    registry: str | os.PathLike,
    settings: CalibrationSettings = CalibrationSettings(),
    figure: bool = True,
    digests: Mapping[str, RunDigest] | None = None,
    method: str = "tilt",
    base_passport: Passport | None = None,
    within: Mapping[str, dict] | None = None,
) -> UnitOutcome:
    """Calibrate ``unit`` from ``runs`` by ``method`` and publish the passport into ``registry``, in this process:
    :func:`compute_group` then :func:`publish_group` (as ``thermocal calibrate``). Bad inputs never raise."""
    computed = compute_group(unit, runs, settings, method, base_passport, within)
    return publish_group(registry, computed, settings, figure, digests, within)
