"""The checks both run layouts share (docs/log-format.md), so that MCAP and Parquet accept and refuse exactly the same
runs.

Stream tables in canonical form, time order and time base, gaps, fixture labels, required streams and metadata:
:func:`assemble_run` turns what a reader decoded into a :class:`pipeline.run.Run`; :func:`writable_streams` checks a
run before a writer writes it.
"""

from __future__ import annotations

import math
import re

import numpy as np
import polars as pl

from pipeline.errors import RunFormatError
from pipeline.positions import MOVING, POSITION_NAMES
from pipeline.run import (
    NS_PER_S,
    PER_UNIT_STREAMS,
    REQUIRED_STREAMS,
    SLAB_SAMPLES,
    STREAM_COLUMNS,
    UNITS_KEY,
    Run,
    RunMeta,
    UnitRuns,
    listed_units,
    slab_of,
    unit_meta_values,
)

#: Labels a fixture event may carry (docs/log-format.md).
FIXTURE_LABELS: tuple[str, ...] = (*POSITION_NAMES, MOVING)
#: An interval longer than this many median intervals of a stream is a gap (warned about by the readers, listed by
#: ``inspect``).
GAP_FACTOR = 5.0
#: A sampled stream whose time jumps forward by more than this is refused: a clock error, or two recordings in one
#: file (the segmenter works on the whole time span, so one sample stamped 1970 must not stretch it to decades).
MAX_JUMP_S = 86_400.0
#: The times a sample may carry, ns since the Unix epoch: 1970-01-01 .. 2116-02-20 (2**62 ns). Outside, a time is
#: not a recording's (a -2**63 placeholder, a clock never set); and differences of two such times stay far from
#: int64 overflow.
T_NS_RANGE = (0, 2**62)
#: A thermosensor glitch (:func:`_isolated_readings_missing`): readings lasting at most GLITCH_MAX_S (s, from the
#: first to the last: one reading always qualifies) that depart from the readings around them by more than GLITCH_C
#: plus GLITCH_C_PER_S times the time between those (C, C/s: no case follows its chamber faster than 15 C/min, and a
#: thermosensor's noise is hundredths of a C) and come back, or that begin or end the record. At most
#: GLITCH_MAX_JUMPS stretches between jumps in a row (glitch values that differ among themselves: 85 C then 60 C).
GLITCH_MAX_S = 10.0
GLITCH_MAX_JUMPS = 4
GLITCH_C = 5.0
GLITCH_C_PER_S = 0.25
#: The refusal of a sampled stream that holds two samples with one time and different values.
SAME_TIME = "two different samples at the same time"
#: What a sample of each value column can physically be; a value outside (e.g. 1e308 C) is treated as missing
#: (NaN, as a non-finite sample is) with a warning naming the first such sample. Temperatures in C (absolute zero ..
#: 1000 C), outputs in V or m/s^2.
PHYSICAL_RANGE: dict[str, tuple[float, float]] = {
    "temp_c": (-273.15, 1000.0),
    "setpoint_c": (-273.15, 1000.0),
    "air_c": (-273.15, 1000.0),
    "ux": (-1e6, 1e6),
    "uy": (-1e6, 1e6),
    "uz": (-1e6, 1e6),
}


def check_streams(
    frames: dict[str, pl.DataFrame],
    *,
    path: str,
    warnings: list[str],
    label=None,
    left_out: list[tuple[str, int, int]] | None = None,
) -> dict[str, pl.DataFrame]:
    """Each stream of ``frames`` (name -> table) checked by :func:`check_stream`; returns them in time order.

    Gaps are warned about once for all the streams: one line per set of streams whose gaps coincide (a logger that
    stopped: ``voltmeter, au_temperature, chamber: 1 gap(s) ...``), so a stream is named in one gap line at most.
    ``label(stream)`` names a stream (default: its name; one unit's streams of a run with several units carry the
    unit). ``left_out``: where :func:`check_stream` adds the stretches it sets to NaN as stuck or clipped."""
    spans: dict[str, np.ndarray] = {}
    checked = {
        name: check_stream(
            name, df, path=path, warnings=warnings, label=label(name) if label else None, gaps=spans, left_out=left_out
        )
        for name, df in frames.items()
    }
    warnings.extend(gap_lines(spans))
    return checked


def gap_lines(spans: dict[str, np.ndarray]) -> list[str]:
    """The readers' gap warnings: ``spans`` maps a stream's label to its gaps ((k, 2) int64 ns: the last sample
    before, the first after). Streams whose gaps coincide (as many, each overlapping) share one line. A gap is
    missing data: nothing is made across it (segmentation says which plateau or position it took)."""
    groups: list[list[str]] = []
    for name, g in spans.items():
        for group in groups:
            h = spans[group[0]]
            if len(h) == len(g) and bool(np.all((g[:, 0] < h[:, 1]) & (h[:, 0] < g[:, 1]))):
                group.append(name)
                break
        else:
            groups.append([name])
    from pipeline.utc import utc_span

    out = []
    for group in groups:
        g = spans[group[0]]
        a, b = (int(x) for x in g[int(np.argmax(g[:, 1] - g[:, 0]))])
        out.append(
            f"{', '.join(group)}: {len(g)} gap(s) without samples, the longest {(b - a) / 1e9:.1f} s after "
            f"t_ns={a} ({utc_span(a, b)}): missing data, nothing is made across a gap"
        )
    return out


def check_stream(
    stream: str,
    df: pl.DataFrame,
    *,
    path: str,
    warnings: list[str],
    label: str | None = None,
    gaps: dict[str, np.ndarray] | None = None,
    left_out: list[tuple[str, int, int]] | None = None,
) -> pl.DataFrame:
    """Check a stream table read from a file; return it in time order.

    ``df`` must already hold the canonical columns and dtypes. Null times and unknown fixture labels are errors;
    samples out of time order are sorted (stable) with a warning. In the sampled streams (all but ``fixture``),
    repeated samples (same ``t_ns``, same values) are dropped with a warning, while two different samples at one
    ``t_ns`` or a jump forward by more than :data:`MAX_JUMP_S` are errors; gaps are warned about. Non-finite values
    are kept. ``label`` names the stream in errors and warnings (default: ``stream``; one unit's stream of a run with
    several units is named with its unit). ``gaps``: where to put the stream's gaps (``gaps[label]``, see
    :func:`gap_lines`) when it has any; without it they are warned about here. ``left_out``: where to add the
    stretches of the voltmeter's and the thermosensor's columns (:data:`STUCK_CHECKED`) set to NaN as stuck or
    clipped (:func:`_stuck_missing`), (column, first ns, last ns) each (:attr:`pipeline.run.Run.left_out_ns`).
    """
    label = label or stream
    t = df["t_ns"]
    if t.null_count():
        row = t.is_null().arg_max() or 0  # None only for an empty column
        raise RunFormatError("t_ns is missing (null)", path=path, stream=label, where=f"row {row}")
    if df.height:
        outside = (t < T_NS_RANGE[0]) | (t >= T_NS_RANGE[1])
        if outside.any():
            row = int(outside.arg_max() or 0)
            raise RunFormatError(
                f"t_ns={t[row]} is not a time of a recording (nanoseconds since 1970-01-01, before 2116): a "
                "placeholder or a clock never set",
                path=path,
                stream=label,
                where=f"row {row}",
            )
    df = _impossible_values_missing(label, df, warnings)
    stepped_back = ""  # where the times went back, for an error that sorting them leads to
    if not t.is_sorted():
        t_ns = t.to_numpy()
        # a sample is out of order when an earlier row has a later time (a clock stepped back: every sample
        # until it catches up, not only the first)
        behind = np.maximum.accumulate(t_ns[:-1]) - t_ns[1:]
        back = behind > 0
        row = int(back.argmax()) + 1
        df = df.sort("t_ns", maintain_order=True)
        warnings.append(
            f"{label}: {int(np.count_nonzero(back))} samples were out of time order (first at row {row}: "
            f"t_ns={t_ns[row]} after t_ns={t_ns[row - 1]}; up to {behind.max() / 1e9:.6g} s before an earlier "
            "row's time); sorted by t_ns"
        )
        # the clock was set back by how much earlier than due the sample came: its time against the one before
        # plus the stream's interval (a 2-s set-back of a 10-Hz stream puts 49.9 s before 48.0 s: 2 s, not 1.9 s)
        step_ns = median_interval_ns(df["t_ns"].to_numpy())
        due_ns = int(t_ns[row - 1]) + round(step_ns)
        stepped_back = (
            f"the times go back at row {row} (t_ns={t_ns[row]} after t_ns={t_ns[row - 1]}, where t_ns={due_ns} was "
            f"due at the stream's {step_ns / 1e9:.6g}-s interval): a clock set back {(due_ns - t_ns[row]) / 1e9:.6g} "
            f"s ({(due_ns - t_ns[row]) / step_ns:.6g} sample intervals), or a block written again with other values"
        )
    if stream != "fixture" and df.height > 1:
        df, spans = _check_time_base(label, df, path=path, warnings=warnings, stepped_back=stepped_back)
        if spans.size:
            if gaps is None:
                warnings.extend(gap_lines({label: spans}))
            else:
                gaps[label] = spans
    if stream == "au_temperature" and df.height > 2:
        df = _isolated_readings_missing(label, df, warnings)
    if stream in STUCK_CHECKED and df.height > 1:
        df = _stuck_missing(label, df, warnings, [] if left_out is None else left_out, *STUCK_CHECKED[stream])
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


def _isolated_readings_missing(stream: str, df: pl.DataFrame, warnings: list[str]) -> pl.DataFrame:
    """Thermosensor glitches set to NaN (missing), with one warning naming how many and the first (row, t_ns,
    value): readings lasting at most :data:`GLITCH_MAX_S` (s, from the first of them to the last) that lie beyond
    both readings around them, on one side, by more than the temperature can move between those two
    (:data:`GLITCH_C` plus :data:`GLITCH_C_PER_S` times the time between them, s), while those two agree within
    that. At the record's first or last readings (a DS18B20's 85 C power-on value is its first) there is one
    reading beside them: they lie beyond it by more than the temperature can move from the first of them to it,
    and it agrees with the reading after it. A sensor's power-on or bus-error value (85 C, -127 C) read once in a
    soak would otherwise split its plateau. A glitch has no more readings than the stretch before it or after it
    (the readings between two glitches a few seconds apart are not one). The candidates are the stretches between
    jumps (consecutive readings further apart than the temperature can move), up to :data:`GLITCH_MAX_JUMPS` of
    them in a row (glitch values that differ among themselves). ``df`` is sorted by time; non-finite readings are
    skipped (the readings around a glitch are the finite ones). Vectorised over the candidates."""
    finite = np.flatnonzero(np.isfinite(df["temp_c"].to_numpy()))
    y = df["temp_c"].to_numpy()[finite]
    t_s = df["t_ns"].to_numpy()[finite] / NS_PER_S
    glitch = np.zeros(y.size, dtype=bool)
    if y.size >= 3:
        jump = np.abs(np.diff(y)) > GLITCH_C + GLITCH_C_PER_S * np.diff(t_s)
        # stretches between jumps: readings edge[m] + 1 .. edge[m + 1] (the record's ends as edges -1 and size - 1)
        edge = np.concatenate(([-1], np.flatnonzero(jump), [y.size - 1]))
        lo_seg = np.minimum.reduceat(y, edge[:-1] + 1)
        hi_seg = np.maximum.reduceat(y, edge[:-1] + 1)
        jump_at = np.append(jump, False)  # jump_at[i]: y[i] and y[i + 1] are a jump (False past the end)
        for k in range(1, min(GLITCH_MAX_JUMPS, edge.size - 2) + 1):
            first, last = edge[:-k] + 1, edge[k:]  # the candidate: readings first .. last
            lo = np.lib.stride_tricks.sliding_window_view(lo_seg, k).min(axis=1)
            hi = np.lib.stride_tricks.sliding_window_view(hi_seg, k).max(axis=1)
            before, after = first - 1, last + 1  # -1 at the start, size at the end
            has_b, has_a = before >= 0, after < y.size
            b, a = np.clip(before, 0, y.size - 1), np.clip(after, 0, y.size - 1)
            short = t_s[last] - t_s[first] <= GLITCH_MAX_S
            # no longer than the stretches beside it (two glitches 5 s apart: the readings between them are not one)
            count = last - first + 1
            seg_n = np.diff(edge)  # readings per stretch between jumps
            m = np.arange(first.size)
            short &= count <= np.where(m >= 1, seg_n[np.maximum(m - 1, 0)], count)
            short &= count <= np.where(m + k < seg_n.size, seg_n[np.minimum(m + k, seg_n.size - 1)], count)
            # inside: beyond both readings around it, which agree
            limit = GLITCH_C + GLITCH_C_PER_S * (t_s[a] - t_s[b])
            inside = has_b & has_a
            inside &= (lo - np.maximum(y[b], y[a]) > limit) | (np.minimum(y[b], y[a]) - hi > limit)
            inside &= np.abs(y[a] - y[b]) <= limit
            # at the start: beyond the reading after it, which agrees with the next one
            lim_a = GLITCH_C + GLITCH_C_PER_S * (t_s[a] - t_s[first])
            start = ~has_b & has_a & ((lo - y[a] > lim_a) | (y[a] - hi > lim_a)) & ~jump_at[a]
            start &= a + 1 < y.size
            # at the end: beyond the reading before it, which agrees with the one before that
            lim_b = GLITCH_C + GLITCH_C_PER_S * (t_s[last] - t_s[b])
            end = has_b & ~has_a & ((lo - y[b] > lim_b) | (y[b] - hi > lim_b)) & (b >= 1) & ~jump_at[b - 1]
            for c in np.flatnonzero(short & (inside | start | end)).tolist():  # the few glitches found
                glitch[first[c] : last[c] + 1] = True
    if not glitch.any():
        return df
    rows = finite[glitch]
    row = int(rows[0])
    warnings.append(
        f"{stream}: {rows.size} reading(s) of temp_c that leave the readings around them and come back, or begin or "
        f"end the record away from the readings beside them (a glitch: "
        f"more than {GLITCH_C:g} C plus {GLITCH_C_PER_S:g} C/s) treated as missing; the first at "
        f"t_ns={df['t_ns'][row]} (row {row}): {df['temp_c'][row]!r}"
    )
    bad = np.zeros(df.height, dtype=bool)
    bad[rows] = True
    return df.with_columns(pl.when(pl.Series(bad)).then(float("nan")).otherwise(pl.col("temp_c")).alias("temp_c"))


def _impossible_values_missing(stream: str, df: pl.DataFrame, warnings: list[str]) -> pl.DataFrame:
    """Values outside :data:`PHYSICAL_RANGE` set to NaN (missing), with one warning per column naming how many and
    the first (row, t_ns, value)."""
    for col, (lo, hi) in PHYSICAL_RANGE.items():
        if col not in df.columns:
            continue
        v = df[col]
        bad = v.is_finite() & ((v < lo) | (v > hi))  # (polars orders NaN above every number)
        n = int(bad.sum())
        if not n:
            continue
        row = int(bad.arg_max() or 0)
        warnings.append(
            f"{stream}: {n} sample(s) of {col} outside what it can be ({lo:g}..{hi:g}) treated as missing; the "
            f"first at t_ns={df['t_ns'][row]} (row {row}): {v[row]!r}"
        )
        df = df.with_columns(pl.when(pl.Series(bad)).then(float("nan")).otherwise(pl.col(col)).alias(col))
    return df


def _intervals(t_ns: np.ndarray):
    """``(offset, np.diff(t_ns[offset:offset + SLAB_SAMPLES + 1]))`` over the whole array: no temporary the length of a
    stream (at 1 kHz one is 0.5 GB, and every fresh one costs page faults)."""
    for a in range(0, t_ns.size - 1, SLAB_SAMPLES):
        yield a, np.diff(t_ns[a : a + SLAB_SAMPLES + 1])


def median_interval_ns(t_ns: np.ndarray) -> float:
    """The median interval (ns) of the sorted times ``t_ns``, from at most ~100 000 intervals (0 with fewer than two
    times)."""
    n = t_ns.size - 1
    if n < 1:
        return 0.0
    k = np.arange(0, n, max(1, n // 100_000))
    return float(np.median(t_ns[k + 1] - t_ns[k]))


def gap_indices(t_ns: np.ndarray) -> np.ndarray:
    """Indices ``i`` of the sorted times ``t_ns`` after which comes a gap: ``t_ns[i + 1] - t_ns[i]`` longer than
    :data:`GAP_FACTOR` median intervals (:func:`median_interval_ns`)."""
    median_ns = median_interval_ns(t_ns)
    if not median_ns > 0:
        return np.empty(0, dtype=np.intp)
    limit = np.int64(math.floor(GAP_FACTOR * median_ns))  # integer comparison: no float copy of the intervals
    return np.concatenate([a + np.flatnonzero(dt > limit) for a, dt in _intervals(t_ns)])


def _check_time_base(
    stream: str, df: pl.DataFrame, *, path: str, warnings: list[str], stepped_back: str = ""
) -> tuple[pl.DataFrame, np.ndarray]:
    """Jumps (error), repeated samples (dropped) and gaps (returned: (k, 2) int64 ns, the last sample before each and
    the first after) of a sampled stream sorted by time. ``stepped_back``: where the times of the stream as read went
    back (it was sorted here), said in the refusal of two different samples at one time; without it the rows are
    the file's. Slab by slab
    (:data:`SLAB_SAMPLES`): the only arrays the length of the stream are the times and, when samples repeat, one
    byte a row to drop them (104 M identical rows once made four more copies of the table)."""
    t_ns = df["t_ns"].to_numpy()
    jump_ns = np.int64(MAX_JUMP_S * 1e9)
    values = [df[c] for c in df.columns if c != "t_ns"]
    keep: np.ndarray | None = None
    n_same, first_same = 0, -1
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
        same = np.flatnonzero(dt == 0)  # rows a + same + 1 have the time of the row before
        if not same.size:
            continue
        equal = np.ones(same.size, dtype=bool)
        for col in values:
            x = slab_of(col, a, a + dt.size + 1)
            u, v = x[same], x[same + 1]
            equal &= (u == v) | (np.isnan(u) & np.isnan(v))
        if not equal.all():
            k = a + int(same[~equal][0]) + 1
            why = stepped_back or (
                f"the time does not advance at row {k} (t_ns={t_ns[k]} twice): stamps coarser than the sampling, "
                "or a clock held back"
            )
            raise RunFormatError(f"{SAME_TIME}: {why}", path=path, stream=stream, where=f"t_ns={t_ns[k]}")
        if keep is None:
            keep = np.ones(t_ns.size, dtype=bool)
            first_same = a + int(same[0]) + 1
        keep[a + same + 1] = False
        n_same += same.size
    if keep is not None:
        warnings.append(
            f"{stream}: dropped {n_same} repeated samples (same t_ns and values as the one before), "
            f"first at t_ns={t_ns[first_same]}"
        )
        df = df.filter(pl.Series(keep))
        t_ns = t_ns[keep]
    gaps = gap_indices(t_ns)
    return df, np.stack([t_ns[gaps], t_ns[gaps + 1]], axis=1)


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
    left_out: list[tuple[str, int, int]] = []
    checked = check_streams(frames, path=path, warnings=warnings, left_out=left_out)
    refuse_dead_channel(checked["voltmeter"], meta_values.get("unit_serial"), path=path, stream="voltmeter")
    meta = RunMeta.from_strings(meta_values, path=path)
    warnings.extend(_plausible(meta, checked, path, "au_temperature"))
    return Run(
        meta=meta,
        voltmeter=checked["voltmeter"],
        au_temperature=checked["au_temperature"],
        chamber=checked.get("chamber"),
        fixture=checked.get("fixture"),
        source=path,
        warnings=warnings,
        left_out_ns=tuple(left_out),
    )


def _plausible(meta: RunMeta, checked: dict[str, pl.DataFrame], path: str, temperature_label: str) -> list[str]:
    """The metadata's plausibility findings (:func:`pipeline.plausibility.check_run_metadata`: ``implausible: ...``
    warnings); RunFormatError when the thermosensor has no finite sample (nothing a run is for can be done)."""
    from pipeline.plausibility import check_run_metadata

    temp = checked["au_temperature"]["temp_c"]
    if not temp.is_finite().any():
        raise RunFormatError(
            f"no finite temperature: all {temp.len()} samples are missing (NaN, or beyond what a temperature can be)",
            path=path,
            stream=temperature_label,
        )
    return check_run_metadata(meta, checked)


def assemble_units(
    meta_values: dict[str, str] | None,
    shared: dict[str, pl.DataFrame],
    per_unit: dict[str, dict[str, pl.DataFrame]],
    *,
    path: str,
    warnings: list[str],
    stream_label,
    only: set[str] | None = None,
) -> UnitRuns:
    """Build the :class:`UnitRuns` of a run with several units (log-format.md) from what a reader found.

    ``shared``: the shared streams (``chamber``, ``fixture``), checked once; ``per_unit``: each unit's own streams
    (``voltmeter``, ``au_temperature``) by serial. ``stream_label(serial, stream)`` names a unit's stream as the
    layout does (the MCAP topic, or the Parquet file and unit). ``only``: the units wanted (the reader decoded no
    others). Whole-run problems (no metadata, no ``units`` key, ``unit_serial`` beside it, a bad shared stream) are
    a RunFormatError; a unit's own problem fails that unit alone, with a one-line reason naming the file, the stream
    and the time: listed in ``units`` without samples, a required stream of its own missing or empty, a stream
    refused by :func:`check_stream`, a dead channel (:func:`dead_channels`), a bad metadata override; samples of a
    unit ``units`` does not list. Warnings of a unit's streams name the unit. ``warnings`` (the reader's: a truncated
    file, ignored topics) and those of the shared streams are the run's and each unit's: a unit's passport says what
    a single-unit run's would.
    """
    if meta_values is None:
        raise RunFormatError(
            "no run metadata (an MCAP metadata record named 'run' or run.json)", path=path, stream="metadata"
        )
    try:
        serials = listed_units(meta_values)
    except RunFormatError as e:
        raise RunFormatError(e.message, path=path, stream="metadata") from None
    if serials is None:
        raise RunFormatError(
            f"the file has streams of units {', '.join(sorted(per_unit))} but its metadata has no {UNITS_KEY!r} key",
            path=path,
            stream="metadata",
        )
    if "unit_serial" in meta_values:
        raise RunFormatError(
            f"metadata has both 'unit_serial' and {UNITS_KEY!r}: a run holds one unit or lists several",
            path=path,
            stream="metadata",
        )
    checked = check_streams(shared, path=path, warnings=warnings)
    whole_run = list(warnings)  # what holds for every unit, before the units' own are added
    units: dict[str, Run] = {}
    failed: dict[str, str] = {}
    for serial in serials:
        if only is not None and serial not in only:
            continue
        frames = per_unit.get(serial, {})
        if not any(df.height for df in frames.values()):
            failed[serial] = RunFormatError(
                f"unit {serial} is listed in the metadata's {UNITS_KEY!r} but the file has no samples of it",
                path=path,
                stream=stream_label(serial, "voltmeter"),
            ).one_line()
            continue
        try:
            units[serial] = _unit_run(
                meta_values, serial, serials, frames, checked, path, warnings, stream_label, whole_run
            )
        except RunFormatError as e:
            failed[serial] = e.one_line()
    for serial in sorted(per_unit.keys() - set(serials)):
        if only is None or serial in only:
            first = min(int(df["t_ns"].to_numpy().min()) for df in per_unit[serial].values() if df.height)
            failed[serial] = RunFormatError(
                f"samples of unit {serial}, which the metadata's {UNITS_KEY!r} does not list "
                f"({meta_values.get(UNITS_KEY)!r})",
                path=path,
                stream=stream_label(serial, "voltmeter"),
                where=f"t_ns={first}",
            ).one_line()
    return UnitRuns(units, failed, several=True, meta_values=dict(meta_values), source=path, warnings=warnings)


def _unit_run(meta_values, serial, serials, frames, shared, path, warnings, stream_label, whole_run) -> Run:
    """One unit's checked :class:`Run` (see :func:`assemble_units`); its warnings: ``whole_run``'s, then its own."""
    for stream in PER_UNIT_STREAMS:
        df = frames.get(stream)
        what = "thermosensor" if stream == "au_temperature" else "voltmeter"
        if df is None or df.height == 0:
            raise RunFormatError(
                f"unit {serial} has no {what} samples: it cannot be calibrated",
                path=path,
                stream=stream_label(serial, stream),
            )
    own: list[str] = []
    left_out: list[tuple[str, int, int]] = []
    checked = check_streams(frames, path=path, warnings=own, label=lambda s: stream_label(serial, s), left_out=left_out)
    refuse_dead_channel(checked["voltmeter"], serial, path=path, stream=stream_label(serial, "voltmeter"))
    meta = RunMeta.from_strings(unit_meta_values(meta_values, serial, serials), path=path)
    own += [f"{w} (unit {serial})" for w in _plausible(meta, checked, path, stream_label(serial, "au_temperature"))]
    warnings.extend(own)
    return Run(
        meta=meta,
        voltmeter=checked["voltmeter"],
        au_temperature=checked["au_temperature"],
        chamber=shared.get("chamber"),
        fixture=shared.get("fixture"),
        source=path,
        warnings=whole_run + own,
        left_out_ns=tuple(left_out),
    )


def dead_channels(voltmeter: pl.DataFrame) -> list[str]:
    """The voltmeter channels that carry no signal, one phrase each: no finite sample, or every finite sample the
    same value (a channel that is not connected or stuck reads so; a live one has at least its noise)."""
    out = []
    for c in ("ux", "uy", "uz"):
        col = voltmeter[c]
        finite = col.filter(col.is_finite())
        if finite.len() == 0:
            out.append(f"{c} has no finite sample")
        elif finite.min() == finite.max():
            out.append(f"{c} reads {finite.min()!r} V in every sample")
    return out


def refuse_dead_channel(voltmeter: pl.DataFrame, serial: str | None, *, path: str, stream: str) -> None:
    """Refuse a unit with a dead voltmeter channel (:func:`dead_channels`) in one line naming the file, the stream
    (``stream``, as the layout names it), the unit and the first dead channel: a single-unit run and each unit of a
    run with several alike (its calibration could only fail later, on a plateau whose positions look missing)."""
    dead = dead_channels(voltmeter)
    if dead:
        raise RunFormatError(f"unit {serial or '(no serial)'} has a dead channel: {dead[0]}", path=path, stream=stream)


def index_stretches(idx: np.ndarray, max_step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The sorted sample indices ``idx`` (non-empty) grouped into stretches, a new one wherever the next index is
    more than ``max_step`` further on: ((k, 2) [first, last + 1) indices, how many of ``idx`` each holds)."""
    cut = np.flatnonzero(np.diff(idx) > max_step)
    first, last = idx[np.concatenate(([0], cut + 1))], idx[np.concatenate((cut, [idx.size - 1]))]
    return np.column_stack((first, last + 1)), np.diff(np.concatenate(([0], cut + 1, [idx.size])))


#: Expected number of stretches a live channel repeats one reading for by chance, per channel and record, that
#: :func:`stuck_stretches` may call stuck: the threshold is set so that quantised noise stays below it.
STUCK_FALSE_RATE = 1e-3
#: The fewest consecutive identical samples called stuck, whatever the channel's noise (see :func:`stuck_stretches`).
MIN_STUCK_SAMPLES = 4
#: A channel with more than :data:`MAX_STUCK_STRETCHES` stuck stretches at more than :data:`MAX_STUCK_VALUES`
#: different values is not judged: a fault gives a few stretches (a logger freezing at its last value now and then),
#: or many at one value (0 V, a rail); dozens to thousands at as many values mean the channel's noise lies below its
#: quantisation step in places (a coarse ADC, or averaged readings: every quiet hold one long run at its own value,
#: 36-4196 stretches at 4-2011 values in simulated runs at 5 uV-1 mV steps), which repeats alone cannot tell from
#: stuck (see :func:`stuck_stretches`).
MAX_STUCK_VALUES = 3
MAX_STUCK_STRETCHES = 16


def stuck_stretches(col: pl.Series, interval_s: float = 0.0) -> tuple[np.ndarray, int, float, float]:
    """The stretches where a voltmeter channel ``col`` (V, in time order) repeats one finite value for so many
    consecutive samples that its noise cannot: a channel stuck (at its last value, at 0 V), or clipped at a rail
    (a saturated output reads the rail's value exactly). Returns ((k, 2) [first, end) sample indices, the fewest
    samples called stuck, the channel's highest and lowest finite value).

    The threshold: a live channel's reading changes from one sample to the next unless its noise sigma is within a
    quantisation step q of the voltmeter (a 24-bit voltmeter's LSB repeats: two consecutive readings are equal with
    probability p ~ q / (2 sqrt(pi) sigma) when sigma >> q, p = 0 for unquantised values). p is measured on the
    channel itself: the fraction of consecutive equal pairs outside the runs called stuck (the threshold and p
    found together: a long stuck stretch would otherwise make a live channel look quiet). A run
    of n equal readings then starts at a given sample with probability p**(n - 1), so over the record's N samples
    n_min = 1 + ceil(log(STUCK_FALSE_RATE / N) / log p) keeps the expected number of live runs called stuck below
    :data:`STUCK_FALSE_RATE`; in seconds n_min / rate: e.g. the real recordings' p of 0.03-0.12 (N 1e4-3e5) give
    7-9 samples (7 s at 1 Hz, 0.09 s at 102 Hz) where their longest repeat is 4-6; 5 uV noise on a 24-bit +-1 V
    voltmeter (p ~ 0.007, N = 1e6) 6 samples. At least :data:`MIN_STUCK_SAMPLES` (a logger repeating one reading
    once or twice when a conversion is late is no fault). A channel whose readings are mostly equal (p >= 0.5: its
    noise far below the step) cannot be told stuck from quiet and gives none; nor does one with more than
    :data:`MAX_STUCK_STRETCHES` stretches at more than :data:`MAX_STUCK_VALUES` different values (a 1-mV step with
    5 uV of noise: each quiet hold reads one value for its whole length, so p outside the long runs is tiny and
    every hold would be called stuck). Of the runs left, those the readings beside them explain are dropped
    (:func:`_locally_unlikely`, with the channel's sample interval ``interval_s``, s, 0 if not known: a coarse
    step's p varies from hold to hold with where the signal sits in its bin).
    NaN breaks a run (missing data is the gap and non-finite checks' business). One pass over the column in slabs
    of :data:`SLAB_SAMPLES`."""
    n = col.len()
    m = MIN_STUCK_SAMPLES - 1  # equal pairs in a row that make the shortest run
    found: list[np.ndarray] = []
    equal = 0
    hi, lo = -math.inf, math.inf
    for a in range(0, n, SLAB_SAMPLES):
        x = slab_of(col, a, min(n, a + SLAB_SAMPLES + m))  # pairs a .. a + SLAB_SAMPLES + m - 2
        hi, lo = max(hi, float(np.fmax.reduce(x))), min(lo, float(np.fmin.reduce(x)))
        same = x[1:] == x[:-1]  # NaN is never equal: it breaks a run
        equal += int(np.count_nonzero(same[:SLAB_SAMPLES]))
        w = max(same.size - m + 1, 0)
        run = same[:w].copy()
        for k in range(1, m):
            run &= same[k : w + k]
        found.append(a + np.flatnonzero(run[:SLAB_SAMPLES]))  # samples i .. i + m all equal
    first = np.concatenate(found) if found else np.zeros(0, dtype=np.int64)
    runs = index_stretches(first)[0] + (0, m) if first.size else np.zeros((0, 2), dtype=np.int64)
    length = runs[:, 1] - runs[:, 0]
    n_min = MIN_STUCK_SAMPLES
    for _ in range(8):  # p without the runs called stuck, until the threshold no longer changes
        p = max(equal - int(np.sum(length[length >= n_min] - 1)), 0) / max(n - 1, 1)
        if p >= 0.5:
            return np.zeros((0, 2), dtype=np.int64), n, hi, lo
        was, n_min = n_min, MIN_STUCK_SAMPLES
        if p > 0:
            n_min = max(n_min, 1 + math.ceil(math.log(STUCK_FALSE_RATE / max(n, 1)) / math.log(p)))
        if n_min == was:
            break
    runs = runs[length >= n_min]
    if runs.shape[0] > MAX_STUCK_STRETCHES and np.unique(col.gather(runs[:, 0]).to_numpy()).size > MAX_STUCK_VALUES:
        return np.zeros((0, 2), dtype=np.int64), n, hi, lo
    return runs[_locally_unlikely(col, runs, n, interval_s)], n_min, hi, lo


#: Around a run of one reading, :func:`_locally_unlikely` looks this many times the run's own duration before it
#: and after it (the channel's readings there: the same hold, where its noise sits in the same quantisation bins),
#: and at least :data:`STUCK_WINDOW_S` seconds on each side: f from the 20 readings beside a 10-s freeze at 2 Hz was
#: too rough to judge it by, and a window much longer than a hold's drift through one bin (240 s at 0.5 Hz)
#: averages f down where the hold crosses the middle of v's bin (live runs of 15-20 readings called stuck).
STUCK_WINDOW_RUNS = 1
STUCK_WINDOW_S = 30.0
#: The pooled f needs at least this many times the run's readings near v beside it (:func:`_locally_unlikely`).
STUCK_POOLED_RUNS = 1.5


def _locally_unlikely(col: pl.Series, runs: np.ndarray, n: int, interval_s: float = 0.0) -> np.ndarray:
    """Which of the ``runs`` ((k, 2) [first, end) samples of ``col``, each one reading v repeated, as long as the
    channel-wide threshold of :func:`stuck_stretches` or longer) the channel's own readings next to them do not
    explain. A coarsely quantised channel's chance of repeating v depends on where the signal sits in its bin: a
    quiet hold whose mean lies at the middle of a bin reads that bin's value in a fraction f (68 % at a noise of
    half a step) of its samples, so it repeats it far longer than the channel-wide p (taken over holds whose
    means lie at bin edges, and ramps) predicts (a consumer unit on a 1-mV voltmeter: uy 'stuck' for 2.7 s at
    10 Hz, nothing stuck). f is measured in :data:`STUCK_WINDOW_RUNS` times the run's duration before the run and
    after it, at least :data:`STUCK_WINDOW_S` on each side (``interval_s``: the sample interval, s), both sides
    pooled where their readings near v are at least :data:`STUCK_POOLED_RUNS` times the run's (the larger of two
    sides of 20 readings each biased f upward: 10-s freezes at 2 Hz kept as live; with fewer, a short hold or a
    low rate, the larger side's f), other runs called stuck left out: among the finite readings within a
    quantisation step of v (v's bin and the two beside it: a hold's readings, not those of a ramp far from v),
    the fraction at v, with one reading at v and one beside it added ((k + 1) / (m + 2): a margin for the few
    dozen readings beside a run in a short hold, and 2 of 2 on a ramp crossing v is not certainty). A run of L
    readings is unlikely when L >= 1 + ceil(log(STUCK_FALSE_RATE / N) / log f), the channel-wide rule with the
    local f. A channel frozen at its last value, at 0 V or at a rail reads v rarely or never beside the frozen
    stretch (f about 1/3 at most, for a 24-bit voltmeter: a threshold of ~20 samples, and 0 where no reading is
    near v): still named. One slice per run (the runs are few: at most :data:`MAX_STUCK_STRETCHES` at more than
    :data:`MAX_STUCK_VALUES` values, or many at a few values)."""
    keep = np.ones(runs.shape[0], dtype=bool)
    log_rate = math.log(STUCK_FALSE_RATE / max(n, 1))
    w_min = math.ceil(STUCK_WINDOW_S / interval_s) if interval_s > 0 else 0  # samples
    values = col.gather(runs[:, 0]).to_numpy() if runs.size else np.zeros(0)
    for k, (a, b) in enumerate(runs.tolist()):
        w = max(STUCK_WINDOW_RUNS * (b - a), w_min)
        at, near, f_side = 0, 0, 0.0  # readings at v and within a step of it, both sides pooled; the larger side's f
        for s0, s1 in ((max(0, a - w), a), (b, min(n, b + w))):
            x = slab_of(col, s0, s1).copy()
            # the other runs in the window (the rest of a stretch frozen around a NaN or a glitch) are left out
            for j in range(int(np.searchsorted(runs[:, 1], s0, "right")), int(np.searchsorted(runs[:, 0], s1))):
                if j != k:
                    x[max(runs[j, 0], s0) - s0 : min(runs[j, 1], s1) - s0] = np.nan
            x = x[np.isfinite(x)]
            if x.size < 2:
                continue
            # the readings within one quantisation step of v (its bin and the two beside it: < 1.5 steps off; the
            # step: the smallest change between consecutive readings there), not a ramp's readings far from it
            dx = np.abs(np.diff(x))
            step = np.fmin.reduce(np.where(dx > 0, dx, np.inf))
            off = np.abs(x - values[k])
            m_side, k_side = int(np.count_nonzero(off < 1.5 * step)), int(np.count_nonzero(off == 0))
            near, at = near + m_side, at + k_side
            if m_side:  # one more reading at v than seen: a margin for the few readings of a short hold
                f_side = max(f_side, (k_side + 1) / (m_side + 2))
        # pooled where the readings near v outnumber the run STUCK_POOLED_RUNS times; else (a short hold, a low
        # rate) the larger side's f, which a few readings at v on one side make larger
        f = (at + 1) / (near + 2) if near >= STUCK_POOLED_RUNS * (b - a) else f_side
        if f > 0 and b - a < 1 + math.ceil(log_rate / math.log(f)):
            keep[k] = False
    return keep


#: How a stuck or clipped channel's warning ends (:func:`stuck_clauses` finds them by it).
STUCK_LEFT_OUT = "treated as missing (no hold in them is used)"


def stuck_clauses(warnings: list[str]) -> list[str]:
    """The stuck and clipped channels' warnings (:func:`_stuck_missing`) among ``warnings``, each shortened to its
    stream, channel, stretches and time in all (``voltmeter.parquet unit AU-0302: uy stuck in 1 stretch(es),
    11811.0 s in all``): what a refusal adds when a unit has too little left."""
    return [
        re.sub(r" \([^()]*\)", "", w.split(": the first at ")[0])
        for w in dict.fromkeys(warnings)
        if w.endswith(STUCK_LEFT_OUT)
    ]


#: The streams whose columns are checked for stuck and clipped stretches (:func:`_stuck_missing`): their columns
#: and the unit of their values. The thermosensor too: frozen for an hour while the chamber ramps, it would make a
#: plateau that is not there (for it, only runs it leaves by a jump, :func:`_thermosensor_frozen`; no rails).
STUCK_CHECKED: dict[str, tuple[tuple[str, ...], str]] = {
    "voltmeter": (("ux", "uy", "uz"), "V"),
    "au_temperature": (("temp_c",), "C"),
}

#: Readings at a rail at most this many samples apart belong to one clipped stretch (see :func:`rail_stretches`).
RAIL_GAP_SAMPLES = 32
#: The rail's count must exceed twice the next value's by this many of its Poisson standard deviations (see
#: :func:`rail_stretches`).
RAIL_MARGIN_SIGMAS = 3.0


def rail_stretches(col: pl.Series, rail_v: float, n_min: int) -> tuple[np.ndarray, int, int]:
    """Where a voltmeter channel ``col`` reads its highest (or lowest) value ``rail_v`` (V) as an output clipped at a
    rail does: ((k, 2) [first, end) sample indices, how many samples read ``rail_v``, how many the next value
    inwards). A rail piles every reading beyond it onto one value, so a hold whose signal lies at the rail within
    its noise reads ``rail_v`` in many samples with others between (no run long enough for
    :func:`stuck_stretches`, yet its mean is biased); a live channel's readings thin out towards its extreme, the
    extreme value read fewer times than the next one inwards. Called clipped: ``rail_v`` read by at least ``n_min``
    samples (the stuck threshold) and by more than twice as many (k) as the next value inwards (j), by
    :data:`RAIL_MARGIN_SIGMAS` of the counts' Poisson standard deviation: k - 2 j >= 3 sqrt(k + 4 j). A coarse step
    (noise half a step) makes a live hold whose mean sits in the channel's top bin read it about twice as often as
    the next (a 62-s +1 g hold at 0.5 Hz, 10-uV steps: 21 and 10, called a rail by the bare factor 2); a hold at a
    rail reads it in half its samples and the next value rarely (60 against 1: 60 - 2 >= 24). A stretch runs from the
    first to the last of a group of >= ``n_min`` such samples each within :data:`RAIL_GAP_SAMPLES` of the next, the
    readings between included: leaving out only the clipped readings would keep a hold's readings below the rail
    and bias its mean the other way. A hold whose mean lies d sigma inside the rail reads it in a fraction
    1 - Phi(d) of its samples (16 % at d = 1: one group; 2.3 % at d = 2, where its mean is biased by only
    sigma (phi(d) - d (1 - Phi(d))) = 0.008 sigma, kept or not). One pass in slabs."""
    n = col.len()
    found = sum(
        int(np.count_nonzero(slab_of(col, a, min(n, a + SLAB_SAMPLES)) == rail_v)) for a in range(0, n, SLAB_SAMPLES)
    )
    if found < n_min:  # a live channel's extreme: the usual case, one cheap pass
        return np.zeros((0, 2), dtype=np.int64), found, 0
    at: list[np.ndarray] = []
    found = 0
    nxt, n_nxt = math.nan, 0
    upper = None
    for a in range(0, n, SLAB_SAMPLES):
        x = slab_of(col, a, min(n, a + SLAB_SAMPLES))
        hit = np.flatnonzero(x == rail_v)
        at.append(a + hit)
        found += hit.size
        if upper is None:
            upper = bool(np.fmax.reduce(x) <= rail_v) if x.size else True
        rest = x[x < rail_v] if upper else x[x > rail_v]
        if not rest.size or np.isnan(rest).all():
            continue
        v = float(np.fmax.reduce(rest)) if upper else float(np.fmin.reduce(rest))
        k = int(np.count_nonzero(rest == v))
        if math.isnan(nxt) or (v > nxt if upper else v < nxt):
            nxt, n_nxt = v, k
        elif v == nxt:
            n_nxt += k
    if found < n_min or found - 2 * n_nxt < RAIL_MARGIN_SIGMAS * math.sqrt(found + 4 * n_nxt):
        return np.zeros((0, 2), dtype=np.int64), found, n_nxt
    runs, size = index_stretches(np.concatenate(at), max(RAIL_GAP_SAMPLES, n_min))
    return runs[size >= n_min], found, n_nxt


def _thermosensor_frozen(
    col: pl.Series, t_ns: pl.Series, runs: np.ndarray, values: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Of a thermosensor's stuck ``runs`` ((k, 2) [first, end) readings of ``col``, C, at ``values``), those it
    left by a jump the temperature cannot make (:func:`_isolated_readings_missing`'s :data:`GLITCH_C` plus
    :data:`GLITCH_C_PER_S` times the time from the run's last reading to the next finite one): a sensor frozen
    while the chamber moved, which would make a plateau that is not there. A quiet plateau read in coarse steps
    (0.0625 C: one value for minutes, the extreme one at the coldest plateau) ends a step away, and a run at the
    record's end has no reading after it: neither is named (neither makes a plateau that is not there)."""
    keep = np.zeros(runs.shape[0], dtype=bool)
    n = col.len()
    for k, b in enumerate(runs[:, 1].tolist()):
        after = slab_of(col, b, min(n, b + SLAB_SAMPLES))
        nxt = np.flatnonzero(np.isfinite(after))
        if nxt.size:
            dt_s = (int(t_ns[b + int(nxt[0])]) - int(t_ns[b - 1])) / 1e9
            keep[k] = abs(float(after[nxt[0]]) - float(values[k])) > GLITCH_C + GLITCH_C_PER_S * dt_s
    return runs[keep], values[keep]


def _stuck_missing(
    label: str,
    df: pl.DataFrame,
    warnings: list[str],
    left_out: list[tuple[str, int, int]],
    columns: tuple[str, ...] = ("ux", "uy", "uz"),
    unit: str = "V",
) -> pl.DataFrame:
    """The stuck stretches (:func:`stuck_stretches`) and stretches clipped at a rail (:func:`rail_stretches`) of the
    ``columns`` (values in ``unit``: the voltmeter's channels in V, the thermosensor's temp_c in C) set to NaN
    (missing: no hold in them is used, as with any non-finite sample; a thermosensor's missing readings leave a
    gap, where no voltmeter sample has a temperature), with one warning per column and kind naming how many, the
    time in all (s), the first and the longest (value, start as t_ns, UTC and seconds from the stream's first
    sample, duration in s). A column that reads one value in every sample is left as it is (a voltmeter's:
    :func:`dead_channels`; a thermosensor at one temperature throughout is a run without a temperature model), and
    so is one whose stretches leave fewer than the threshold's number of live readings (nothing to tell them from).
    The thermosensor (``unit`` C) has no rails and only the stuck runs :func:`_thermosensor_frozen` keeps.
    Each stretch set to NaN is added to ``left_out`` as (column, first ns, last ns)."""
    t_ns = df["t_ns"].to_numpy()
    step_ns = median_interval_ns(t_ns)
    for c in columns:
        col = df[c]
        runs, n_min, hi, lo = stuck_stretches(col, step_ns / NS_PER_S)
        if hi == lo or not math.isfinite(hi):
            continue
        gone: list[np.ndarray] = []
        said: list[str] = []
        values = col.gather(runs[:, 0]).to_numpy()
        if unit == "C":
            runs, values = _thermosensor_frozen(col, df["t_ns"], runs, values)
        for rail_v, side, inwards in ((hi, "highest", "lower"), (lo, "lowest", "higher")) if unit == "V" else ():
            clipped, found, n_next = rail_stretches(col, rail_v, n_min)
            if not clipped.size:
                continue
            runs, values = runs[values != rail_v], values[values != rail_v]
            gone.append(clipped)
            said.append(
                _stretches_line(
                    f"{label}: {c} clipped at {rail_v:.7g} {unit}, its {side} reading ({found} samples read it, "
                    f"{n_next} the next {inwards} value: a rail, where a live channel's readings thin out)",
                    t_ns,
                    clipped,
                    np.full(clipped.shape[0], rail_v),
                    step_ns,
                    unit=unit,
                )
            )
        if runs.size:
            gone.append(runs)
            said.append(
                _stretches_line(
                    f"{label}: {c} stuck (one reading repeated for >= {n_min * step_ns / 1e9:.3g} s, {n_min} "
                    "samples, which its noise does not give)",
                    t_ns,
                    runs,
                    values,
                    step_ns,
                    hi,
                    lo,
                    unit=unit,
                )
            )
        if not gone:
            continue
        both = np.concatenate(gone)
        edge = np.zeros(df.height + 1, dtype=np.int8)
        np.add.at(edge, both[:, 0], 1)
        np.add.at(edge, both[:, 1], -1)
        stuck = np.cumsum(edge[:-1], dtype=np.int32) > 0
        finite = col.is_finite().to_numpy()
        if int(np.count_nonzero(finite & ~stuck)) < n_min:
            # nothing live left to tell the stretches from (a quiet column read coarsely: a 160-s handheld
            # record's thermosensor at 20 C in 0.0625 C steps reads one value but once): not judged, as one
            # value throughout is not
            continue
        warnings.extend(said)
        left_out += [(c, int(t_ns[a]), int(t_ns[b - 1])) for a, b in index_stretches(np.flatnonzero(stuck))[0]]
        df = df.with_columns(pl.when(pl.Series(stuck)).then(float("nan")).otherwise(pl.col(c)).alias(c))
    return df


def _stretches_line(
    head: str,
    t_ns: np.ndarray,
    runs: np.ndarray,
    values: np.ndarray,
    step_ns: float,
    hi: float = math.nan,
    lo: float = math.nan,
    unit: str = "V",
) -> str:
    """One warning about the stretches ``runs`` ((k, 2) [first, end) samples) of a channel: ``head``, how many, the
    time in all, the first and the longest (:func:`stretches_text`; values in ``unit``)."""
    return f"{head} {stretches_text(t_ns, runs, step_ns, values, hi, lo, unit)}; {STUCK_LEFT_OUT}"


def stretches_text(
    t_ns: np.ndarray,
    runs: np.ndarray,
    step_ns: float,
    values: np.ndarray | None = None,
    hi: float = math.nan,
    lo: float = math.nan,
    unit: str = "V",
) -> str:
    """The stretches ``runs`` ((k, 2) [first, end) sample indices into ``t_ns``, one sample lasting ``step_ns``) in
    a warning, in seconds: how many, the time in all, the first and the longest, each with its value when ``values``
    (in ``unit``: V, or C for the thermosensor) are given (:func:`_stuck_text`): ``in 1 stretch(es), 1200.0 s in
    all: the first at 0 V for 1200.0 s from t_ns=... (UTC span, 2900.0 s after the start)``. The one text of
    stretches of a voltmeter channel or the thermosensor: stuck, clipped, or non-finite
    (:func:`pipeline.segment.segment_run`)."""
    step_ns = step_ns if math.isfinite(step_ns) else 0.0
    dur_s = (t_ns[runs[:, 1] - 1] - t_ns[runs[:, 0]] + step_ns) / 1e9
    said = [
        _stuck_text(
            t_ns,
            int(runs[k, 0]),
            int(runs[k, 1]),
            None if values is None else float(values[k]),
            float(dur_s[k]),
            hi,
            lo,
            unit,
        )
        for k in dict.fromkeys((0, int(np.argmax(dur_s))))
    ]
    more = f"; the longest {said[1]}" if len(said) > 1 else ""
    return f"in {runs.shape[0]} stretch(es), {float(dur_s.sum()):.1f} s in all: the first {said[0]}{more}"


def _stuck_text(
    t_ns: np.ndarray, a: int, b: int, value_v: float | None, dur_s: float, hi: float, lo: float, unit: str = "V"
) -> str:
    """One stretch (samples ``a .. b - 1``, at ``value_v`` when given) in a warning: value, a rail when it is the
    channel's highest or lowest (``hi``, ``lo``), duration (s), start (t_ns, UTC, s after the stream's first
    sample)."""
    from pipeline.utc import utc_span

    rail = " (the channel's highest value: clipped at a rail?)" if value_v == hi else ""
    rail = " (the channel's lowest value: clipped at a rail?)" if value_v == lo else rail
    value = "" if value_v is None else f"at {value_v:.7g} {unit}{rail} "
    return (
        f"{value}for {dur_s:.1f} s from t_ns={t_ns[a]} "
        f"({utc_span(int(t_ns[a]), int(t_ns[b - 1]))}, {(t_ns[a] - t_ns[0]) / 1e9:.1f} s after the start)"
    )


def writable_units(runs: UnitRuns, *, path: str) -> tuple[dict[str, pl.DataFrame], dict[str, dict[str, pl.DataFrame]]]:
    """The shared streams and each unit's own streams of a run with several units, checked for writing
    (:func:`writable_streams` per unit)."""
    if not runs.units:
        raise RunFormatError("cannot write a run with several units without a unit", path=path)
    per_unit = {}
    shared: dict[str, pl.DataFrame] = {}
    for serial, run in runs.units.items():
        streams = writable_streams(run, path=path)
        per_unit[serial] = {s: df for s, df in streams.items() if s in PER_UNIT_STREAMS}
        if not shared:
            shared = {s: df for s, df in streams.items() if s not in PER_UNIT_STREAMS}
    return shared, per_unit


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
