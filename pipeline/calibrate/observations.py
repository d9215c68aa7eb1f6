"""What every calibration method takes from a run: the averaged static segments (observations), the run's
warnings, and the VP verification of a fitted model on them.

- :class:`Observation`: one averaged static segment (position, mean outputs V, mean AU temperature C);
- :func:`observations_from_segmentation` / :func:`observe_run`: a run's observations (the latter refuses a run with
  no named static position on any plateau, with a one-line error naming the file, the stream and the time span);
- :class:`ObservedRun`: one run reduced for a calibration, the per-run step of every recipe (what a fleet isolates:
  a run that cannot be observed is dropped, the others are calibrated);
- :func:`unit_of`: the one unit serial of a set of runs;
- :func:`verification_observations`: the VP observations that are verification results (no soak holds);
- :func:`verify_unit`: dg at each of them, uncompensated and by both compensation methods, and the status (never
  ``pass`` where :func:`verification_gap` finds the thermal model's range unverified);
- :func:`plateau_summary`: the plateaus and their positions, for ``calibrate --json``;
- :func:`plateau_groups`, :func:`calibration_plateaus`: the test-position observations per plateau, and the
  plateaus whose test positions determine the 12 constants (:func:`determines_constants`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from pipeline.errors import CalibrationError
from pipeline.plausibility import IMPLAUSIBLE, mirrored_axis
from pipeline.positions import gravity_vector_g, is_test_position, is_verification_position
from pipeline.run import RunMeta
from pipeline.segment import SegmentSettings, StaticSegment, segment_run
from pipeline.verify import Tolerances, VerificationRow, overall_status, verify_positions


@dataclass(frozen=True)
class Observation:
    """One averaged static segment: named position, mean outputs (V), mean AU temperature (C)."""

    run_id: str
    plateau: int | None  # plateau index within its run (None: not on a plateau)
    position: str
    u_v: tuple[float, float, float]
    std_v: tuple[float, float, float]
    count: int
    temp_c: float
    t_start_ns: int
    t_end_ns: int
    source: str = ""  # the file or directory the run was read from ("" for a run made in memory)
    settling: bool = False  # held while the unit still settled towards the plateau (before its stable part)
    #: the readings' resolution per channel (V, :attr:`pipeline.segment.Segmentation.resolution_v`): a floor of the
    #: mean's uncertainty (:func:`pipeline.uncertainty.segment_noise_var_v2`)
    resolution_v: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: the standard error (C) of ``temp_c`` from the thermosensor's noise
    #: (:attr:`pipeline.segment.StaticSegment.temp_sigma_c`)
    temp_sigma_c: float = 0.0


@dataclass
class ObservedRun:
    """One run reduced for a calibration (the per-run step of every recipe): its metadata and file, its
    observations (named static segments), the reader's and segmenter's warnings, and ``data``, what the method
    keeps of the run besides (the scalar method: every static segment on a plateau; the differential method: the
    block averages of its orientation windows). Small: the samples themselves are not kept."""

    meta: RunMeta
    source: str
    observations: list[Observation]
    warnings: list[str] = field(default_factory=list)
    data: Any = None


def observations_from_segmentation(run_id: str, segmentation, source: str = "") -> list[Observation]:
    """Named static segments on plateaus, in the settling before a plateau (as that plateau's, ``settling``), and VP
    segments anywhere, as observations (``source``: the run's file). The pieces of one hold split by a gap
    (:attr:`pipeline.segment.StaticSegment.continues`) are one observation: their samples pooled (means weighted by
    their counts, the spread about the pooled mean), spanning the first piece's start to the last one's end."""
    out: list[Observation] = []
    resolution_v = tuple(segmentation.resolution_v)
    made: dict[int, int] = {}  # segment index -> index in ``out`` of its observation
    for s in segmentation.segments:
        if s.position is None or s.count == 0:
            continue
        joined = made.get(s.continues) if s.continues is not None else None
        if joined is not None:
            out[joined] = _pooled(out[joined], s)
            made[s.index] = joined
            continue
        settling = s.plateau is None and s.settling is not None
        if s.plateau is None and not settling and not is_verification_position(s.position):
            continue
        out.append(
            Observation(
                run_id=run_id,
                plateau=s.settling if settling else s.plateau,
                position=s.position,
                u_v=tuple(s.mean_v),
                std_v=tuple(s.std_v),
                count=int(s.count),
                temp_c=float(s.temp_c),
                t_start_ns=int(s.t_start_ns),
                t_end_ns=int(s.t_end_ns),
                source=source,
                settling=settling,
                resolution_v=resolution_v,
                temp_sigma_c=float(s.temp_sigma_c),
            )
        )
        made[s.index] = len(out) - 1
    return out


def _pooled(o: Observation, s: StaticSegment) -> Observation:
    """Observation ``o`` with the samples of segment ``s`` (a later piece of the same hold) pooled into it."""
    n1, n2 = o.count, int(s.count)
    m1, m2 = np.asarray(o.u_v), np.asarray(s.mean_v)
    mean = (n1 * m1 + n2 * m2) / (n1 + n2)
    # sum of squares about the pooled mean (ddof 1 per piece as the segments' std, ddof 1 overall)
    ss = (n1 - 1) * np.asarray(o.std_v) ** 2 + (n2 - 1) * np.asarray(s.std_v) ** 2
    ss = ss + n1 * (m1 - mean) ** 2 + n2 * (m2 - mean) ** 2
    std = np.sqrt(ss / max(n1 + n2 - 1, 1))
    return replace(
        o,
        u_v=(float(mean[0]), float(mean[1]), float(mean[2])),
        std_v=(float(std[0]), float(std[1]), float(std[2])),
        count=n1 + n2,
        temp_c=(n1 * o.temp_c + n2 * float(s.temp_c)) / (n1 + n2),
        temp_sigma_c=float(np.hypot(n1 * o.temp_sigma_c, n2 * s.temp_sigma_c)) / (n1 + n2),
        t_end_ns=int(s.t_end_ns),
    )


def unit_of(runs) -> str:
    """The one unit serial of ``runs`` (runs or :class:`ObservedRun`, anything with a ``meta``); CalibrationError
    when none are given or they are of different units."""
    serials = sorted({r.meta.unit_serial for r in runs})
    if not serials:
        raise CalibrationError("no runs given")
    if len(serials) != 1:
        raise CalibrationError(f"runs of different units given together: {', '.join(serials)}")
    return serials[0]


def observe_run(run, settings: SegmentSettings = SegmentSettings(), seg=None) -> tuple[list[Observation], list[str]]:
    """Segment a run (or take its segmentation ``seg``, made with ``settings``) and return its observations and the
    segmenter's and reader's warnings.

    A run with no named static position on any temperature plateau is of no use to a calibration:
    :class:`CalibrationError` naming the file, the stream at fault and the time span.
    """
    seg = seg if seg is not None else segment_run(run, settings)
    obs = observations_from_segmentation(run.meta.run_id, seg, run.source)
    warnings = list(run.warnings) + list(seg.warnings)
    if not any(o.plateau is not None for o in obs):
        raise _unusable_run(run, seg.plateaus, warnings, settings)
    mirrored = mirrored_axis([(s.fixture_label, s.position) for s in seg.segments if s.label_conflict])
    if mirrored:
        warnings.append(f"{IMPLAUSIBLE}{run.source or run.meta.run_id}: {mirrored}")
    return obs, warnings


def _unusable_run(run, plateaus, warnings: list[str], settings: SegmentSettings) -> CalibrationError:
    if not plateaus:
        t = run.au_temperature["t_ns"]
        temp = run.au_temperature["temp_c"].fill_nan(None)
        reads = f", it reads {temp.min():.2f}..{temp.max():.2f} C" if temp.null_count() < temp.len() else ""
        return CalibrationError(
            f"no temperature plateau: the AU temperature never stays within "
            f"{settings.plateau_rate_c_per_min} C/min for {settings.plateau_min_s:.0f} s{reads}",
            path=run.source,
            stream="au_temperature",
            where=f"t_ns={t.min()}..{t.max()}",
        )
    why = f" ({'; '.join(warnings)})" if warnings else ""
    return CalibrationError(
        f"no named static position on any of the {len(plateaus)} temperature plateau(s){why}",
        path=run.source,
        stream="voltmeter",
        where=f"t_ns={plateaus[0].t_start_ns}..{plateaus[-1].t_end_ns}",
    )


def verify_unit(
    model, observations: list[Observation], normal_temp_c: float, tolerances: Tolerances = Tolerances()
) -> tuple[list[VerificationRow], str]:
    """dg at every VP observation on a plateau, except a soak hold (:func:`soak_holds`); returns the rows (by time)
    and the overall status."""
    vp = verification_observations(observations)
    if not vp:
        return [], "unverified"
    rows = verify_positions(
        model,
        [o.position for o in vp],
        np.array([o.u_v for o in vp]),
        np.array([o.temp_c for o in vp]),
        normal_temp_c=normal_temp_c,
        tolerances=tolerances,
        run_ids=[o.run_id for o in vp],
        spans_ns=[(o.t_start_ns, o.t_end_ns) for o in vp],
        plateaus=[o.plateau for o in vp],
    )
    status = overall_status(rows)
    if status == "pass" and verification_gap(observations, normal_temp_c) is not None:
        status = "unverified"
    return rows, status


#: a side of T0 the calibration reaches by more than this (C) must be verified on that side too
_VERIFY_REACH_C = 5.0


def verification_observations(observations: list[Observation]) -> list[Observation]:
    """The observations that are verification results, by run and time: VP observations on a plateau (or in the
    settling before it), except soak holds (:func:`soak_holds`)."""
    held = soak_holds(observations)
    return sorted(
        (
            o
            for o in observations
            if is_verification_position(o.position) and o.plateau is not None and id(o) not in held
        ),
        key=lambda o: (o.run_id, o.t_start_ns),
    )


def verification_gap(observations: list[Observation], normal_temp_c: float) -> str | None:
    """What the VP data leave unverified of the thermal model's range, or None: the calibration's positions reach
    below (above) T0 by more than 5 C and no verification result (:func:`verification_observations`: a soak hold
    is none) is below (above) T0 by more than 5 C. A status is then never ``pass`` (say what was verified
    instead). Nor is it when VP positions were held off every plateau found, more than 5 C outside the calibrated
    temperatures (soaks too short for the plateau test: the run went where the calibration does not)."""
    held = soak_holds(observations)
    cal = [
        o.temp_c
        for o in observations
        if o.plateau is not None and not is_verification_position(o.position) and id(o) not in held
    ]
    vp = [o.temp_c for o in verification_observations(observations)]
    if not cal:
        return None
    lo, hi = min(cal), max(cal)
    gaps = []
    if lo < normal_temp_c - _VERIFY_REACH_C and not any(t < normal_temp_c - _VERIFY_REACH_C for t in vp):
        gaps.append(f"below T0 (the model reaches {lo:+.1f} C)")
    if hi > normal_temp_c + _VERIFY_REACH_C and not any(t > normal_temp_c + _VERIFY_REACH_C for t in vp):
        gaps.append(f"above T0 (the model reaches {hi:+.1f} C)")
    where = ", ".join(f"{t:+.1f}" for t in sorted({round(t, 1) for t in vp})) or "none"
    said = (
        [f"verification does not exercise the thermal model {' nor '.join(gaps)}: VP data only at {where} C"]
        if gaps
        else []
    )
    off = [
        o.temp_c
        for o in observations
        if o.plateau is None
        and is_verification_position(o.position)
        and not lo - _VERIFY_REACH_C <= o.temp_c <= hi + _VERIFY_REACH_C
    ]
    if off:
        said.append(
            f"{len(off)} VP segments held between {min(off):+.1f} and {max(off):+.1f} C lie off every "
            f"temperature plateau found, outside the calibrated {lo:+.1f} .. {hi:+.1f} C (soaks too short "
            "for the plateau test?)"
        )
    if not said:
        return None
    return "; ".join(said) + ", so the status is not pass"


def soak_holds(observations: list[Observation]) -> set[int]:
    """``id()`` of the observations that are soak holds: the first observation on a plateau whose position is the
    one the run held just before (the unit stayed there through the ramp and the soak). It was taken while the
    unit settled, not as a visit of the position, so it is no verification result."""
    by_run: dict[str, list[Observation]] = {}
    for o in observations:
        by_run.setdefault(o.run_id, []).append(o)
    held = set()
    for rows in by_run.values():
        rows = sorted(rows, key=lambda o: o.t_start_ns)
        for prev, o in zip(rows, rows[1:]):
            if o.plateau is not None and o.plateau != prev.plateau and o.position == prev.position:
                held.add(id(o))
    return held


def plateau_summary(observations: list[Observation]) -> list[dict]:
    """``[{"temp_c", "run_id", "positions"}]`` per plateau, in time order (for ``calibrate --json``)."""
    groups: dict[tuple[str, int], list[Observation]] = {}
    for o in observations:
        if o.plateau is not None:
            groups.setdefault((o.run_id, o.plateau), []).append(o)
    out = []
    for (run_id, _plateau), rows in sorted(groups.items(), key=lambda kv: (kv[0][0], min(o.t_start_ns for o in kv[1]))):
        rows.sort(key=lambda o: o.t_start_ns)
        out.append(
            {
                "temp_c": round(float(np.mean([o.temp_c for o in rows])), 2),
                "run_id": run_id,
                "positions": [o.position for o in rows],
            }
        )
    return out


def plateau_groups(obs: list[Observation]) -> dict[tuple[str, int], list[Observation]]:
    """Test-position observations per plateau; a position held while the unit still settled towards the plateau
    counts only where the plateau's stable part lacks it (each at its own temperature: see
    :func:`pipeline.calibrate.tilt.fit_unit`)."""
    groups: dict[tuple[str, int], list[Observation]] = {}
    for o in obs:
        if o.plateau is not None and is_test_position(o.position):
            groups.setdefault((o.run_id, o.plateau), []).append(o)
    for key, rows in groups.items():
        stable = {o.position for o in rows if not o.settling}
        groups[key] = [o for o in rows if not (o.settling and o.position in stable)]
    return groups


def calibration_plateaus(observations: list[Observation]) -> list[tuple[str, int, float, tuple[str, ...]]]:
    """The plateaus the tilt method fits constants on: ``(run_id, plateau, mean temperature C, positions)`` for
    each plateau whose test positions determine the 12 constants (:func:`determines_constants`), in the order
    found. What ``inspect`` tells of a recording before calibrating it."""
    out = []
    for (run_id, p), rows in plateau_groups(observations).items():
        names = tuple(dict.fromkeys(o.position for o in rows))
        if determines_constants(names):
            out.append((run_id, p, float(np.mean([o.temp_c for o in rows])), names))
    return out


def determines_constants(positions) -> bool:
    """Whether static positions determine all 12 constants: U = K a + U0 has, per channel, four unknowns and the
    positions' [a, 1] rows must have rank 4 (e.g. five of the six test positions do)."""
    rows = np.array([[*gravity_vector_g(p), 1.0] for p in dict.fromkeys(positions)])
    return rows.shape[0] >= 4 and np.linalg.matrix_rank(rows) == 4
