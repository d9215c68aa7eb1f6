"""What a run holds, for ``thermocal inspect``: metadata, per-stream counts, rates, time span, gaps, non-finite
samples; and the plateaus and static positions the segmenter finds.

:func:`summarize_run` returns a JSON-ready dict (plain ints, floats, strings and lists); :func:`format_summary`
renders it as a few lines per stream.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.errors import ThermocalError
from pipeline.io.checks import GAP_FACTOR, gap_indices  # noqa: F401  (GAP_FACTOR: the gap definition, shared with the readers)
from pipeline.run import Run


def summarize_run(run: Run) -> dict[str, Any]:
    """Metadata, per-stream statistics and the segmentation summary of ``run`` (JSON-ready)."""
    summary: dict[str, Any] = {
        "source": run.source,
        "metadata": run.meta.to_strings(),
        "streams": {name: stream_summary(name, df["t_ns"].to_numpy(), _non_finite(df))
                    for name, df in run.streams().items()},
        "warnings": list(run.warnings),
    }
    if run.fixture is not None:
        summary["streams"]["fixture"]["positions"] = sorted(run.fixture["position"].unique().to_list())
    summary.update(_segmentation_summary(run))
    return summary


def stream_summary(name: str, t_ns: np.ndarray, non_finite: int) -> dict[str, Any]:
    """Sample count, rate (from the median interval), span, gaps (> GAP_FACTOR median intervals) of one stream.

    ``gaps`` is a list of ``[t_ns, length_s]``: where the gap starts (time of the last sample before it) and how long
    the interval is. The fixture log is a list of events, so it has no rate and no gaps.
    """
    n = int(len(t_ns))
    out: dict[str, Any] = {"samples": n, "rate_hz": None, "t_start_ns": None, "t_end_ns": None, "duration_s": 0.0,
                           "gaps": [], "non_finite": int(non_finite)}
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


def _segmentation_summary(run: Run) -> dict[str, Any]:
    """``plateaus`` and ``static_positions`` found by :func:`pipeline.segment.segment_run`.

    Each plateau and static segment is its dataclass as a JSON-ready dict. A segmenter error is reported, not
    raised, so that ``inspect`` still shows the streams.
    """
    try:
        from pipeline.segment import segment_run
    except ImportError:
        return {"plateaus": [], "static_positions": [], "segmentation": "not available (pipeline.segment missing)"}
    try:
        result = segment_run(run)
    except ThermocalError as exc:
        return {"plateaus": [], "static_positions": [], "segmentation": f"failed: {exc}"}
    return {"plateaus": _jsonable(result.plateaus), "static_positions": _jsonable(result.segments),
            "segmentation": "ok", "segmentation_warnings": list(result.warnings)}


def _jsonable(value: Any) -> Any:
    """Dataclasses, tuples and numpy values as JSON-ready data."""
    import dataclasses

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable text of :func:`summarize_run`'s result, a few lines per stream."""
    meta = summary["metadata"]
    lines = [f"run {meta.get('run_id', '?')}  unit {meta.get('unit_serial', '?')}  station {meta.get('station') or '-'}"
             f"  fixture {meta.get('fixture') or '-'}  T0 {meta.get('normal_temp_c', '?')} C"
             f"  started {meta.get('started_utc') or '-'}"]
    if summary.get("source"):
        lines.append(f"  source: {summary['source']}")
    for name, s in summary["streams"].items():
        if s["samples"] == 0:
            lines.append(f"{name}: no samples")
            continue
        rate = f", {s['rate_hz']:.4g} Hz" if s["rate_hz"] else ""
        unit = "events" if name == "fixture" else "samples"
        lines.append(f"{name}: {s['samples']} {unit}{rate}, {_duration(s['duration_s'])} "
                     f"from {utc_text(s['t_start_ns'])} to {utc_text(s['t_end_ns'])}")
        details = []
        if s["gaps"]:
            longest = max(g[1] for g in s["gaps"])
            details.append(f"{len(s['gaps'])} gaps (longest {_duration(longest)} at "
                           f"{utc_text(max(s['gaps'], key=lambda g: g[1])[0])})")
        if s["non_finite"]:
            details.append(f"{s['non_finite']} non-finite values")
        if "positions" in s:
            details.append("positions " + " ".join(s["positions"]))
        if details:
            lines.append("  " + "; ".join(details))
    plateaus, positions = summary.get("plateaus") or [], summary.get("static_positions") or []
    lines.append(f"segmentation: {summary.get('segmentation', '-')}; {len(plateaus)} plateaus, "
                 f"{len(positions)} static positions")
    t0 = min((p["t_start_ns"] for p in plateaus), default=0)
    for p in plateaus:
        names = [s["position"] or "?" for s in positions if s["plateau"] == p["index"]]
        lines.append(f"  plateau {p['index']}: {p['temp_c']:+7.2f} C  from {(p['t_start_ns'] - t0) / 3.6e12:5.2f} h, "
                     f"{(p['t_end_ns'] - p['t_start_ns']) / 6e10:5.1f} min  {' '.join(names)}")
    conflicts = [s for s in positions if s.get("label_conflict")]
    if conflicts:
        lines.append(f"  {len(conflicts)} segments whose fixture label disagrees with gravity (see warnings)")
    for w in [*summary.get("warnings", []), *summary.get("segmentation_warnings", [])]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def utc_text(t_ns: int) -> str:
    """``t_ns`` (ns since the Unix epoch) as a UTC time for people, to the millisecond:
    ``2026-11-01 00:00:00.000 UTC``."""
    from datetime import datetime, timedelta, timezone

    t = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=int(t_ns) // 1000)
    return t.strftime("%Y-%m-%d %H:%M:%S.") + f"{t.microsecond // 1000:03d} UTC"


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.3g} s"
