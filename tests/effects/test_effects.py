"""Each catalogue effect changes the simulated signal where docs/physics.md says it shows, and nowhere else.

Every test compares a noise-free standard run (1 Hz voltmeter) with and without one effect, same seed.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.dynamics import ramp_sign_from_temperature
from pipeline.effects.base import SignalContext
from pipeline.effects.catalogue import EFFECTS, make_effect, parse_effect_spec
from pipeline.effects.fixture_face_error import FixtureFaceError
from pipeline.effects.tilt_settling import TiltSettling
from pipeline.model import output_v
from pipeline.positions import gravity_vector_g
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.program import standard_program
from pipeline.simulate.unit import seed000_unit

CATALOGUE = [
    "thermal_lag",
    "thermal_hysteresis",
    "time_drift",
    "warmup_transient",
    "temperature_curvature",
    "scale_nonlinearity",
    "fixture_face_error",
    "tilt_settling",
]
TIMETABLE = standard_program().timetable()
UV = 1e-6


def config(*effects) -> SimConfig:
    return SimConfig(rate_hz=1.0, noise_v=0.0, temp_noise_c=0.0, effects=list(effects))


@pytest.fixture(scope="module")
def base():
    return simulate(config())


@pytest.fixture(scope="module")
def diff(base):
    """diff(effect_id, **params) -> (with - without) voltages (n, 3) and the run with the effect."""
    cache = {}

    def run(effect_id, **params):
        key = repr((effect_id, sorted(params.items())))
        if key not in cache:
            res = simulate(config((effect_id, params)))
            cache[key] = (res.run.u_v() - base.run.u_v(), res)
        return cache[key]

    return run


def t_s(base):
    return base.context.t_s


def hold_mask(base, hold, late_fraction=0.5):
    t = base.run.t_ns()
    start = hold["t_start_ns"] + late_fraction * (hold["t_end_ns"] - hold["t_start_ns"])
    return (t >= start) & (t < hold["t_end_ns"])


def late_holds(base, late_fraction=0.5):
    m = np.zeros(base.run.t_ns().size, dtype=bool)
    for h in base.truth["holds"]:
        m |= hold_mask(base, h, late_fraction)
    return m


def kind_mask(base, kind):
    t = t_s(base)
    m = np.zeros(t.size, dtype=bool)
    for s in TIMETABLE.segments:
        if s.kind == kind:
            m |= (t >= s.t_start_s) & (t < s.t_end_s)
    return m


def since_segment_start(t):
    starts = np.array([s.t_start_s for s in TIMETABLE.segments])
    return t - starts[np.searchsorted(starts, t, side="right") - 1]


def holds_where(base, setpoint_c=None, position=None, stage=None):
    return [
        h
        for h in base.truth["holds"]
        if (setpoint_c is None or h["setpoint_c"] == setpoint_c)
        and (position is None or h["position"] == position)
        and (stage is None or h["stage"] == stage)
    ]


def mean_in(d, base, hold, late_fraction=0.5):
    return d[hold_mask(base, hold, late_fraction)].mean(axis=0)


def test_catalogue_ids():
    assert list(EFFECTS) == CATALOGUE
    for eid in CATALOGUE:
        effect = make_effect(eid)
        assert effect.id == eid and effect.params()
        # Every parameter has its unit (or is dimensionless / a seed) in its name.
        for name in effect.params():
            assert name in ("f", "seed") or name.rsplit("_", 1)[-1] in ("s", "v", "h", "c3", "g2", "deg", "rad")


# ----------------------------------------------------------------------------------------------------------------
# One test per effect


def test_thermal_lag(base, diff):
    tau_s = 120.0
    d, _ = diff("thermal_lag", tau_s=tau_s)
    ramps = kind_mask(base, "ramp")
    # Large during ramps (about tau * dT/dt = 2 C of lag), tiny on soaked plateaus.
    assert np.abs(d[ramps]).max() > 100 * UV
    assert np.abs(d[late_holds(base)]).max() < 1 * UV
    # Quantitatively: once the lag has settled in a ramp, T_e = T - tau dT/dt + tau^2 d2T/dt2 (the case temperature
    # itself still bends), so the sign of d follows the direction of the ramp.
    ctx = base.context
    unit = seed000_unit()
    dtdt = np.gradient(ctx.temp_c, ctx.t_s)
    lagged_c = ctx.temp_c - tau_s * dtdt + tau_s**2 * np.gradient(dtdt, ctx.t_s)
    k_e, u0_e = unit.constants_at(lagged_c)
    predicted = output_v(k_e, u0_e, ctx.a_g) - ctx.model_output_v()
    steady = ramps & (since_segment_start(ctx.t_s) > 1200)
    assert steady.sum() > 5000
    np.testing.assert_allclose(d[steady], predicted[steady], rtol=0.02, atol=0.5 * UV)
    heating = steady & (dtdt > 0)
    cooling = steady & (dtdt < 0)
    assert heating.any() and cooling.any()
    # Early in the soak after the first ramp it is still there.
    first_soak_start = [s for s in TIMETABLE.segments if s.kind == "soak"][1].t_start_s
    assert np.abs(d[ctx.t_s == first_soak_start + 60]).max() > 20 * UV
    # Nothing before the first ramp (the unit starts soaked).
    assert np.abs(d[ctx.t_s < 5500]).max() < 1e-12


def test_thermal_hysteresis(base, diff):
    h_v = np.array([50e-6, -40e-6, 30e-6])
    d, _ = diff("thermal_hysteresis")
    stage = TIMETABLE.stage_index(t_s(base))
    np.testing.assert_array_equal(d[stage == 0], 0.0)  # before the first ramp
    # +20 C from below (stage 4, after heating from -10) and from above (stage 7, after cooling from +70).
    for position in ("TP1", "TP4", "VP2"):
        below = mean_in(d, base, holds_where(base, 20.0, position, stage=3)[0])
        above = mean_in(d, base, holds_where(base, 20.0, position, stage=6)[0])
        np.testing.assert_allclose(below - above, 2 * h_v, rtol=1e-9)
        np.testing.assert_allclose(below, h_v, rtol=1e-9)
    # Soaked -40 C came from above (cooling): -h.
    np.testing.assert_allclose(mean_in(d, base, holds_where(base, -40.0, "TP3")[0]), -h_v, rtol=1e-9)


def test_time_drift(base, diff):
    d, _ = diff("time_drift", r_v_per_h_y=-6e-6)
    t = t_s(base)
    r_v_per_h = np.array([3e-6, -6e-6, 4e-6])
    np.testing.assert_allclose(d, t[:, None] / 3600 * r_v_per_h, rtol=0, atol=1e-15)
    # Revisits of +20 C in TP1 drift monotonically with time.
    revisits = [mean_in(d, base, h)[0] for h in holds_where(base, 20.0, "TP1")]
    assert len(revisits) == 3 and np.all(np.diff(revisits) > 5 * UV)


def test_warmup_transient(base, diff):
    d, _ = diff("warmup_transient", tau_s=600.0)
    t = t_s(base)
    a_v = np.array([300e-6, -200e-6, 150e-6])
    np.testing.assert_allclose(d[0], a_v, rtol=1e-12)
    np.testing.assert_allclose(d[t == 600.0][0], a_v / np.e, rtol=1e-9)
    # Only early in the first plateau: below 1 % of A from 5 tau on, and the first hold of each later
    # plateau sees nothing.
    assert np.all(np.abs(d[t >= 3000]) < 0.01 * np.abs(a_v))
    assert np.abs(mean_in(d, base, holds_where(base, -40.0, "TP1")[0])).max() < 1e-9
    early = t < 3000
    assert np.all(np.diff(np.abs(d[early])) <= 0)  # decays monotonically


def test_temperature_curvature(base, diff):
    c_v_per_c3 = np.array([1.5e-9, -1e-9, 1e-9])
    c_rel_per_c3 = np.array([1e-9, 1.5e-9, -1e-9])
    d, _ = diff("temperature_curvature")
    unit = seed000_unit()
    # Zero at T0: the first +20 C plateau is soaked at exactly 20 C.
    np.testing.assert_array_equal(d[TIMETABLE.stage_index(t_s(base)) == 0], 0.0)
    # Grows as dT^3: x channel in TP1 (a_x = 0) is c_x dT^3 at every plateau.
    for sp in (-40.0, 70.0):
        hold = holds_where(base, sp, "TP1")[0]
        m = hold_mask(base, hold)
        dt = base.context.temp_c[m] - 20.0
        np.testing.assert_allclose(d[m, 0], c_v_per_c3[0] * dt**3, rtol=1e-6)
        np.testing.assert_allclose(d[m, 1], c_v_per_c3[1] * dt**3, rtol=1e-6)
        # z in TP1 also sees the gain term, Kzz (1 + c_rel dT^3).
        k, _ = unit.constants_at(base.context.temp_c[m])
        np.testing.assert_allclose(d[m, 2], (c_v_per_c3[2] + k[:, 2, 2] * c_rel_per_c3[2]) * dt**3, rtol=1e-6)
    # The -40 C value is (-60/50)^3 times the +70 C value for the offset-only channel.
    r = mean_in(d, base, holds_where(base, -40.0, "TP1")[0])[0] / mean_in(d, base, holds_where(base, 70.0, "TP1")[0])[0]
    assert r == pytest.approx((-60 / 50) ** 3, rel=1e-3)
    # Between calibration temperatures (-10 C VP plateau) it is of an engineer's size.
    assert np.abs(mean_in(d, base, holds_where(base, -10.0, "VP1")[0])).max() > 20 * UV


def test_scale_nonlinearity(base, diff):
    k2 = np.array([30e-6, -20e-6, 25e-6])
    d, _ = diff("scale_nonlinearity")
    for hold in base.truth["holds"]:
        a = gravity_vector_g(hold["position"])
        np.testing.assert_allclose(mean_in(d, base, hold), k2 * a**2, rtol=0, atol=1e-15)
    # Only in channels with a nonzero component of a, and the same for +1 g and -1 g.
    tp1, tp3 = holds_where(base, 20.0, "TP1")[0], holds_where(base, 20.0, "TP3")[0]
    np.testing.assert_array_equal(mean_in(d, base, tp1)[:2], 0.0)
    assert mean_in(d, base, tp1)[2] == mean_in(d, base, tp3)[2] == pytest.approx(k2[2])
    tp5, tp6 = holds_where(base, 20.0, "TP5")[0], holds_where(base, 20.0, "TP6")[0]
    assert mean_in(d, base, tp5)[0] == pytest.approx(mean_in(d, base, tp6)[0], abs=1e-15)


def test_fixture_face_error_explicit(base, diff):
    delta_rad = {"TP1": (2e-4, -1e-4, 0.0), "VP3": (0.0, 0.0, 3e-4)}
    d, _ = diff("fixture_face_error", delta_rad=delta_rad)
    unit = seed000_unit()
    for hold in base.truth["holds"]:
        m = hold_mask(base, hold)
        if hold["position"] not in delta_rad:
            np.testing.assert_array_equal(d[m], 0.0)
            continue
        a = gravity_vector_g(hold["position"])
        k, _ = unit.constants_at(base.context.temp_c[m])
        first_order = np.einsum("nij,j->ni", k, np.cross(delta_rad[hold["position"]], a))
        np.testing.assert_allclose(d[m], first_order, rtol=0, atol=1e-7)
    # Constant in temperature: TP1 at -40, +20, +70 C agree within the (small) change of K with T.
    tp1 = np.array([mean_in(d, base, holds_where(base, sp, "TP1")[0]) for sp in (-40.0, 20.0, 70.0)])
    np.testing.assert_allclose(tp1, tp1[1][None].repeat(3, 0), rtol=0.01, atol=0.1 * UV)
    # Horizontal channels carry it; the vertical channel only to second order.
    assert (
        np.abs(tp1[:, :2]).min() > 50 * UV
        and np.abs(
            tp1[:, 2]
            - np.einsum("ij,j->i", unit.constants_at(np.array([20.0]))[0][0], np.cross(delta_rad["TP1"], (0, 0, 1)))[2]
        ).max()
        < 0.1 * UV
    )


def test_fixture_face_error_seeded(base, diff):
    d, _ = diff("fixture_face_error", sigma_deg=0.01, seed=7)
    per_position = {}
    for hold in base.truth["holds"]:
        per_position.setdefault(hold["position"], []).append(mean_in(d, base, hold))
    spread = [np.ptp(np.array(v), axis=0).max() for v in per_position.values()]
    level = [np.abs(np.array(v)).max() for v in per_position.values()]
    assert max(spread) < 2 * UV  # constant in temperature (and time) per position
    assert np.median(level) > 20 * UV  # 0.01 deg is about 100 uV on a horizontal channel
    assert len({round(float(v[0][0]) / UV) for v in per_position.values()}) == 12  # each face its own
    # The diagnosis form (delta_u_v on a context with nominal a) gives the same change on static samples.
    effect = make_effect("fixture_face_error", {"sigma_deg": 0.01, "seed": 7})
    static = base.context.position_idx >= 0
    np.testing.assert_allclose(effect.delta_u_v(base.context)[static], d[static], rtol=0, atol=1e-12)


def test_tilt_settling(base, diff):
    f, tau_s = 2e-4, 30.0
    d, _ = diff("tilt_settling", f=f, tau_s=tau_s)
    t = t_s(base)
    u = base.run.u_v()
    np.testing.assert_array_equal(d[t < 3920], 0.0)  # nothing before the first arrival
    starts, arrivals = TIMETABLE.move_times_s()
    assert arrivals.size == 53
    for t_start, t_arrive in zip(starts, arrivals):
        i, i_before = np.searchsorted(t, [t_arrive, t_start - 1])
        jump = u[i] - u[i_before]  # U_new - U_old, at the temperature of the move
        np.testing.assert_allclose(d[i], -f * jump, rtol=1e-3, atol=1e-3 * UV)
        np.testing.assert_allclose(d[i + int(tau_s)], d[i] / np.e, rtol=1e-6, atol=1e-12)
    # Decayed in the late part of every hold (more than 7 tau after arrival) and during ramps.
    assert np.abs(d[late_holds(base, 0.7)]).max() < 0.5 * UV
    assert np.abs(d[kind_mask(base, "ramp")]).max() < 0.1 * UV


def test_effects_add_nothing_in_noise_free_run_without_them(base):
    again = simulate(config())
    assert again.run.voltmeter.equals(base.run.voltmeter)


# ----------------------------------------------------------------------------------------------------------------
# Building blocks for the diagnosis


def test_ramp_sign_from_recorded_temperature_matches_the_program(base):
    temp = base.run.au_temperature
    t_rec = (temp["t_ns"].to_numpy() - temp["t_ns"][0]) / 1e9
    sign = ramp_sign_from_temperature(t_rec, temp["temp_c"].to_numpy())
    static_late = np.zeros(t_rec.size, dtype=bool)
    for h in base.truth["holds"]:
        static_late |= (temp["t_ns"].to_numpy() >= h["t_start_ns"]) & (temp["t_ns"].to_numpy() < h["t_end_ns"])
    np.testing.assert_array_equal(sign[static_late], TIMETABLE.ramp_sign(t_rec[static_late]))


def test_effects_on_a_hand_built_context():
    """delta_u_v works on any context, e.g. one built from a recording with nominal positions."""
    t = np.arange(0.0, 200.0, 0.5)
    a = np.where((t < 100)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    ctx = SignalContext(
        t_s=t,
        temp_c=np.full(t.size, 20.0),
        a_g=a,
        position_idx=np.where(t < 100, 0, 5),
        move_start_s=np.array([100.0]),
        arrive_s=np.array([100.0]),
        constants=seed000_unit(),
        normal_temp_c=20.0,
        ramp_sign=None,
    )
    du = TiltSettling(f=1e-3, tau_s=10.0).delta_u_v(ctx)
    k = np.array(seed000_unit().k_coef[0])
    np.testing.assert_allclose(du[t == 100.0][0], -1e-3 * k @ np.array([1.0, 0.0, -1.0]), rtol=1e-12)
    np.testing.assert_array_equal(du[t < 100], 0.0)
    face = FixtureFaceError(delta_rad={"TP1": (1e-4, 0.0, 0.0)})
    du = face.delta_u_v(ctx)
    np.testing.assert_allclose(du[0], k @ np.cross([1e-4, 0, 0], [0, 0, 1]), rtol=0, atol=1e-8)  # first order
    np.testing.assert_array_equal(du[t >= 100], 0.0)
    for eid in CATALOGUE:
        assert make_effect(eid).delta_u_v(ctx).shape == (t.size, 3)
    assert np.all(make_effect("thermal_hysteresis").delta_u_v(ctx) == 0.0)  # ramp_sign None: no ramp yet
    # The thermal-lag hook: the element temperature lags a step with tau.
    step = SignalContext(
        t_s=t,
        temp_c=np.where(t < 50, 20.0, 30.0),
        a_g=a,
        position_idx=np.zeros(t.size, int),
        move_start_s=np.array([]),
        arrive_s=np.array([]),
        constants=seed000_unit(),
    )
    te = make_effect("thermal_lag", {"tau_s": 20.0}).element_temperature_c(step)
    after = t >= 50
    np.testing.assert_allclose(te[after], 30 - 10 * np.exp(-(t[after] - 49.75) / 20.0), atol=2e-3)
    np.testing.assert_array_equal(te[t < 49.5], 20.0)


# ----------------------------------------------------------------------------------------------------------------
# The CLI syntax


def test_parse_effect_spec_defaults_and_overrides():
    assert parse_effect_spec("thermal_lag") == ("thermal_lag", {"tau_s": 120.0})
    assert parse_effect_spec(" thermal_lag:tau_s=60 ") == ("thermal_lag", {"tau_s": 60.0})
    assert parse_effect_spec("thermal_hysteresis:h_v=1e-5")[1] == {"h_v": [1e-5, 1e-5, 1e-5]}
    assert parse_effect_spec("thermal_hysteresis:h_v_y=2e-5")[1] == {"h_v": [50e-6, 2e-5, 30e-6]}
    assert parse_effect_spec("warmup_transient:a_v=1e-4,a_v_z=0,tau_s=300")[1] == {
        "a_v": [1e-4, 1e-4, 0.0],
        "tau_s": 300.0,
    }
    eid, params = parse_effect_spec("fixture_face_error:sigma_deg=0.02,seed=3")
    assert eid == "fixture_face_error" and params["seed"] == 3 and params["sigma_deg"] == 0.02
    assert set(params["delta_rad"]) == {f"TP{i}" for i in range(1, 7)} | {f"VP{i}" for i in range(1, 7)}
    # The parsed parameters rebuild the same effect (the resolved face errors are explicit).
    again = make_effect(eid, params)
    np.testing.assert_array_equal(again.rotation_vectors_rad()["VP4"], params["delta_rad"]["VP4"])
    assert make_effect("scale_nonlinearity", {"k2_v_per_g2": [1e-6, 2e-6, 3e-6]}).k2_v_per_g2 == (1e-6, 2e-6, 3e-6)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("nope", "unknown effect 'nope'"),
        ("thermal_lag:tau=3", "has no parameter 'tau'"),
        ("thermal_lag:tau_s=abc", "not a number"),
        ("thermal_lag:", "no parameters"),
        ("thermal_lag:tau_s", "expected name=value"),
        ("thermal_lag:tau_s=inf", "not a finite number"),
        ("fixture_face_error:seed=1.5", "needs an integer"),
        ("thermal_hysteresis:h_v_w=1", "has no parameter 'h_v_w'"),
        ("warmup_transient:tau_s=-1", "must not be negative"),
        ("tilt_settling:tau_s=0", "must be positive"),
    ],
)
def test_parse_effect_spec_errors(spec, message):
    with pytest.raises(ValueError, match=message):
        parse_effect_spec(spec)


def test_make_effect_vector_errors():
    with pytest.raises(ValueError, match="needs 3 values"):
        make_effect("time_drift", {"r_v_per_h": [1.0, 2.0]})
    with pytest.raises(ValueError, match="unknown positions"):
        make_effect("fixture_face_error", {"delta_rad": {"TP9": (0, 0, 0)}})
