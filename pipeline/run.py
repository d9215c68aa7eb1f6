"""The canonical in-memory form of a chamber run, whatever the file format (docs/log-format.md).

A :class:`Run` holds the run metadata and one polars table per stream. Column names and dtypes are fixed:

========================  ==============================================================
stream                    columns (dtype)
========================  ==============================================================
``voltmeter``             ``t_ns`` (Int64, ns since the Unix epoch), ``ux, uy, uz`` (Float64, V)
``au_temperature``        ``t_ns`` (Int64), ``temp_c`` (Float64, C, the AU's own thermosensor)
``chamber`` (optional)    ``t_ns`` (Int64), ``setpoint_c``, ``air_c`` (Float64, C)
``fixture`` (optional)    ``t_ns`` (Int64), ``position`` (String: TP1..TP6, VP1..VP6, MOVING)
========================  ==============================================================

A run holding several units (log-format.md, "Runs with several units") is a :class:`UnitRuns`: one :class:`Run` per
unit, each with its own voltmeter and thermosensor tables and the unit's metadata (shared keys, ``<serial>.<key>``
overrides applied), all sharing the one ``chamber`` and ``fixture`` table objects (decoded once, never copied per
unit), plus the units that failed the input checks with their one-line reasons.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import polars as pl

from pipeline.errors import RunFormatError

STREAM_COLUMNS: dict[str, dict[str, Any]] = {
    "voltmeter": {"t_ns": pl.Int64, "ux": pl.Float64, "uy": pl.Float64, "uz": pl.Float64},
    "au_temperature": {"t_ns": pl.Int64, "temp_c": pl.Float64},
    "chamber": {"t_ns": pl.Int64, "setpoint_c": pl.Float64, "air_c": pl.Float64},
    "fixture": {"t_ns": pl.Int64, "position": pl.String},
}
REQUIRED_STREAMS = ("voltmeter", "au_temperature")
OPTIONAL_STREAMS = ("chamber", "fixture")

#: Metadata keys that every run must carry (docs/log-format.md); values are strings in the files.
REQUIRED_META = ("unit_serial", "run_id")
#: Metadata key of a run holding several units: their serials, comma-separated (log-format.md)
UNITS_KEY = "units"
#: Optional metadata key: the PX4 device id of the unit's accelerometer (decimal or 0x hexadecimal, 1 .. 2^32 - 1),
#: recorded in the passport's provenance and used by ``thermocal export --format px4`` (log-format.md)
PX4_DEVICE_ID_KEY = "px4_accel_device_id"
#: Streams each unit of a run with several units has its own of; the others are shared by all units
PER_UNIT_STREAMS = REQUIRED_STREAMS
#: nanoseconds per second (times are Int64 ns since the Unix epoch)
NS_PER_S = 1_000_000_000
#: per-sample passes over a long run read it this many samples at a time (a slab's temporaries, not the record's)
SLAB_SAMPLES = 1 << 20

#: a number's default where the metadata lacks it: a number, or None for an optional one
_Default = TypeVar("_Default", float, None)


def slab_of(column, s0: int, s1: int) -> np.ndarray:
    """Samples ``s0 .. s1 - 1`` of one column (a polars Series or a numpy array) as a numpy array.

    The readers build long tables in chunks (no whole-record copy while reading); a slab inside one chunk is a
    view of the table's memory, one across a chunk boundary a copy of the slab only."""
    if isinstance(column, pl.Series):
        return column.slice(s0, s1 - s0).to_numpy()
    return column[s0:s1]


@dataclass(frozen=True)
class RunMeta:
    """Run metadata (docs/log-format.md). Values are typed here; in files they are strings."""

    unit_serial: str
    run_id: str
    station: str = ""
    fixture: str = ""
    normal_temp_c: float = 20.0
    g_local_mps2: float = 9.80665
    started_utc: str = ""
    nominal_gain_v_per_g: float | None = None
    #: the unit's class (``navigation``, ``tactical``, ``industrial``, ``consumer``: :data:`pipeline.verify.GRADES`),
    #: which sets the verification limits; None where the run names none
    unit_grade: str | None = None
    extra: dict[str, str] = field(default_factory=dict)

    def to_strings(self) -> dict[str, str]:
        """The metadata as the string-to-string map stored in files."""
        out = {
            "unit_serial": self.unit_serial,
            "run_id": self.run_id,
            "station": self.station,
            "fixture": self.fixture,
            "normal_temp_c": _fmt_float(self.normal_temp_c),
            "g_local_mps2": _fmt_float(self.g_local_mps2),
            "started_utc": self.started_utc,
        }
        if self.nominal_gain_v_per_g is not None:
            out["nominal_gain_v_per_g"] = _fmt_float(self.nominal_gain_v_per_g)
        if self.unit_grade is not None:
            out["unit_grade"] = self.unit_grade
        out.update(self.extra)
        return out

    @classmethod
    def from_strings(cls, values: dict[str, Any], *, path: str | None = None) -> RunMeta:
        """Parse the string map of a file; raise :class:`RunFormatError` naming the key on bad input."""
        if not isinstance(values, dict):
            raise RunFormatError("run metadata is not a key/value map", path=path, stream="metadata")
        for key in REQUIRED_META:
            v = values.get(key)
            if not isinstance(v, str) or not v.strip():
                raise RunFormatError(f"metadata key {key!r} is missing or empty", path=path, stream="metadata")

        def num(key: str, default: _Default) -> float | _Default:
            v = values.get(key)
            if v is None or (isinstance(v, str) and v.strip() == ""):
                return default
            try:
                x = float(v)
            except (TypeError, ValueError):
                raise RunFormatError(
                    f"metadata key {key!r} is not a number: {v!r}", path=path, stream="metadata"
                ) from None
            if not math.isfinite(x):
                raise RunFormatError(f"metadata key {key!r} is not finite: {v!r}", path=path, stream="metadata")
            return x

        known = {
            "unit_serial",
            "run_id",
            "station",
            "fixture",
            "normal_temp_c",
            "g_local_mps2",
            "started_utc",
            "nominal_gain_v_per_g",
            "unit_grade",
        }
        if values.get(PX4_DEVICE_ID_KEY) not in (None, "") and px4_device_id(values[PX4_DEVICE_ID_KEY]) is None:
            raise RunFormatError(
                f"metadata key {PX4_DEVICE_ID_KEY!r} is not a device id (1 .. 2^32 - 1, decimal or 0x hexadecimal): "
                f"{values[PX4_DEVICE_ID_KEY]!r}",
                path=path,
                stream="metadata",
            )
        return cls(
            unit_serial=str(values["unit_serial"]).strip(),
            run_id=str(values["run_id"]).strip(),
            station=str(values.get("station", "")),
            fixture=str(values.get("fixture", "")),
            normal_temp_c=num("normal_temp_c", 20.0),
            g_local_mps2=num("g_local_mps2", 9.80665),
            started_utc=str(values.get("started_utc", "")),
            nominal_gain_v_per_g=num("nominal_gain_v_per_g", None),
            unit_grade=_grade(values.get("unit_grade"), path),
            extra={str(k): str(v) for k, v in values.items() if k not in known},
        )


def px4_device_id(value: Any) -> int | None:
    """A PX4 device id from text (decimal or 0x hexadecimal) or a number: 1 .. 2^32 - 1, else None."""
    try:
        n = int(str(value).strip(), 0)
    except ValueError:
        return None
    return n if 0 < n < 1 << 32 else None


def _grade(value: Any, path: str | None) -> str | None:
    """The metadata's ``unit_grade`` (None when absent or empty); RunFormatError for a name that is no grade."""
    from pipeline.verify import GRADES

    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    grade = str(value).strip()
    if grade not in GRADES:
        raise RunFormatError(
            f"metadata key 'unit_grade' is not a unit grade: {value!r} ({', '.join(GRADES)})",
            path=path,
            stream="metadata",
        )
    return grade


def _fmt_float(x: float) -> str:
    return repr(float(x))


@dataclass
class Run:
    """One unit's recording: metadata plus one polars table per stream (see module doc for columns).

    ``source`` is the file or directory it was read from (empty for a run made in memory); ``warnings`` lists what
    the reader dropped or repaired, in one line each.
    """

    meta: RunMeta
    voltmeter: pl.DataFrame
    au_temperature: pl.DataFrame
    chamber: pl.DataFrame | None = None
    fixture: pl.DataFrame | None = None
    source: str = ""
    warnings: list[str] = field(default_factory=list)
    #: (first, last) voltmeter ns of the files joined into this run (:func:`pipeline.calibrate.inputs.join_runs`)
    #: that had no fixture log while another had one: the log says nothing then, and a position it logged before
    #: is believed there, or after, only where the signal agrees
    unlogged_ns: tuple[tuple[int, int], ...] = ()
    #: the voltmeter stretches the readers set to NaN as stuck or clipped, already named in a warning
    #: (:func:`pipeline.io.checks.check_stream`): (channel, first ns, last ns) each; the segmenter's non-finite line
    #: does not count them again
    left_out_ns: tuple[tuple[str, int, int], ...] = ()

    def stream(self, name: str) -> pl.DataFrame | None:
        return getattr(self, name)

    def streams(self) -> dict[str, pl.DataFrame]:
        """The streams present, by name, in the order of docs/log-format.md."""
        out = {}
        for name in STREAM_COLUMNS:
            df = self.stream(name)
            if df is not None:
                out[name] = df
        return out

    # Convenience numpy views (no copy for the float columns of a single-chunk frame).
    def t_ns(self) -> np.ndarray:
        return self.voltmeter["t_ns"].to_numpy()

    def voltmeter_slab(self, s0: int, s1: int, columns: tuple[str, ...] = ("ux", "uy", "uz")) -> list[np.ndarray]:
        """Voltmeter samples ``s0 .. s1 - 1`` of the named columns as 1-D numpy arrays (:func:`slab_of`).
        Per-sample passes over a long run read it :data:`SLAB_SAMPLES` at a time this way, so that their memory
        stays that of the table."""
        df = self.voltmeter
        return [slab_of(df[c], s0, s1) for c in columns]

    def u_v(self) -> np.ndarray:
        """Voltmeter samples as an (n, 3) float64 array of volts (a copy of all samples; see
        :meth:`voltmeter_slab`)."""
        return np.column_stack([self.voltmeter[c].to_numpy() for c in ("ux", "uy", "uz")])

    def thermosensor(self) -> tuple[np.ndarray, np.ndarray]:
        """The AU thermosensor's finite samples, as stored: times (n,) int64 ns and temperatures (n,) C."""
        tt = self.au_temperature["t_ns"].to_numpy()
        temp = self.au_temperature["temp_c"].to_numpy()
        ok = np.isfinite(temp)
        return tt[ok], temp[ok]

    def temperature_at(self, t_ns: np.ndarray) -> np.ndarray:
        """AU thermosensor temperature (C) linearly interpolated at ``t_ns``."""
        tt = self.au_temperature["t_ns"].to_numpy()
        return np.interp(
            np.asarray(t_ns, dtype=np.float64), tt.astype(np.float64), self.au_temperature["temp_c"].to_numpy()
        )


def make_frame(stream: str, columns: dict[str, Any]) -> pl.DataFrame:
    """Build a stream table with the canonical column names and dtypes from arrays or lists."""
    spec = STREAM_COLUMNS[stream]
    return pl.DataFrame({name: pl.Series(name, columns[name], dtype=dtype) for name, dtype in spec.items()})


def empty_frame(stream: str) -> pl.DataFrame:
    return pl.DataFrame(schema=STREAM_COLUMNS[stream])


def listed_units(values: dict[str, str]) -> list[str] | None:
    """The serials the metadata's ``units`` key lists, in its order (None: a single-unit run, no ``units`` key).
    RunFormatError for an empty list or a serial listed twice."""
    text = values.get(UNITS_KEY)
    if text is None:
        return None
    serials = [s.strip() for s in str(text).split(",")]
    if not any(serials) or not all(serials):
        raise RunFormatError(f"metadata key {UNITS_KEY!r} has an empty serial: {text!r}", stream="metadata")
    twice = sorted({s for s in serials if serials.count(s) > 1})
    if twice:
        raise RunFormatError(f"metadata key {UNITS_KEY!r} lists {', '.join(twice)} more than once", stream="metadata")
    return serials


def unit_meta_values(values: dict[str, str], serial: str, serials: list[str]) -> dict[str, str]:
    """One unit's metadata in a run with several units: the shared keys, overridden by the ``<serial>.<key>`` keys of
    this unit, with ``unit_serial`` set to ``serial``; ``units`` and the other units' overrides left out."""
    prefixes = tuple(f"{s}." for s in serials)
    out = {k: v for k, v in values.items() if k != UNITS_KEY and not k.startswith(prefixes)}
    mine = f"{serial}."
    out.update({k[len(mine) :]: v for k, v in values.items() if k.startswith(mine)})
    out["unit_serial"] = serial
    return out


def shared_meta_values(metas: list[RunMeta]) -> dict[str, str]:
    """The metadata strings of a run with several units made of the units' metadata (``metas``, one per unit, the
    same run_id): the first unit's keys, ``units`` listing the serials, and a ``<serial>.<key>`` for each key in which
    a unit differs from the first."""
    first = metas[0].to_strings()
    out = {k: v for k, v in first.items() if k != "unit_serial"}
    out[UNITS_KEY] = ",".join(m.unit_serial for m in metas)
    for m in metas:
        for k, v in m.to_strings().items():
            if k != "unit_serial" and out.get(k) != v:
                out[f"{m.unit_serial}.{k}"] = v
        for k in first.keys() - m.to_strings().keys():
            if k != "unit_serial":
                out[f"{m.unit_serial}.{k}"] = ""
    return out


@dataclass
class UnitRuns:
    """A recording of one or more units in one file (log-format.md, "Runs with several units").

    ``units``: the units that passed the input checks, by serial in the metadata's order, each a :class:`Run` of its
    own whose ``chamber`` and ``fixture`` are the one shared table objects; ``failed``: the units that did not (a
    unit listed without samples, samples of an unlisted unit, a bad per-unit stream, a dead channel), each with its
    one-line reason; ``several``: True for the layout with several units (even when it lists one), False for a
    single-unit run (then ``units`` holds that run). ``meta_values``: the metadata strings as in the file.
    """

    units: dict[str, Run]
    failed: dict[str, str] = field(default_factory=dict)
    several: bool = False
    meta_values: dict[str, str] = field(default_factory=dict)
    source: str = ""
    warnings: list[str] = field(default_factory=list)

    @classmethod
    def of_units(cls, runs: list[Run], source: str = "") -> UnitRuns:
        """A run with several units made in memory from per-unit runs of one recording (same run_id); the first
        run's chamber and fixture are the shared ones."""
        if not runs:
            raise RunFormatError("a run with several units needs at least one unit", path=source or None)
        serials = [r.meta.unit_serial for r in runs]
        if len(set(serials)) != len(serials):
            raise RunFormatError(f"units listed twice: {', '.join(serials)}", path=source or None)
        first = runs[0]
        units = {
            r.meta.unit_serial: Run(
                meta=r.meta,
                voltmeter=r.voltmeter,
                au_temperature=r.au_temperature,
                chamber=first.chamber,
                fixture=first.fixture,
                source=source,
                left_out_ns=r.left_out_ns,
            )
            for r in runs
        }
        return cls(units, several=True, meta_values=shared_meta_values([r.meta for r in runs]), source=source)

    @property
    def serials(self) -> list[str]:
        """Every unit the recording names: the checked ones in order, then the failed ones."""
        return [*self.units, *(s for s in self.failed if s not in self.units)]

    @property
    def chamber(self) -> pl.DataFrame | None:
        return next(iter(self.units.values())).chamber if self.units else None

    @property
    def fixture(self) -> pl.DataFrame | None:
        return next(iter(self.units.values())).fixture if self.units else None

    def select(self, serials: list[str] | None) -> UnitRuns:
        """Only the named units (None: all); RunFormatError naming a serial the recording does not hold."""
        if not serials:
            return self
        unknown = [s for s in serials if s not in self.units and s not in self.failed]
        if unknown:
            raise RunFormatError(
                f"no unit {', '.join(unknown)} in this run (units: {', '.join(self.serials)})",
                path=self.source or None,
                where="--unit",
            )
        return UnitRuns(
            {s: r for s, r in self.units.items() if s in serials},
            {s: why for s, why in self.failed.items() if s in serials},
            self.several,
            self.meta_values,
            self.source,
            self.warnings,
        )

    def one(self, serial: str | None = None) -> Run:
        """The run of one unit: ``serial``'s, or the only unit's. RunFormatError when the unit failed its checks
        (its reason), or when ``serial`` is None and the run holds several units."""
        if serial is None:
            if len(self.units) + len(self.failed) != 1:
                raise RunFormatError(
                    f"the run holds {len(self.serials)} units ({', '.join(self.serials)}): name one with --unit",
                    path=self.source or None,
                )
            serial = self.serials[0]
        if serial in self.failed:
            raise UnitFailed(self.failed[serial])
        return self.select([serial]).units[serial]


def check_serials(read: list[UnitRuns], serials: list[str] | None) -> None:
    """``--unit`` over the files given together (``read``: each file's :class:`UnitRuns`): a serial is selectable
    when some file holds it (a unit missing from one piece of its run is calibrated from the pieces it is in); one
    in no file is a RunFormatError naming it (one file: :meth:`UnitRuns.select`'s, naming that file's units). A file
    of a single unit must be that unit's (:meth:`UnitRuns.select`)."""
    if not serials:
        return
    if len(read) == 1:
        read[0].select(serials)
        return
    for got in read:
        if not got.several:
            got.select(serials)
    held = [s for got in read for s in got.serials]
    unknown = [s for s in serials if s not in held]
    if unknown:
        raise RunFormatError(
            f"no unit {', '.join(unknown)} in any of these runs (units: {', '.join(dict.fromkeys(held))})",
            path=" + ".join(got.source or "?" for got in read),
            where="--unit",
        )


class UnitFailed(RunFormatError):
    """A unit of a run with several units that failed its input checks; the message is its one-line reason."""

    def __init__(self, line: str):
        super().__init__(line)
