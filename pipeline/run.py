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
        }
        return cls(
            unit_serial=str(values["unit_serial"]).strip(),
            run_id=str(values["run_id"]).strip(),
            station=str(values.get("station", "")),
            fixture=str(values.get("fixture", "")),
            normal_temp_c=num("normal_temp_c", 20.0),
            g_local_mps2=num("g_local_mps2", 9.80665),
            started_utc=str(values.get("started_utc", "")),
            nominal_gain_v_per_g=num("nominal_gain_v_per_g", None),
            extra={str(k): str(v) for k, v in values.items() if k not in known},
        )


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
