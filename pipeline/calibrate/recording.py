"""What a recording holds, before anything is fitted: the facts every calibration method judges it by
(:meth:`pipeline.calibrate.method.Method.supports`) and ``inspect`` describes.

:class:`Recording` (``Recording.of(run, segmentation)``): the temperature program (plateaus, sweep or constant,
:func:`pipeline.segment.classify_temperature`), the static poses (:func:`static_poses`: static segments grouped by
the direction of gravity, with the axis vertical in each), which plateaus are soaks, whether a fixture logged its
positions, and the soaks whose test positions determine the 12 constants.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from pipeline.run import Run

#: static segments whose gravity directions lie within this angle (deg) are one pose
POSE_ANGLE_DEG = 10.0
#: an axis within this angle (deg) of the gravity direction is vertical in the pose; beyond 90 - it, horizontal
AXIS_ANGLE_DEG = 15.0
#: the kinds of temperature record (:attr:`pipeline.segment.TemperatureProgram.kind`) in words
KIND_WORDS = {"plateaus": "plateau program", "constant": "one temperature", "sweep": "temperature sweep"}


@dataclass(frozen=True)
class Recording:
    """One run as the methods judge it: ``run`` and its ``segmentation`` (:func:`pipeline.segment.segment_run`),
    the temperature ``program`` (:class:`pipeline.segment.TemperatureProgram`), the static ``poses``
    (:func:`static_poses`, JSON-ready) and the temperatures of each pose's segments (``pose_temps``, C), and
    ``soaks``: the indices of the segmentation's plateaus that are soaks (not a sweep's drifting stretches)."""

    run: Run
    segmentation: Any
    program: Any
    poses: tuple[dict[str, Any], ...]
    pose_temps: tuple[tuple[float, ...], ...]
    soaks: frozenset[int]

    @classmethod
    def of(cls, run: Run, segmentation) -> Recording:
        """The recording ``run`` segmented as ``segmentation``."""
        from pipeline.segment import classify_temperature

        tt = run.au_temperature["t_ns"].to_numpy()
        order = np.argsort(tt, kind="stable")
        program = classify_temperature(tt[order], run.au_temperature["temp_c"].to_numpy()[order], segmentation.plateaus)
        poses, temps = static_poses(segmentation)
        soak_span = {(p.t_start_ns, p.t_end_ns) for p in program.plateaus}
        soaks = frozenset(p.index for p in segmentation.plateaus if (p.t_start_ns, p.t_end_ns) in soak_span)
        return cls(run, segmentation, program, tuple(poses), tuple(tuple(t) for t in temps), soaks)

    @property
    def fixture_logged(self) -> bool:
        """A fixture log says where the positions were (a tilt fixture's), rather than gravity alone."""
        return self.run.fixture is not None and self.run.fixture.height > 0

    @cached_property
    def constant_plateaus(self) -> list[tuple[str, int, float, tuple[str, ...]]]:
        """The soaks whose test positions determine the 12 constants
        (:func:`pipeline.calibrate.observations.calibration_plateaus`: ``(run_id, plateau, mean temperature C,
        positions)``), as the tilt method takes them (the six, or fewer by least squares; held while the unit
        still settled too)."""
        from pipeline.calibrate.observations import calibration_plateaus, observations_from_segmentation

        observations = observations_from_segmentation(self.run.meta.run_id, self.segmentation)
        return [c for c in calibration_plateaus(observations) if c[1] in self.soaks]

    def poses_near(self, temp_c: float, tol_c: float = 3.0) -> list[dict[str, Any]]:
        """The poses held within ``tol_c`` (C) of ``temp_c`` at least once."""
        return [
            p
            for p, temps in zip(self.poses, self.pose_temps)
            if any(abs(t - temp_c) <= tol_c for t in temps if np.isfinite(t))
        ]


def static_poses(seg) -> tuple[list[dict[str, Any]], list[list[float]]]:
    """Static segments grouped by gravity direction (within POSE_ANGLE_DEG): per pose its direction (unit vector,
    AU axes), the axis vertical in it (``+z``: z points up, ``-z``: down; None when none is), the holds (runs of
    consecutive segments in the pose), total and shortest hold durations, temperatures covered, position name; and
    per pose the temperatures of its segments (C). In the order first held."""
    segs = [s for s in seg.segments if s.count > 0]
    if not segs:
        return [], []
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
    out: list[tuple[dict[str, Any], list[float]]] = []
    for j in range(len(centres)):
        idx = np.flatnonzero(label == j)
        holds: list[list[int]] = []
        for k in idx.tolist():
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
            (
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
                },
                temps,
            )
        )
    out.sort(key=lambda p: p[0]["first_t_ns"])
    for k, (p, _) in enumerate(out):
        p["index"] = k
    return [p for p, _ in out], [t for _, t in out]


def axis_roles(poses) -> dict[str, tuple[bool, bool]]:
    """Per axis of ``poses`` (:func:`static_poses`): (vertical in some pose, horizontal in some pose)."""
    roles = {}
    s = np.sin(np.radians(AXIS_ANGLE_DEG))
    c = np.cos(np.radians(AXIS_ANGLE_DEG))
    for i, ax in enumerate("xyz"):
        comp = [abs(p["direction_g"][i]) for p in poses]
        roles[ax] = (any(x >= c for x in comp), any(x <= s for x in comp))
    return roles


def _r(x: float, nd: int = 3):
    return round(float(x), nd) if np.isfinite(x) else None
