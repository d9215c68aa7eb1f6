"""The chamber-run simulator: one unit through a chamber program, as an in-memory :class:`~pipeline.run.Run`.

Physics (docs/physics.md):

- the chamber air follows the setpoint with a first-order lag (``air_lag_s``, about 1.5 min); the AU case follows
  the air with a first-order lag ``case_lag_s`` (the program's default: 600 s standard, 120 s short); both are
  computed on a 1 Hz grid, exactly for inputs linear between samples;
- the thermosensor reads the case temperature plus white noise ``temp_noise_c`` at 1 Hz; the chamber stream gives
  the setpoint and the air temperature (plus the same noise) at 1 Hz;
- the voltmeter at ``rate_hz`` gives ``U = K(T) a + U0(T) + effects + disturbances + noise`` with T the case temperature
  interpolated linearly from the 1 Hz grid (the same interpolation a reader applies to the thermosensor);
- in a static position a is the position's vector (rotated by its face error if ``fixture_face_error`` is on);
  during a move the vector turns about a fixed axis with a minimum-jerk profile between the two, plus a vibration of
  ``vibration_g`` (tones at 23-37 Hz, aliased at low rates) under a sin^2 window;
- the fixture log has the start position at t=0, ``MOVING`` at each move start and the new position at arrival.

Everything is vectorised; the 16.5 h standard program at 10 Hz takes about a second.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.dynamics import first_order_lag
from pipeline.effects.base import Effect, SignalContext
from pipeline.effects.catalogue import EFFECTS, make_effect
from pipeline.jsonable import to_jsonable
from pipeline.model import output_v
from pipeline.positions import ALL_POSITIONS, POSITION_NAMES
from pipeline.run import Run, RunMeta, make_frame
from pipeline.simulate.disturbances import make_disturbance
from pipeline.simulate.program import Program, Timetable, get_program
from pipeline.simulate.unit import UnitTruth, unit_type

#: Vibration tones during moves, Hz per axis (x, y, z).
VIBRATION_HZ = (23.1, 29.7, 37.3)
_NOMINAL_G = np.array([ALL_POSITIONS[p] for p in POSITION_NAMES], dtype=float)
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
#: Rate of the thermosensor and chamber streams, Hz.
THERMAL_RATE_HZ = 1.0


@dataclass
class SimConfig:
    """Settings of one simulated run. ``unit_type``: the kind of unit (:data:`pipeline.simulate.unit.UNIT_TYPES`:
    ``navigation``, seed 000's; ``consumer``, a MEMS part); ``unit_seed`` None is the type's reference unit (the seed
    000 unit for the navigation type); ``seed`` drives the noise. ``nominal_gain_v_per_g`` None: the type's.
    ``unit_grade``: the run metadata's ``unit_grade`` (None: the type's grade; the navigation type's runs name none,
    the default grade)."""

    unit_serial: str = "AU-0001"
    seed: int = 0
    unit_seed: int | None = None
    program: str | Program = "standard"  # a name of pipeline.simulate.program.PROGRAMS, or a Program
    rate_hz: float = 10.0
    noise_v: float = 5e-6
    temp_noise_c: float = 0.01
    case_lag_s: float | None = None
    effects: list[tuple[str, dict]] = field(default_factory=list)
    #: mismatches outside the catalogue (:mod:`pipeline.simulate.disturbances`), same form as ``effects``
    disturbances: list[tuple[str, dict]] = field(default_factory=list)
    with_fixture_log: bool = True
    with_chamber: bool = True
    normal_temp_c: float = 20.0
    started_utc: str = "2026-11-01T00:00:00Z"
    station: str = "sim-ch1"
    nominal_gain_v_per_g: float | None = None
    air_lag_s: float | None = None
    vibration_g: float = 3e-3
    #: timestamp jitter (s, standard deviation, clipped to 0.45 of the sample interval so the order holds): a
    #: wireless logger's stamps; the samples themselves are taken on the regular grid
    jitter_s: float = 0.0
    unit_type: str = "navigation"
    unit_grade: str | None = None


@dataclass
class SimResult:
    """The simulated run, its JSON-able ground truth, and the per-sample truth the effects saw (``context``)."""

    run: Run
    truth: dict
    context: SignalContext | None = field(default=None, repr=False)


def parse_utc_ns(text: str) -> int:
    """ISO 8601 time (``Z`` or an offset; naive is taken as UTC) as int ns since the Unix epoch."""
    try:
        dt = datetime.fromisoformat(text.strip())
    except ValueError:
        raise ValueError(f"started_utc is not an ISO 8601 time: {text!r}") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return (dt - _EPOCH) // timedelta(microseconds=1) * 1_000


def unit_for(config: SimConfig) -> UnitTruth:
    """The unit of ``config``: its type's reference unit (seed 000's for the navigation type), or one drawn from
    ``unit_seed``."""
    return unit_type(config.unit_type).unit(config.unit_seed, config.normal_temp_c)


def simulate(config: SimConfig) -> SimResult:
    """Simulate ``config.program`` for one unit; see the module doc for the physics."""
    _check(config)
    program = get_program(config.program)
    timetable = program.timetable()
    case_lag_s = program.case_lag_s if config.case_lag_s is None else float(config.case_lag_s)
    air_lag_s = program.air_lag_s if config.air_lag_s is None else float(config.air_lag_s)
    effects = [make_effect(eid, params) for eid, params in config.effects]
    disturbances = [make_disturbance(did, params) for did, params in config.disturbances]
    unit = unit_for(config)
    start_ns = parse_utc_ns(config.started_utc)
    rng = np.random.default_rng(config.seed)
    duration_s = timetable.duration_s

    # Temperatures on the 1 Hz grid.
    t1_s = np.arange(int(np.floor(duration_s * THERMAL_RATE_HZ)) + 1) / THERMAL_RATE_HZ
    setpoint_c = timetable.setpoint_c(t1_s)
    air_c = first_order_lag(t1_s, setpoint_c, air_lag_s)
    case_c = first_order_lag(t1_s, air_c, case_lag_s)

    # Voltmeter grid, true temperature and specific force.
    k = np.arange(int(np.floor(duration_s * config.rate_hz)) + 1)
    tv_s = k / config.rate_hz
    tv_ns = voltmeter_t_ns(start_ns, k, config, rng)
    temp_v_c = np.interp(tv_s, t1_s, case_c)
    face_rad = _face_rotations_rad(effects)
    a_g, position_idx = _specific_force_g(timetable, tv_s, face_rad, config.vibration_g, rng)
    move_start_s, arrive_s = timetable.move_times_s()
    ctx = SignalContext(
        t_s=tv_s,
        temp_c=temp_v_c,
        a_g=a_g,
        position_idx=position_idx,
        move_start_s=move_start_s,
        arrive_s=arrive_s,
        constants=unit,
        normal_temp_c=config.normal_temp_c,
        ramp_sign=timetable.ramp_sign(tv_s),
        start_ns=start_ns,
    )

    u_v = output_with_effects_v(ctx, effects, disturbances, config.noise_v, rng)
    temp_noise_c = rng.normal(0.0, config.temp_noise_c, (2, t1_s.size))  # thermosensor, chamber air
    t1_ns = start_ns + np.round(t1_s * 1e9).astype(np.int64)

    run = Run(
        meta=_meta(config),
        voltmeter=make_frame("voltmeter", {"t_ns": tv_ns, "ux": u_v[:, 0], "uy": u_v[:, 1], "uz": u_v[:, 2]}),
        au_temperature=make_frame("au_temperature", {"t_ns": t1_ns, "temp_c": case_c + temp_noise_c[0]}),
        chamber=(
            make_frame("chamber", {"t_ns": t1_ns, "setpoint_c": setpoint_c, "air_c": air_c + temp_noise_c[1]})
            if config.with_chamber
            else None
        ),
        fixture=_fixture_frame(timetable, start_ns) if config.with_fixture_log else None,
    )
    truth = _truth(
        config,
        unit,
        effects + disturbances,
        timetable,
        _position_vectors_g(face_rad),
        start_ns,
        {"case_lag_s": case_lag_s, "air_lag_s": air_lag_s},
        t1_s,
        case_c,
        run.meta,
    )
    return SimResult(run=run, truth=truth, context=ctx)


def write_truth(truth: dict, path) -> None:
    """Write the ground truth as JSON with sorted keys."""
    Path(path).write_text(json.dumps(to_jsonable(truth), sort_keys=True, indent=1) + "\n")


# ----------------------------------------------------------------------------------------------------------------


def _check(config: SimConfig) -> None:
    if not config.rate_hz > 0:
        raise ValueError(f"rate_hz must be positive, got {config.rate_hz}")
    for name in ("noise_v", "temp_noise_c", "vibration_g", "jitter_s"):
        if not getattr(config, name) >= 0:
            raise ValueError(f"{name} must not be negative, got {getattr(config, name)}")
    for name in ("case_lag_s", "air_lag_s"):
        v = getattr(config, name)
        if v is not None and not v >= 0:
            raise ValueError(f"{name} must not be negative, got {v}")
    if not config.unit_serial.strip():
        raise ValueError("unit_serial is empty")
    unit_type(config.unit_type)  # ValueError naming the types
    if config.unit_grade is not None:
        from pipeline.verify import grade_tolerances

        grade_tolerances(config.unit_grade)


def _face_rotations_rad(effects: list[Effect]) -> np.ndarray:
    """(12, 3) rotation vectors of the positions' specific force (POSITION_NAMES order) from the effects that act
    on it (the fixture's face errors); zero without them."""
    faces = [e for e in effects if e.acts_on == "specific_force"]
    if not faces:
        return np.zeros((len(POSITION_NAMES), 3))
    rot = faces[-1].rotation_vectors_rad()
    return np.array([rot[p] for p in POSITION_NAMES])


def _position_vectors_g(face_rad: np.ndarray) -> np.ndarray:
    """(12, 3) true specific force of the positions, R(delta_P) a_P, in g."""
    return Rotation.from_rotvec(face_rad).apply(_NOMINAL_G)


def _specific_force_g(
    timetable: Timetable, t_s: np.ndarray, face_rad: np.ndarray, vibration_g: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """a (n, 3) in g and the position index per sample (-1 while moving).

    Static: R(delta_P) a_P. Moving: the nominal vector turns about a fixed axis (minimum-jerk profile) while the
    face rotation blends from the old face's to the new one's, plus vibration.
    """
    nominal = _NOMINAL_G
    vectors_g = _position_vectors_g(face_rad)
    position_idx = timetable.position_index(t_s)
    a = vectors_g[np.maximum(position_idx, 0)]
    moves = timetable.moves()
    phases = rng.uniform(0.0, 2 * np.pi, (len(moves), 3))
    moving = np.flatnonzero(position_idx < 0)
    if not moves or moving.size == 0:
        return a, position_idx
    start = np.array([m.t_start_s for m in moves])
    end = np.array([m.t_end_s for m in moves])
    i_from = np.array([POSITION_NAMES.index(m.from_position) for m in moves])
    i_to = np.array([POSITION_NAMES.index(m.to_position) for m in moves])
    axis, angle = _rotation_between(nominal[i_from], nominal[i_to])
    t = t_s[moving]
    j = np.clip(np.searchsorted(start, t, side="right") - 1, 0, len(moves) - 1)
    u = np.clip((t - start[j]) / (end[j] - start[j]), 0.0, 1.0)
    profile = (u**3 * (10 - 15 * u + 6 * u**2))[:, None]  # minimum jerk: zero rate and acceleration at ends
    theta = angle[j][:, None] * profile
    a_from = nominal[i_from][j]
    turned = a_from * np.cos(theta) + np.cross(axis[j], a_from) * np.sin(theta)
    if np.any(face_rad):
        turned = Rotation.from_rotvec((1 - profile) * face_rad[i_from][j] + profile * face_rad[i_to][j]).apply(turned)
    window = np.sin(np.pi * u)[:, None] ** 2
    tones = np.sin(2 * np.pi * np.asarray(VIBRATION_HZ) * t[:, None] + phases[j])
    a[moving] = turned + vibration_g * window * tones
    return a, position_idx


def _rotation_between(a_from: np.ndarray, a_to: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit axis (m, 3), perpendicular to a_from, and angle (m,) turning unit vectors a_from into a_to."""
    cross = np.cross(a_from, a_to)
    norm = np.linalg.norm(cross, axis=1)
    angle = np.arctan2(norm, np.einsum("mi,mi->m", a_from, a_to))
    # Parallel or antiparallel: turn about the axis least aligned with a_from (any perpendicular will do).
    helper = np.eye(3)[np.argmin(np.abs(a_from), axis=1)]
    fallback = np.cross(a_from, helper)
    axis = np.where((norm > 1e-12)[:, None], cross, fallback)
    axis = axis - np.einsum("mi,mi->m", axis, a_from)[:, None] * a_from  # exactly perpendicular
    return axis / np.linalg.norm(axis, axis=1)[:, None], angle


def _fixture_frame(timetable: Timetable, start_ns: int):
    events = timetable.fixture_events()
    return make_frame(
        "fixture", {"t_ns": [start_ns + int(round(t * 1e9)) for t, _ in events], "position": [p for _, p in events]}
    )


def _meta(config: SimConfig) -> RunMeta:
    kind = unit_type(config.unit_type)
    gain = kind.nominal_gain_v_per_g if config.nominal_gain_v_per_g is None else config.nominal_gain_v_per_g
    grade = config.unit_grade or (kind.grade if kind.name != "navigation" else None)
    return RunMeta(
        unit_serial=config.unit_serial,
        run_id=f"sim-{config.unit_serial}-s{config.seed}",
        station=config.station,
        fixture="tilt-6",
        normal_temp_c=float(config.normal_temp_c),
        g_local_mps2=9.80665,
        started_utc=config.started_utc,
        nominal_gain_v_per_g=float(gain),
        unit_grade=grade,
        extra={"simulator": "thermocal", "program": get_program(config.program).name},
    )


def _truth(
    config: SimConfig,
    unit: UnitTruth,
    effects: list[Effect],
    timetable: Timetable,
    vectors_g: np.ndarray,
    start_ns: int,
    lags_s: dict[str, float],
    t1_s: np.ndarray,
    case_c: np.ndarray,
    meta: RunMeta,
) -> dict[str, Any]:
    holds: list[dict[str, Any]] = []
    for h in timetable.holds():
        inside = (t1_s >= h.t_start_s) & (t1_s < h.t_end_s)
        holds.append(
            {
                "position": h.position,
                "stage": h.stage,
                "setpoint_c": h.setpoint_start_c,
                "t_start_ns": start_ns + int(round(h.t_start_s * 1e9)),
                "t_end_ns": start_ns + int(round(h.t_end_s * 1e9)),
                "case_temp_c_mean": float(case_c[inside].mean()) if inside.any() else None,
            }
        )
    plateau_temps = sorted({h["setpoint_c"] for h in holds})
    k, u0 = unit.constants_at(np.array(plateau_temps))
    return {
        "schema": "thermocal.sim_truth/1",
        "unit_serial": config.unit_serial,
        "run_id": meta.run_id,
        "program": get_program(config.program).name,
        "duration_s": timetable.duration_s,
        **lags_s,
        "unit": unit.to_dict(),
        "unit_constants_at": [
            {"temp_c": t, "K": k[i].tolist(), "U0": u0[i].tolist()} for i, t in enumerate(plateau_temps)
        ],
        "effects": [{"id": e.id, "params": e.params()} for e in effects if e.id in EFFECTS],
        "disturbances": [{"id": e.id, "params": e.params()} for e in effects if e.id not in EFFECTS],
        "position_vectors_g": {p: vectors_g[i].tolist() for i, p in enumerate(POSITION_NAMES)},
        "holds": holds,
        "config": dataclasses.asdict(config),
        "metadata": meta.to_strings(),
    }


def voltmeter_t_ns(start_ns: int, k: np.ndarray, config: SimConfig, rng: np.random.Generator) -> np.ndarray:
    """Voltmeter time stamps (ns) of sample numbers ``k``: the nominal grid at ``config.rate_hz`` plus, when
    ``config.jitter_s`` > 0, Gaussian jitter (s) clipped to 0.45 of a sample interval so the order is kept."""
    t_ns = start_ns + np.round(k * (1e9 / config.rate_hz)).astype(np.int64)
    if config.jitter_s > 0:
        lim = 0.45 / config.rate_hz
        t_ns += np.round(np.clip(rng.normal(0.0, config.jitter_s, k.size), -lim, lim) * 1e9).astype(np.int64)
    return t_ns


def output_with_effects_v(
    ctx: SignalContext, effects: list, disturbances: list, noise_v: float, rng: np.random.Generator
) -> np.ndarray:
    """The unit's outputs (n, 3) in V: U = K a + U0 at each sample's temperature, plus every effect acting on the
    output (a face error is already in ``ctx.a_g``), every disturbance, and white noise of ``noise_v`` V."""
    u_v = output_v(*ctx.k_u0, ctx.a_g)
    for e in effects:
        if e.acts_on != "specific_force":
            u_v += e.delta_u_v(ctx)
    for d in disturbances:
        u_v += d.delta_u_v(ctx)
    if noise_v > 0:
        u_v += rng.normal(0.0, noise_v, u_v.shape)
    return u_v
