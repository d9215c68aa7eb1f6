"""The checks both run layouts share (docs/log-format.md), so that MCAP and Parquet accept and refuse exactly the same
runs.

Stream tables in canonical form, time order and time base, gaps, fixture labels, required streams and metadata:
:func:`assemble_run` turns what a reader decoded into a :class:`pipeline.run.Run`; :func:`writable_streams` checks a
run before a writer writes it.
"""

from __future__ import annotations

import math

import numpy as np
import polars as pl

from pipeline.errors import RunFormatError
from pipeline.positions import MOVING, POSITION_NAMES
from pipeline.run import REQUIRED_STREAMS, SLAB_SAMPLES, STREAM_COLUMNS, Run, RunMeta

#: Labels a fixture event may carry (docs/log-format.md).
FIXTURE_LABELS: tuple[str, ...] = (*POSITION_NAMES, MOVING)
#: An interval longer than this many median intervals of a stream is a gap (warned about by the readers, listed by
#: ``inspect``).
GAP_FACTOR = 5.0
#: A sampled stream whose time jumps forward by more than this is refused: a clock error, or two recordings in one
#: file (the segmenter works on the whole time span, so one sample stamped 1970 must not stretch it to decades).
MAX_JUMP_S = 86_400.0


def check_stream(stream: str, df: pl.DataFrame, *, path: str, warnings: list[str]) -> pl.DataFrame:
    """Check a stream table read from a file; return it in time order.

    ``df`` must already hold the canonical columns and dtypes. Null times and unknown fixture labels are errors;
    samples out of time order are sorted (stable) with a warning. In the sampled streams (all but ``fixture``),
    repeated samples (same ``t_ns``, same values) are dropped with a warning, while two different samples at one
    ``t_ns`` or a jump forward by more than :data:`MAX_JUMP_S` are errors; gaps are warned about. Non-finite values
    are kept.
    """
    t = df["t_ns"]
    if t.null_count():
        row = t.is_null().arg_max() or 0  # None only for an empty column
        raise RunFormatError("t_ns is missing (null)", path=path, stream=stream, where=f"row {row}")
    if not t.is_sorted():
        t_ns = t.to_numpy()
        back = t_ns[1:] < t_ns[:-1]
        row = int(back.argmax()) + 1
        df = df.sort("t_ns", maintain_order=True)
        warnings.append(
            f"{stream}: {int(np.count_nonzero(back))} samples were out of time order (first at row {row}: "
            f"t_ns={t_ns[row]} after t_ns={t_ns[row - 1]}); sorted by t_ns"
        )
    if stream != "fixture" and df.height > 1:
        df = _check_time_base(stream, df, path=path, warnings=warnings)
    if stream == "fixture" and df.height:
        bad = ~df["position"].is_in(FIXTURE_LABELS) | df["position"].is_null()
        if bad.any():
            row = bad.arg_max() or 0  # None only for an empty column
            raise RunFormatError(
                f"unknown fixture position {df['position'][row]!r} (expected one of {', '.join(FIXTURE_LABELS)})",
                path=path,
                stream=stream,
                where=f"t_ns={df['t_ns'][row]}",
            )
    return df


def _intervals(t_ns: np.ndarray):
    """``(offset, np.diff(t_ns[offset:offset + SLAB_SAMPLES + 1]))`` over the whole array: no temporary the length of a
    stream (at 1 kHz one is 0.5 GB, and every fresh one costs page faults)."""
    for a in range(0, t_ns.size - 1, SLAB_SAMPLES):
        yield a, np.diff(t_ns[a : a + SLAB_SAMPLES + 1])


def gap_indices(t_ns: np.ndarray) -> np.ndarray:
    """Indices ``i`` of the sorted times ``t_ns`` after which comes a gap: ``t_ns[i + 1] - t_ns[i]`` longer than
    :data:`GAP_FACTOR` median intervals (the median from at most ~100 000 intervals)."""
    n = t_ns.size - 1
    if n < 1:
        return np.empty(0, dtype=np.intp)
    k = np.arange(0, n, max(1, n // 100_000))
    median_ns = float(np.median(t_ns[k + 1] - t_ns[k]))
    if not median_ns > 0:
        return np.empty(0, dtype=np.intp)
    limit = np.int64(math.floor(GAP_FACTOR * median_ns))  # integer comparison: no float copy of the intervals
    return np.concatenate([a + np.flatnonzero(dt > limit) for a, dt in _intervals(t_ns)])


def _check_time_base(stream: str, df: pl.DataFrame, *, path: str, warnings: list[str]) -> pl.DataFrame:
    """Jumps (error), repeated samples (dropped) and gaps (warned) of a sampled stream sorted by time."""
    t_ns = df["t_ns"].to_numpy()
    jump_ns = np.int64(MAX_JUMP_S * 1e9)
    same_parts = []
    for a, dt in _intervals(t_ns):
        jump = np.flatnonzero(dt > jump_ns)
        if jump.size:
            i = a + int(jump[0])
            raise RunFormatError(
                f"time jumps forward by {(t_ns[i + 1] - t_ns[i]) / 3.6e12:.1f} h after "
                f"t_ns={t_ns[i]}: a clock error or two recordings in one file (at most "
                f"{MAX_JUMP_S / 3600:.0f} h without samples)",
                path=path,
                stream=stream,
                where=f"t_ns={t_ns[i + 1]}",
            )
        same_parts.append(a + np.flatnonzero(dt == 0) + 1)  # rows with the time of the row before
    same = np.concatenate(same_parts)
    if same.size:
        values = [c for c in df.columns if c != "t_ns"]
        a = df.select(values)[same - 1]
        b = df.select(values)[same]
        equal = np.ones(same.size, dtype=bool)
        for c in values:
            x, y = a[c].to_numpy(), b[c].to_numpy()
            equal &= (x == y) | (np.isnan(x) & np.isnan(y))
        if not equal.all():
            k = int(same[~equal][0])
            raise RunFormatError(
                "two different samples at the same time", path=path, stream=stream, where=f"t_ns={t_ns[k]}"
            )
        warnings.append(
            f"{stream}: dropped {same.size} repeated samples (same t_ns and values as the one before), "
            f"first at t_ns={t_ns[same[0]]}"
        )
        keep = np.ones(t_ns.size, dtype=bool)
        keep[same] = False
        df = df.filter(pl.Series(keep))
        t_ns = t_ns[keep]
    gaps = gap_indices(t_ns)
    if gaps.size:
        dt = t_ns[gaps + 1] - t_ns[gaps]
        i = int(gaps[np.argmax(dt)])
        warnings.append(
            f"{stream}: {gaps.size} gap(s) without samples, the longest {dt.max() / 1e9:.1f} s after "
            f"t_ns={t_ns[i]}; the samples either side are used"
        )
    return df


def assemble_run(
    meta_values: dict[str, str] | None, frames: dict[str, pl.DataFrame], *, path: str, warnings: list[str]
) -> Run:
    """Build the :class:`Run` from what a reader found; refuse a run without metadata or a required stream.

    ``frames`` maps stream name to its canonical table (streams absent from the file are absent from the map).
    """
    if meta_values is None:
        raise RunFormatError(
            "no run metadata (an MCAP metadata record named 'run' or run.json)", path=path, stream="metadata"
        )
    for stream in REQUIRED_STREAMS:
        df = frames.get(stream)
        if df is None:
            raise RunFormatError("required stream is missing", path=path, stream=stream)
        if df.height == 0:
            raise RunFormatError("required stream has no samples", path=path, stream=stream)
    checked = {name: check_stream(name, df, path=path, warnings=warnings) for name, df in frames.items()}
    meta = RunMeta.from_strings(meta_values, path=path)
    return Run(
        meta=meta,
        voltmeter=checked["voltmeter"],
        au_temperature=checked["au_temperature"],
        chamber=checked.get("chamber"),
        fixture=checked.get("fixture"),
        source=path,
        warnings=warnings,
    )


def writable_streams(run: Run, *, path: str) -> dict[str, pl.DataFrame]:
    """The run's stream tables in canonical column order and dtypes, checked for writing.

    Required streams must be present; times must be present, non-negative and in order (docs/log-format.md).
    """
    out = {}
    for stream in REQUIRED_STREAMS:
        if run.stream(stream) is None:
            raise RunFormatError("cannot write a run without this required stream", path=path, stream=stream)
    for stream, df in run.streams().items():
        spec = STREAM_COLUMNS[stream]
        missing = [c for c in spec if c not in df.columns]
        if missing:
            raise RunFormatError(f"stream table lacks columns {missing}", path=path, stream=stream)
        try:
            df = df.select([pl.col(c).cast(dtype, strict=True) for c, dtype in spec.items()])
        except pl.exceptions.PolarsError as exc:
            raise RunFormatError(
                f"stream table has columns of the wrong type ({exc})", path=path, stream=stream
            ) from None
        t = df["t_ns"]
        if t.null_count():
            raise RunFormatError("t_ns has nulls", path=path, stream=stream)
        if (t < 0).any():
            raise RunFormatError("t_ns before the Unix epoch", path=path, stream=stream)
        if not t.is_sorted():
            raise RunFormatError("samples are not in time order", path=path, stream=stream)
        out[stream] = df
    return out
