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
from pipeline.jsonable import to_jsonable
from pipeline.run import Run
from pipeline.utc import utc_text
from pipeline.words import count_words


def summarize_run(run: Run) -> dict[str, Any]:
    """Metadata, per-stream statistics and the segmentation summary of ``run`` (JSON-ready)."""
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
    summary.update(_segmentation_summary(run))
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


def _segmentation_summary(run: Run) -> dict[str, Any]:
    """``plateaus`` and ``static_positions`` found by :func:`pipeline.segment.segment_run`, and ``recording``: what
    the recording is (:func:`describe_recording`).

    Each plateau and static segment is its dataclass as a JSON-ready dict. In a temperature sweep the drifting
    stretches the plateau test passes piecewise are not plateaus and are not listed. A segmenter error is reported,
    not raised, so that ``inspect`` still shows the streams.
    """
    from pipeline.segment import segment_run

    try:
        result = segment_run(run)
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


#: static segments whose gravity directions lie within this angle (deg) are one pose
POSE_ANGLE_DEG = 10.0
#: an axis within this angle (deg) of the gravity direction is vertical in the pose; beyond 90 - it, horizontal
AXIS_ANGLE_DEG = 15.0
#: scalar calibration: at least this many distinct poses for the full model (gains, offsets, 3 psi combinations),
#: and this many for gains and offsets only
SCALAR_FULL_POSES = 9
SCALAR_DIAGONAL_POSES = 6
#: a sweep orientation counts when held this long (s) through at least this temperature change (C)
SWEEP_MIN_HOLD_S = 3600.0
SWEEP_MIN_SPAN_C = 2.0


def describe_recording(run: Run, seg) -> dict[str, Any]:
    """What a recording is, before anything is fitted (JSON-ready): the temperature program (plateaus, sweep or
    constant: range, largest rate), the static poses (count, holds, durations, direction of gravity, which axis is
    vertical, temperatures covered), and for each calibration method whether the data supports it and which
    constants it can determine (``methods``; ``method_auto`` is the one ``calibrate --method auto`` picks).

    ``seg`` is the run's :class:`pipeline.segment.Segmentation`. The key ``_plateaus`` carries the plateaus that are
    soaks (for the caller; not part of the description).
    """
    from pipeline.segment import classify_temperature

    tt = run.au_temperature["t_ns"].to_numpy()
    order = np.argsort(tt, kind="stable")
    program = classify_temperature(tt[order], run.au_temperature["temp_c"].to_numpy()[order], seg.plateaus)
    poses = _poses(seg)
    soak_idx = {(p.t_start_ns, p.t_end_ns) for p in program.plateaus}
    on_soak = {p.index for p in seg.plateaus if (p.t_start_ns, p.t_end_ns) in soak_idx}
    methods = _methods(program, poses, seg, on_soak, run)
    for p in poses:
        del p["_temps"]
    auto = _auto(methods, program, run)
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
            "poses": len(poses),
        },
        "poses": poses,
        "methods": methods,
        "method_auto": auto,
        "_plateaus": list(program.plateaus),
    }


def _r(x: float, nd: int = 3):
    return round(float(x), nd) if np.isfinite(x) else None


def _poses(seg) -> list[dict[str, Any]]:
    """Static segments grouped by gravity direction (within POSE_ANGLE_DEG): per pose its direction (unit vector,
    AU axes), the axis vertical in it (``+z``: z points up, ``-z``: down; None when none is), the holds (runs of
    consecutive segments in the pose), total and shortest hold durations, temperatures covered, position name."""
    segs = [s for s in seg.segments if s.count > 0]
    if not segs:
        return []
    d = np.array([s.direction_g for s in segs], dtype=float)
    if not np.all(np.isfinite(d)):  # no gain known: the direction of the raw outputs (sign unknown)
        m = np.array([s.mean_v for s in segs], dtype=float)
        d = m / np.linalg.norm(m, axis=1, keepdims=True)
    cos_max = np.cos(np.radians(POSE_ANGLE_DEG))
    centres: list[np.ndarray] = []
    label = np.empty(len(segs), dtype=int)
    for k, v in enumerate(d):
        hit = next((j for j, c in enumerate(centres) if float(v @ c) >= cos_max), None)
        if hit is None:
            centres.append(v.copy())
            hit = len(centres) - 1
        label[k] = hit
    out = []
    for j in range(len(centres)):
        idx = np.flatnonzero(label == j)
        holds: list[list[int]] = []
        for k in idx:
            if holds and holds[-1][-1] == k - 1:
                holds[-1].append(k)
            else:
                holds.append([k])
        durations = [(segs[h[-1]].t_end_ns - segs[h[0]].t_start_ns) / 1e9 for h in holds]
        w = np.array([segs[k].count for k in idx], dtype=float)
        v = np.average(d[idx], axis=0, weights=w)
        v = v / np.linalg.norm(v)
        big = int(np.argmax(np.abs(v)))
        vertical = (
            ("+" if v[big] > 0 else "-") + "xyz"[big] if abs(v[big]) >= np.cos(np.radians(AXIS_ANGLE_DEG)) else None
        )
        temps = [segs[k].temp_c for k in idx]
        names = sorted({segs[k].position for k in idx if segs[k].position})
        out.append(
            {
                "index": j,
                "direction_g": [round(float(x), 4) for x in v],
                "vertical_axis": vertical,
                "position": names[0] if len(names) == 1 else None,
                "holds": len(holds),
                "duration_s": round(float(sum(durations)), 2),
                "shortest_hold_s": round(float(min(durations)), 2),
                "longest_hold_s": round(float(max(durations)), 2),
                "temp_range_c": [_r(min(temps), 2), _r(max(temps), 2)],
                "first_t_ns": int(segs[idx[0]].t_start_ns),
                "_temps": temps,
            }
        )
    out.sort(key=lambda p: p["first_t_ns"])
    for k, p in enumerate(out):
        p["index"] = k
    return out


def _near(pose: dict[str, Any], t0: float, tol_c: float = 3.0) -> bool:
    return any(abs(t - t0) <= tol_c for t in pose["_temps"] if np.isfinite(t))


def _axis_roles(poses: list[dict[str, Any]]) -> dict[str, tuple[bool, bool]]:
    """Per axis: (vertical in some pose, horizontal in some pose)."""
    roles = {}
    s = np.sin(np.radians(AXIS_ANGLE_DEG))
    c = np.cos(np.radians(AXIS_ANGLE_DEG))
    for i, ax in enumerate("xyz"):
        comp = [abs(p["direction_g"][i]) for p in poses]
        roles[ax] = (any(x >= c for x in comp), any(x <= s for x in comp))
    return roles


def _methods(program, poses, seg, on_soak: set[int], run: Run) -> list[dict[str, Any]]:
    """Whether each method can run on this recording and what it determines (in the order ``auto`` prefers)."""
    from pipeline.calibrate.observations import observations_from_segmentation
    from pipeline.calibrate.tilt import calibration_plateaus
    from pipeline.thermal import cluster_temperatures, default_order

    out = []
    # tilt: the soaks whose test positions determine the 12 constants, as the tilt calibration takes them (the
    # six, or fewer by least squares; held while the unit still settled too); the thermal model's order is what
    # their distinct temperatures allow (calibrate --thermal-model refuses a higher one)
    cal = [c for c in calibration_plateaus(observations_from_segmentation(run.meta.run_id, seg)) if c[1] in on_soak]
    n = len(cal)
    six = sum(set(c[3]) >= {f"TP{k}" for k in range(1, 7)} for c in cal)
    temps = np.array([c[2] for c in cal])
    labels = cluster_temperatures(temps) if n else np.zeros(0, dtype=int)
    distinct = int(labels.max()) + 1 if n else 0
    order = default_order(temps) if n else 0
    at = ", ".join(f"{t:+.0f}" for t in sorted(float(np.mean(temps[labels == k])) for k in range(distinct)))
    out.append(
        {
            "method": "tilt",
            "supported": n > 0,
            "why": (
                f"{count_words(n, 'plateau')} whose test positions determine the 12 constants ({six} with all "
                f"six), at {count_words(distinct, 'temperature')} ({at} C)"
                if n
                else "no temperature plateau holds test positions that determine the 12 constants (TP1..TP6, "
                "or five of them)"
            ),
            "determines": (
                [
                    "K (9) and U0 (3) at each plateau temperature",
                    f"thermal model of order up to {order} (one less than the distinct temperatures, at most 3)"
                    if distinct > 1
                    else "no thermal model (one temperature)",
                ]
                if n
                else []
            ),
        }
    )
    # sweep (differential): orientations held through temperature excursions
    held = [
        p
        for p in poses
        if p["longest_hold_s"] >= SWEEP_MIN_HOLD_S
        and None not in p["temp_range_c"]
        and p["temp_range_c"][1] - p["temp_range_c"][0] >= SWEEP_MIN_SPAN_C
    ]
    roles = _axis_roles(held)
    both = [ax for ax, (v, h) in roles.items() if v and h]
    sweep_ok = len(held) >= 2
    det = []
    if sweep_ok:
        det.append("per axis: bias temperature terms (polynomial in T, rate terms)")
        det += [
            f"axis {ax}: bias and scale factor separated (vertical in one orientation, horizontal in another)"
            for ax in both
        ]
        det += [
            f"axis {ax}: scale factor and its temperature terms undetermined without --base-passport (never vertical)"
            if not roles[ax][0]
            else f"axis {ax}: bias at T0 undetermined without --base-passport (never horizontal)"
            for ax in "xyz"
            if ax not in both
        ]
        det.append(
            "cross-axis constants: undetermined without --base-passport (only their temperature terms, "
            "where the orientations excite them)"
        )
    out.append(
        {
            "method": "differential",
            "supported": sweep_ok,
            "why": (
                f"{len(held)} orientations held {SWEEP_MIN_HOLD_S / 3600:.0f} h or more through "
                f"{SWEEP_MIN_SPAN_C:.0f} C or more"
                if sweep_ok
                else f"needs two or more orientations each held {SWEEP_MIN_HOLD_S / 3600:.0f} h or more through "
                f"{SWEEP_MIN_SPAN_C:.0f} C or more; found {len(held)}"
            ),
            "determines": det,
        }
    )
    # scalar: many distinct poses at one temperature
    t0 = float(run.meta.normal_temp_c)
    near = [p for p in poses if _near(p, t0)]
    k = len(near)
    out.append(
        {
            "method": "scalar",
            "supported": k >= SCALAR_DIAGONAL_POSES,
            "why": f"{k} distinct static poses within 3 C of T0 ({t0:g} C)",
            "determines": (
                [
                    "gains and offsets at T0",
                    "psi_xy, psi_xz, psi_yz (sums of cross-axis pairs; the "
                    "individual cross-axis terms are not determined)",
                ]
                if k >= SCALAR_FULL_POSES
                else [
                    "gains and offsets at T0 (orthogonal axes assumed: too few poses for the cross-axis combinations)"
                ]
                if k >= SCALAR_DIAGONAL_POSES
                else []
            ),
        }
    )
    # in the order auto prefers them: tilt on a plateau program, the sweep method on a sweep, scalar on many poses
    # at one temperature when no fixture log says where they are (poses named from gravity alone are not known to
    # a fixture's precision: a hand-turned fixture) and tilt would not determine a thermal model (fewer than two
    # plateaus with the six test positions), or when tilt cannot run
    logged = _fixture_logged(run)
    if program.kind == "sweep":
        out = [out[1], out[0], out[2]]
    elif (k >= SCALAR_FULL_POSES and not logged and n < 2) or (k >= SCALAR_DIAGONAL_POSES and not out[0]["supported"]):
        out = [out[2], out[0], out[1]]
    return out


def _fixture_logged(run: Run) -> bool:
    return run.fixture is not None and run.fixture.height > 0


def _auto(methods: list[dict[str, Any]], program, run: Run) -> str | None:
    """The method ``calibrate --method auto`` uses: the sweep method on a sweep it supports; tilt on a recording
    whose tilt fixture logged its positions (even where the data fall short: the tilt method then says exactly
    what is missing); otherwise the first supported method in the order of ``methods``; None when none is."""
    by = {m["method"]: m for m in methods}
    if program.kind == "sweep" and by["differential"]["supported"]:
        return "differential"
    if _fixture_logged(run):
        return "tilt"
    return next((m["method"] for m in methods if m["supported"]), None)


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable text of :func:`summarize_run`'s result, a few lines per stream."""
    meta = summary["metadata"]
    lines = [
        f"run {meta.get('run_id', '?')}  unit {meta.get('unit_serial', '?')}  station {meta.get('station') or '-'}"
        f"  fixture {meta.get('fixture') or '-'}  T0 {meta.get('normal_temp_c', '?')} C"
        f"  started {meta.get('started_utc') or '-'}"
    ]
    if summary.get("source"):
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
    auto = rec["method_auto"]
    supported = any(m["method"] == auto and m["supported"] for m in rec["methods"])
    lines.append(
        f"  calibrate --method auto: {auto or 'no method fits this recording'}"
        + ("" if auto is None or supported else " (the fixture log says tilt; it will say what is missing)")
    )
    return lines


#: the kinds of temperature record (``recording.temperature.kind``) in words
KIND_WORDS = {"plateaus": "plateau program", "constant": "one temperature", "sweep": "temperature sweep"}


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.3g} s"
