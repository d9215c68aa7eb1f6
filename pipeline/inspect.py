"""What a run holds, for ``thermocal inspect``: metadata, per-stream counts, rates, time span, gaps, non-finite
samples; and the plateaus and static positions the segmenter finds.

:func:`summarize_run` returns a JSON-ready dict (plain ints, floats, strings and lists); :func:`format_summary`
renders it as a few lines per stream. A run holding several units: :func:`summarize_units` and :func:`format_units`,
each unit as above.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.calibrate.recording import KIND_WORDS, Recording
from pipeline.errors import ThermocalError
from pipeline.io.checks import GAP_FACTOR, gap_indices  # noqa: F401  (GAP_FACTOR: the gap definition, shared with the readers)
from pipeline.jsonable import to_jsonable
from pipeline.run import Run, UnitRuns
from pipeline.utc import utc_text
from pipeline.words import count_words


def summarize_units(got: UnitRuns | Sequence[tuple[str, UnitRuns]]) -> dict[str, Any]:
    """What a run holding several units holds (JSON-ready): its metadata as in the file, each unit's
    :func:`summarize_run` (poses, plateaus, the methods it supports) in ``units``, segmented once for the run
    (:func:`pipeline.segment_units.segment_units`), the units that failed their input checks with their reasons in
    ``failed``, and the run's warnings (a unit whose signal disagrees with the others' is named there).

    ``got`` may be the files such a run was cut into ([(path, what was read from it)], one run_id): each unit's
    pieces are one recording (:func:`pipeline.calibrate.inputs.unit_recordings`, with its ``files`` as
    :func:`summarize_runs` lists them) and the units of the same files are segmented together, as ``calibrate``
    does (:func:`pipeline.calibrate.inputs.segment_recordings`): the poses and plateaus of the file they were cut
    from. ``metadata`` is then the first file's in time, ``source`` the files in time order; a unit missing from
    one of the pieces (the other units in it) is named first in its ``warnings``, as ``calibrate`` names it
    (:func:`pipeline.calibrate.inputs.absent_from_pieces`)."""
    from pipeline.calibrate.inputs import absent_from_pieces, segment_recordings, unit_recordings, units_span_ns

    read = [(got.source, got)] if isinstance(got, UnitRuns) else list(got)
    absent: dict[str, list[str]] = {}  # a unit missing from one of the pieces: named first, as calibrate names it
    if len(read) > 1:
        span_of = {p: units_span_ns(g) for p, g in read}
        read.sort(key=lambda item: (span_of[item[0]] or (int(np.iinfo(np.int64).max), 0))[0])
        absent = absent_from_pieces(
            [(p, g.meta_values.get("run_id", ""), g.serials) for p, g in read if g.several], span_of.__getitem__
        )
    recordings, unjoined = unit_recordings(read)
    try:
        segs, disagree = segment_recordings(recordings)
    except ThermocalError as exc:
        segs, disagree = {}, [f"segmentation of the run failed: {exc.one_line()}"]
    units = []
    for serial, (run, paths, left_out) in recordings.items():
        unit = summarize_run(run, segs.get(serial))
        if len(read) > 1:
            unit["files"] = _files([r for p, g in read for s, r in g.units.items() if s == serial and p in paths])
            unit["warnings"] = absent.get(serial, []) + left_out + unit["warnings"]
        units.append(unit)
    failed = {u: why for _, g in read for u, why in g.failed.items()}
    failed.update(unjoined)
    several = len(read) > 1
    return {
        "source": " + ".join(p for p, _ in read) if several else read[0][1].source,
        "metadata": dict(read[0][1].meta_values),
        "units": units,
        "failed": [{"unit": u, "reason": why} for u, why in failed.items()],
        "warnings": [*(f"{p}: {w}" if several else w for p, g in read for w in g.warnings), *disagree],
    }


def _files(kept: list[Run]) -> list[dict[str, Any]]:
    """``files`` of a recording of several files: each file's source, run_id, first and last voltmeter time, in
    time order."""
    from pipeline.calibrate.inputs import time_span_ns

    spans = [time_span_ns(r.voltmeter) or (None, None) for r in kept]
    files = [
        {"source": r.source, "run_id": r.meta.run_id, "t_start_ns": a, "t_end_ns": b} for r, (a, b) in zip(kept, spans)
    ]
    files.sort(key=lambda f: (f["t_start_ns"] is None, f["t_start_ns"] or 0))
    return files


def format_units(summary: dict[str, Any]) -> str:
    """Human-readable text of :func:`summarize_units`'s result: the run, then each unit as :func:`format_summary`
    says it (indented), the failed units and the run's warnings."""
    meta = summary["metadata"]
    serials = [u["metadata"]["unit_serial"] for u in summary["units"]] + [f["unit"] for f in summary["failed"]]
    lines = [
        f"run {meta.get('run_id', '?')}  {count_words(len(serials), 'unit')} ({', '.join(serials)})  station "
        f"{meta.get('station') or '-'}  fixture {meta.get('fixture') or '-'}",
    ]
    if summary.get("source"):
        lines.append(f"  source: {summary['source']}")
    for unit in summary["units"]:
        text = format_summary({**unit, "warnings": []})
        lines += ["", f"unit {unit['metadata']['unit_serial']}:"] + ["  " + line for line in text.splitlines()]
    for f in summary["failed"]:
        lines += ["", f"unit {f['unit']}: not usable: {f['reason']}"]
    if summary["warnings"]:
        lines.append("")
    lines += [f"warning: {w}" for w in summary["warnings"]]
    return "\n".join(lines)


def summarize_run(run: Run, seg=None) -> dict[str, Any]:
    """Metadata, per-stream statistics and the segmentation summary of ``run`` (JSON-ready); ``seg``: its
    segmentation, when already made."""
    summary: dict[str, Any] = {
        "source": run.source,
        "metadata": run.meta.to_strings(),
        "streams": {
            name: stream_summary(name, df["t_ns"].to_numpy(), _non_finite(df)) for name, df in run.streams().items()
        },
        "warnings": list(run.warnings),
    }
    if run.fixture is not None:
        summary["streams"]["fixture"]["positions"] = sorted(run.fixture["position"].unique().to_list())
    summary.update(_segmentation_summary(run, seg))
    return summary


def summarize_runs(runs: list[Run]) -> dict[str, Any]:
    """``inspect RUN...``: the runs given together as the one recording a calibration reads
    (:func:`pipeline.calibrate.inputs.select_runs`: copies left out; ``join_runs``: the files in time order as one
    run),
    described by :func:`summarize_run`; with several files, ``files`` lists each one used (source, run_id, first
    and last voltmeter time) and ``warnings`` also says which were left out."""
    from pipeline.calibrate.inputs import join_runs, select_runs

    if len(runs) == 1:
        return summarize_run(runs[0])
    kept, left_out = select_runs(runs)
    recording = join_runs(kept)
    summary = summarize_run(recording)
    summary["files"] = _files(kept)
    summary["warnings"] = left_out + summary["warnings"]
    return summary


def stream_summary(name: str, t_ns: np.ndarray, non_finite: int) -> dict[str, Any]:
    """Sample count, rate (from the median interval), span, gaps (> GAP_FACTOR median intervals) of one stream.

    ``gaps`` is a list of ``[t_ns, length_s]``: where the gap starts (time of the last sample before it) and how long
    the interval is. The fixture log is a list of events, so it has no rate and no gaps.
    """
    n = int(len(t_ns))
    out: dict[str, Any] = {
        "samples": n,
        "rate_hz": None,
        "t_start_ns": None,
        "t_end_ns": None,
        "duration_s": 0.0,
        "gaps": [],
        "non_finite": int(non_finite),
    }
    if n == 0:
        return out
    out["t_start_ns"] = int(t_ns[0])
    out["t_end_ns"] = int(t_ns[-1])
    out["duration_s"] = (int(t_ns[-1]) - int(t_ns[0])) * 1e-9
    if n < 2 or name == "fixture":
        return out
    dt_ns = np.diff(t_ns)
    median_ns = float(np.median(dt_ns))
    if median_ns > 0:
        out["rate_hz"] = 1e9 / median_ns
        idx = gap_indices(t_ns)
        out["gaps"] = [[int(t_ns[i]), float(dt_ns[i]) * 1e-9] for i in idx]
    return out


def _non_finite(df) -> int:
    floats = [c for c, dtype in df.schema.items() if dtype.is_float()]
    return int(sum(np.count_nonzero(~np.isfinite(df[c].to_numpy())) for c in floats))


def _segmentation_summary(run: Run, seg=None) -> dict[str, Any]:
    """``plateaus`` and ``static_positions`` found by :func:`pipeline.segment.segment_run`, and ``recording``: what
    the recording is (:func:`describe_recording`).

    Each plateau and static segment is its dataclass as a JSON-ready dict. In a temperature sweep the drifting
    stretches the plateau test passes piecewise are not plateaus and are not listed. A segmenter error is reported,
    not raised, so that ``inspect`` still shows the streams.
    """
    from pipeline.segment import segment_run

    try:
        result = seg if seg is not None else segment_run(run)
    except ThermocalError as exc:
        return {"plateaus": [], "static_positions": [], "segmentation": f"failed: {exc}"}
    recording = describe_recording(run, result)
    plateaus = recording.pop("_plateaus")
    return {
        "plateaus": to_jsonable(plateaus),
        "static_positions": to_jsonable(result.segments),
        "segmentation": "ok",
        "segmentation_warnings": list(result.warnings),
        "recording": recording,
    }


def describe_recording(run: Run, seg) -> dict[str, Any]:
    """What a recording is, before anything is fitted (JSON-ready): the temperature program (plateaus, sweep or
    constant: range, largest rate), the static poses (count, holds, durations, direction of gravity, which axis is
    vertical, temperatures covered), and for each calibration method (:mod:`pipeline.calibrate.methods`) whether
    the data supports it and which constants it can determine (``methods``, in the order ``auto`` prefers them;
    ``method_auto`` is the one ``calibrate --method auto`` picks).

    ``seg`` is the run's :class:`pipeline.segment.Segmentation`. The key ``_plateaus`` carries the plateaus that are
    soaks (for the caller; not part of the description).
    """
    from pipeline.calibrate.methods import auto_choice, judge

    recording = Recording.of(run, seg)
    program = recording.program
    judged = judge(recording)
    auto = auto_choice(judged)
    lo, hi = program.range_c
    return {
        "temperature": {
            "kind": program.kind,
            "range_c": [_r(lo), _r(hi)],
            "max_rate_c_per_h": _r(program.max_rate_c_per_h),
            "rate_window_s": program.rate_window_s,
            "plateaus": len(program.plateaus),
            "drift_s": round(program.drift_s, 1),
        },
        "static": {
            "window_s": seg.static_window_s,
            "min_s": seg.static_min_s,
            "segments": len(seg.segments),
            "poses": len(recording.poses),
        },
        "poses": [dict(p) for p in recording.poses],
        "methods": [
            {
                "method": m.name,
                "supported": s.supported,
                "why": s.why,
                "determines": list(s.determines),
                **({"insists": s.insists} if s.insists else {}),
            }
            for m, s in judged
        ],
        "method_auto": auto[0].name if auto else None,
        "_plateaus": list(program.plateaus),
    }


def _r(x: float, nd: int = 3):
    return round(float(x), nd) if np.isfinite(x) else None


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable text of :func:`summarize_run`'s result, a few lines per stream."""
    meta = summary["metadata"]
    lines = [
        f"run {meta.get('run_id', '?')}  unit {meta.get('unit_serial', '?')}  station {meta.get('station') or '-'}"
        f"  fixture {meta.get('fixture') or '-'}  T0 {meta.get('normal_temp_c', '?')} C"
        f"  started {meta.get('started_utc') or '-'}"
    ]
    files = summary.get("files")
    if files:
        lines.append(f"  one recording of {count_words(len(files), 'file')}, in time order:")
        lines += [
            f"  {f['source']}  run {f['run_id']}  {utc_text(f['t_start_ns'])} .. {utc_text(f['t_end_ns'])}"
            for f in files
        ]
    elif summary.get("source"):
        lines.append(f"  source: {summary['source']}")
    for name, s in summary["streams"].items():
        if s["samples"] == 0:
            lines.append(f"{name}: no samples")
            continue
        rate = f", {s['rate_hz']:.4g} Hz" if s["rate_hz"] else ""
        unit = "events" if name == "fixture" else "samples"
        lines.append(
            f"{name}: {s['samples']} {unit}{rate}, {_duration(s['duration_s'])} "
            f"from {utc_text(s['t_start_ns'])} to {utc_text(s['t_end_ns'])}"
        )
        details = []
        if s["gaps"]:
            longest = max(g[1] for g in s["gaps"])
            details.append(
                f"{len(s['gaps'])} gaps (longest {_duration(longest)} at "
                f"{utc_text(max(s['gaps'], key=lambda g: g[1])[0])})"
            )
        if s["non_finite"]:
            details.append(f"{s['non_finite']} non-finite values")
        if "positions" in s:
            details.append("positions " + " ".join(s["positions"]))
        if details:
            lines.append("  " + "; ".join(details))
    rec = summary.get("recording")
    if rec:
        lines += _recording_lines(rec)
    plateaus, positions = summary.get("plateaus") or [], summary.get("static_positions") or []
    grouped = " (grouped into the poses above; --json lists each)" if rec and len(positions) > 24 else ""
    lines.append(
        f"segmentation: {summary.get('segmentation', '-')}; {count_words(len(plateaus), 'plateau')}, "
        f"{count_words(len(positions), 'static segment')}{grouped}"
    )
    t0 = min((p["t_start_ns"] for p in plateaus), default=0)
    for p in plateaus:
        names = [s["position"] or "?" for s in positions if s["plateau"] == p["index"]]
        settling = [s["position"] or "?" for s in positions if s.get("settling") == p["index"]]
        before = f"  (held while still settling towards it: {' '.join(settling)})" if settling else ""
        lines.append(
            f"  plateau {p['index']}: {p['temp_c']:+7.2f} C  from {(p['t_start_ns'] - t0) / 3.6e12:5.2f} h, "
            f"{(p['t_end_ns'] - p['t_start_ns']) / 6e10:5.1f} min  {' '.join(names)}{before}"
        )
    conflicts = [s for s in positions if s.get("label_conflict")]
    if conflicts:
        lines.append(f"  {len(conflicts)} segments whose fixture label disagrees with gravity (see warnings)")
    for w in [*summary.get("warnings", []), *summary.get("segmentation_warnings", [])]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def _recording_lines(rec: dict[str, Any]) -> list[str]:
    """The recording's description (:func:`describe_recording`) as text."""
    t = rec["temperature"]
    lo, hi = t["range_c"]
    kinds = {
        **KIND_WORDS,
        "plateaus": f"plateau program: {count_words(t['plateaus'], 'plateau')}",
        "sweep": "temperature sweep (continuous drift, no plateau held)",
    }
    lines = [
        f"recording: {kinds.get(t['kind'], t['kind'])}; {lo:+.2f} .. {hi:+.2f} C, largest rate "
        f"{t['max_rate_c_per_h']:.3g} C/h (over {t['rate_window_s']:.0f} s)"
    ]
    st = rec["static"]
    lines.append(
        f"  {st['poses']} static poses in {st['segments']} segments (static window {st['window_s']:.3g} s, "
        f"shortest {st['min_s']:.3g} s)"
    )
    for p in rec["poses"]:
        d = " ".join(f"{x:+.3f}" for x in p["direction_g"])
        lo_c, hi_c = p["temp_range_c"]
        lines.append(
            f"  pose {p['index']}: g along ({d})  vertical {p['vertical_axis'] or '-':<3} "
            f"{p['position'] or '?':<4} {count_words(p['holds'], 'hold')}, {_duration(p['duration_s'])}"
            + (f" (shortest {_duration(p['shortest_hold_s'])})" if p["holds"] > 1 else "")
            + f"  {lo_c:+.2f} .. {hi_c:+.2f} C"
        )
    for m in rec["methods"]:
        lines.append(f"  method {m['method']:<12} {'supported' if m['supported'] else 'not supported'}: {m['why']}")
        lines += [f"      {d}" for d in m["determines"]]
    auto = next((m for m in rec["methods"] if m["method"] == rec["method_auto"]), None)
    lines.append(
        f"  calibrate --method auto: {auto['method'] if auto else 'no method fits this recording'}"
        + ("" if auto is None or auto["supported"] else f" ({auto['insists']})")
    )
    return lines


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.3g} s"
