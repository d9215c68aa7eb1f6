"""The simulator against its own truth: unit constants, program timetable, temperatures, voltages, noise, logs."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.dynamics import first_order_lag
from pipeline.model import output_v
from pipeline.positions import MOVING, VERIFICATION_POSITIONS, gravity_vector_g
from pipeline.run import RunMeta
from pipeline.simulate.chamber import SimConfig, parse_utc_ns, simulate, write_truth
from pipeline.simulate.program import (
    PROGRAMS,
    Hold,
    Move,
    Program,
    Ramp,
    Soak,
    Stage,
    get_program,
    short_program,
    standard_program,
)
from pipeline.simulate.unit import UnitTruth, random_unit, seed000_tables, seed000_unit

SHARED = Path(__file__).resolve().parents[3] / "shared"
TP = ["TP1", "TP2", "TP3", "TP4", "TP5", "TP6"]
VP = ["VP1", "VP2", "VP3", "VP4", "VP5", "VP6"]


@pytest.fixture(scope="module")
def clean():
    """The standard program at 10 Hz, no voltage or temperature noise."""
    return simulate(SimConfig(noise_v=0.0, temp_noise_c=0.0))


@pytest.fixture(scope="module")
def noisy():
    """The standard program at 10 Hz with the default noise."""
    return simulate(SimConfig())


def hold_mask(run, hold, late_fraction=0.5):
    """Voltmeter samples in the late part of a static hold."""
    t = run.t_ns()
    start = hold["t_start_ns"] + late_fraction * (hold["t_end_ns"] - hold["t_start_ns"])
    return (t >= start) & (t < hold["t_end_ns"])


# ----------------------------------------------------------------------------------------------------------------
# The unit


def test_seed000_unit_reproduces_the_three_tables():
    unit = seed000_unit()
    tables = seed000_tables()
    k, u0 = unit.constants_at(np.array([t["temp_c"] for t in tables]))
    for i, t in enumerate(tables):
        np.testing.assert_allclose(k[i], t["K"], rtol=0, atol=1e-14)
        np.testing.assert_allclose(u0[i], t["U0"], rtol=0, atol=1e-15)
    assert unit.order == 2
    # Row 0 is the +20 C table itself.
    np.testing.assert_array_equal(unit.k_coef[0], np.array(tables[0]["K"]))


#: sha256 of shared/reference/seed000_tables.json, which pipeline/simulate/data/seed000_tables.json copies byte for
#: byte: a clone without ../shared still checks its copy
SEED000_TABLES_SHA256 = "7e89175f7ab82e48c660f597290c62d9eff6e493aeba322f5ac51853134521b3"


def test_seed000_tables_match_the_shared_reference():
    copy = Path(__file__).resolve().parents[2] / "pipeline" / "simulate" / "data" / "seed000_tables.json"
    assert hashlib.sha256(copy.read_bytes()).hexdigest() == SEED000_TABLES_SHA256
    assert json.loads(copy.read_text())["table_1_2_constants"] == seed000_tables()
    ref = SHARED / "reference" / "seed000_tables.json"
    if ref.exists():  # beside the shared reference: it is still the file the digest names
        assert hashlib.sha256(ref.read_bytes()).hexdigest() == SEED000_TABLES_SHA256


def test_seed000_unit_other_normal_temperature_is_the_same_function():
    a, b = seed000_unit(20.0), seed000_unit(25.0)
    temps = np.linspace(-50, 80, 27)
    for x, y in zip(a.constants_at(temps), b.constants_at(temps)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-13)
    assert b.normal_temp_c == 25.0


def test_unit_dict_round_trip_is_exact():
    unit = random_unit(3)
    again = UnitTruth.from_dict(json.loads(json.dumps(unit.to_dict())))
    temps = np.array([-40.0, -10.0, 20.0, 45.0, 70.0])
    for x, y in zip(unit.constants_at(temps), again.constants_at(temps)):
        np.testing.assert_array_equal(x, y)
    assert again.label == "random:3"
    rel = unit.to_dict()["thermal_model"]
    assert rel["kind"] == "polynomial" and rel["order"] == 2
    assert set(rel["alpha"]) == {"x", "y", "z"} and set(rel["beta"]) == {"xx", "yy", "zz"}
    assert set(rel["gamma"]) == {"xy", "xz", "yx", "yz", "zx", "zy"}


def test_relative_coefficients_describe_the_same_model():
    unit = seed000_unit()
    rel = unit.relative_coefficients()
    k0, u00 = unit.constants_at(np.array([20.0]))
    k, u0 = unit.constants_at(np.array([55.0]))
    dt = 35.0
    assert u0[0, 1] == pytest.approx(
        u00[0, 1] + sum(c * dt ** (n + 1) for n, c in enumerate(rel["alpha"]["y"])), abs=1e-15
    )
    assert k[0, 2, 2] == pytest.approx(
        k0[0, 2, 2] * (1 + sum(c * dt ** (n + 1) for n, c in enumerate(rel["beta"]["zz"]))), abs=1e-15
    )
    assert k[0, 0, 2] == pytest.approx(
        k0[0, 0, 2] * (1 + sum(c * dt ** (n + 1) for n, c in enumerate(rel["gamma"]["xz"]))), abs=1e-15
    )


@pytest.mark.parametrize("seed", range(12))
def test_random_unit_magnitudes(seed):
    unit = random_unit(seed)
    k, u0 = unit.constants_at(np.array([20.0, -40.0, 70.0]))
    diag = np.eye(3, dtype=bool)
    gains = k[0][diag]
    assert np.all(np.abs(gains / -0.55 - 1) <= 0.01)
    cas = np.abs(k[0][~diag])
    assert np.all((cas >= 3e-4) & (cas <= 0.016))
    assert np.all((np.abs(u0[0]) >= 1e-3) & (np.abs(u0[0]) <= 5e-3))
    for i, dt in ((1, -60.0), (2, 50.0)):  # chord slopes of the two sub-bands (docs/physics.md "Typical magnitudes")
        alpha = np.abs((u0[i] - u0[0]) / dt)
        rel = np.abs((k[i] - k[0]) / (k[0] * dt))
        assert np.all((alpha >= 1.5e-5 * 0.999) & (alpha <= 1.5e-4 * 1.001))
        assert np.all((rel[diag] >= 1e-5 * 0.999) & (rel[diag] <= 5e-5 * 1.001))
        assert np.all((rel[~diag] >= 1e-4 * 0.999) & (rel[~diag] <= 6e-3 * 1.001))
    # Reproducible, and seeds differ.
    np.testing.assert_array_equal(random_unit(seed).k_coef, unit.k_coef)
    assert not np.allclose(random_unit(seed + 100).k_coef[0], unit.k_coef[0])


def test_random_units_have_both_signs_of_cross_axis_sensitivity():
    signs = np.concatenate([np.sign(random_unit(s).k_coef[0][~np.eye(3, dtype=bool)]) for s in range(10)])
    assert 20 < np.sum(signs > 0) < 70


# ----------------------------------------------------------------------------------------------------------------
# The programs


def test_standard_program_timetable():
    program = standard_program()
    assert len(program.stages) == 7 and program.start_position == "TP1" and program.start_setpoint_c == 20.0
    tt = program.timetable()
    holds = tt.holds()
    expected = [(20.0, TP), (-40.0, TP), (-10.0, VP), (20.0, TP + VP), (45.0, VP), (70.0, TP), (20.0, TP + VP)]
    assert [(h.setpoint_start_c, h.position) for h in holds] == [(sp, p) for sp, ps in expected for p in ps]
    assert all(h.t_end_s - h.t_start_s == 300.0 for h in holds)
    moves = tt.moves()
    assert len(moves) == len(holds) - 1  # every hold but the first (TP1, already there) starts with a move
    assert all(m.t_end_s - m.t_start_s == 20.0 for m in moves)
    ramps = [s for s in tt.segments if s.kind == "ramp"]
    assert [s.setpoint_end_c for s in ramps] == [-40.0, -10.0, 20.0, 45.0, 70.0, 20.0]
    for s in ramps:  # 1 C/min
        assert s.t_end_s - s.t_start_s == pytest.approx(abs(s.setpoint_end_c - s.setpoint_start_c) * 60.0)
    soaks = [s.t_end_s - s.t_start_s for s in tt.segments if s.kind == "soak"]
    assert soaks == [3600.0, 5400.0, 3600.0, 3600.0, 3600.0, 5400.0, 3600.0]
    assert tt.duration_s == 59260.0  # about 16.5 h
    # During ramps and soaks the unit stays in the last position; segments tile the time line.
    for prev, seg in zip(tt.segments, tt.segments[1:]):
        assert seg.t_start_s == prev.t_end_s
        if seg.kind in ("ramp", "soak") and prev.kind != "move":
            assert seg.position == prev.position
    assert [s.position for s in tt.segments if s.kind == "ramp"] == ["TP6", "TP6", "VP6", "VP6", "VP6", "TP6"]


def test_timetable_vectorised_queries():
    tt = standard_program().timetable()
    t = np.array([0.0, 3600.0, 3899.9, 3900.0, 3910.0, 3920.0, 5500.0 + 1800.0, 59259.0])
    np.testing.assert_allclose(tt.setpoint_c(t), [20, 20, 20, 20, 20, 20, -10, 20])
    assert list(tt.positions(t)) == ["TP1", "TP1", "TP1", MOVING, MOVING, "TP2", "TP6", "VP6"]
    np.testing.assert_array_equal(tt.ramp_sign(np.array([0.0, 5499.0, 5501.0, 16420.0 + 1.0])), [0, 0, -1, 1])
    start, end = tt.move_times_s()
    assert start[0] == 3900.0 and end[0] == 3920.0 and np.all(end - start == 20.0)


def test_short_program_is_the_same_sequence_shorter():
    std, short = standard_program().timetable(), short_program().timetable()
    assert [(h.setpoint_start_c, h.position) for h in std.holds()] == [
        (h.setpoint_start_c, h.position) for h in short.holds()
    ]
    assert all(h.t_end_s - h.t_start_s == 60.0 for h in short.holds())
    assert all(m.t_end_s - m.t_start_s == 10.0 for m in short.moves())
    assert short.duration_s < 4 * 3600
    assert short_program().case_lag_s == 120.0 and standard_program().case_lag_s == 600.0


def test_differential_program_holds_orientations_through_cycles():
    tt = get_program("differential").timetable()
    assert [h.position for h in tt.holds()] == [f"TP{k}" for k in range(1, 7)]  # seed 003: six orientations
    t = np.arange(0.0, tt.duration_s, 10.0)
    sp = tt.setpoint_c(t)
    assert sp.min() == -40.0 and sp.max() == 70.0
    assert np.all(tt.position_index(t[sp != 20.0]) >= 0)  # never moves while the temperature cycles


def test_program_errors():
    with pytest.raises(ValueError, match="unknown chamber program"):
        get_program("nope")
    with pytest.raises(ValueError, match="Hold TP2 while the unit is in TP1"):
        Program("bad", (Stage("x", (Soak(10.0), Hold("TP2", 10.0))),)).timetable()
    with pytest.raises(ValueError, match="unknown position"):
        Program("bad", (Stage("x", (Move("TP9"),)),)).timetable()
    with pytest.raises(ValueError, match="ramp rate"):
        Program("bad", (Stage("x", (Ramp(30.0, 0.0),)),)).timetable()
    assert set(PROGRAMS) == {"standard", "short", "differential", "handheld", "sweep", "fast"}


# ----------------------------------------------------------------------------------------------------------------
# Temperatures


def test_first_order_lag_is_exact_for_a_ramp():
    t = np.arange(0.0, 3000.0, 1.0)
    rate, tau = 0.02, 300.0
    y = first_order_lag(t, rate * t, tau)
    np.testing.assert_allclose(y, rate * (t - tau * (1 - np.exp(-t / tau))), atol=1e-12)
    # A non-uniform grid gives the same answer (resampled).
    tn = np.sort(np.concatenate([t[::7], t[3::11] + 0.5]))
    np.testing.assert_allclose(
        first_order_lag(tn, rate * tn, tau), rate * (tn - tau * (1 - np.exp(-tn / tau))), atol=1e-3
    )


@pytest.mark.parametrize("case_lag_s", [None, 900.0])
def test_case_follows_air_with_the_configured_lag(case_lag_s):
    res = simulate(SimConfig(rate_hz=0.2, noise_v=0.0, temp_noise_c=0.0, case_lag_s=case_lag_s))
    tau = 600.0 if case_lag_s is None else case_lag_s
    assert res.truth["case_lag_s"] == tau
    ch, temp = res.run.chamber, res.run.au_temperature
    t_s = (temp["t_ns"].to_numpy() - temp["t_ns"][0]) / 1e9
    case, setpoint, air = temp["temp_c"].to_numpy(), ch["setpoint_c"].to_numpy(), ch["air_c"].to_numpy()
    np.testing.assert_array_equal(ch["t_ns"].to_numpy(), temp["t_ns"].to_numpy())
    # Long soak at -40 C (after the first ramp, 5500 + 3600 s .. + 5400 s): the approach is exp(-t/tau).
    soak_start = 5500.0 + 3600.0
    window = (t_s >= soak_start + 1500) & (t_s <= soak_start + 4500)
    slope = np.polyfit(t_s[window], np.log(np.abs(case[window] - setpoint[window])), 1)[0]
    assert -1.0 / slope == pytest.approx(tau, rel=0.01)
    # Ramp from soaked: two first-order lags in cascade (air 90 s, case tau), exact solution.
    ramp = (t_s >= 5500) & (t_s <= 5500 + 3600)
    u = t_s[ramp] - 5500
    rate_c_per_s, tau_air = -1.0 / 60.0, 90.0
    lag_air = rate_c_per_s * tau_air * (1 - np.exp(-u / tau_air))
    lag_case = rate_c_per_s * (
        tau_air + tau - (tau_air**2 * np.exp(-u / tau_air) - tau**2 * np.exp(-u / tau)) / (tau_air - tau)
    )
    np.testing.assert_allclose(setpoint[ramp] - air[ramp], lag_air, atol=1e-6)
    np.testing.assert_allclose(setpoint[ramp] - case[ramp], lag_case, atol=1e-4)
    assert case[ramp][-1] - setpoint[ramp][-1] == pytest.approx(-rate_c_per_s * (tau_air + tau), rel=0.05)
    # Soaked at the end of the -40 soak (within 0.01 C for the default 10 min lag).
    if case_lag_s is None:
        assert abs(case[int(soak_start + 5399)] + 40.0) < 0.01


def test_thermosensor_noise(noisy):
    truth_c = noisy.context.temp_c[::10]  # 10 Hz voltmeter grid, 1 Hz thermosensor: same instants
    recorded = noisy.run.au_temperature["temp_c"].to_numpy()
    assert recorded.size == truth_c.size
    assert np.std(recorded - truth_c) == pytest.approx(0.01, rel=0.02)
    assert abs(np.mean(recorded - truth_c)) < 4 * 0.01 / np.sqrt(recorded.size)


# ----------------------------------------------------------------------------------------------------------------
# Voltages


def test_noise_free_outputs_are_the_model_at_the_recorded_temperature(clean):
    run, unit = clean.run, seed000_unit()
    t = run.t_ns()
    k, u0 = unit.constants_at(run.temperature_at(t))
    u = run.u_v()
    assert len(clean.truth["holds"]) == 54
    for hold in clean.truth["holds"]:
        m = hold_mask(run, hold)
        assert m.sum() == 1500
        expected = output_v(k[m], u0[m], gravity_vector_g(hold["position"]))
        np.testing.assert_allclose(u[m], expected, rtol=0, atol=1e-9, err_msg=str(hold))
    # The +20 / -40 / +70 C plateaus carry the table constants: TP1 - TP3 over 2 is the z column of K.
    for table in seed000_tables():
        sel = [h for h in clean.truth["holds"] if h["setpoint_c"] == table["temp_c"] and h["position"] in TP]
        mean = {h["position"]: u[hold_mask(run, h, 0.9)].mean(axis=0) for h in sel[:6]}
        np.testing.assert_allclose((mean["TP1"] - mean["TP3"]) / 2, np.array(table["K"])[:, 2], atol=2e-6)


def test_noisy_plateaus_average_to_the_model(noisy):
    run, ctx = noisy.run, noisy.context
    residual = run.u_v() - ctx.model_output_v()
    static = ctx.position_idx >= 0
    assert np.std(residual[static], axis=0) == pytest.approx(np.full(3, 5e-6), rel=0.01)
    # White: no correlation between neighbouring samples or between channels.
    r = residual[static]
    assert abs(np.corrcoef(r[1:, 0], r[:-1, 0])[0, 1]) < 0.01
    assert abs(np.corrcoef(r[:, 0], r[:, 2])[0, 1]) < 0.01
    # Plateau means against the model at the *recorded* temperature (its 0.01 C noise averages out too).
    unit = seed000_unit()
    k, u0 = unit.constants_at(run.temperature_at(run.t_ns()))
    u = run.u_v()
    z = []
    for hold in noisy.truth["holds"]:
        m = hold_mask(run, hold)
        diff = (u[m] - output_v(k[m], u0[m], gravity_vector_g(hold["position"]))).mean(axis=0)
        z.append(diff / (5e-6 / np.sqrt(m.sum())))
    z = np.abs(np.array(z))
    assert z.max() < 5.0 and np.mean(z**2) < 2.0


def test_moves_turn_smoothly_with_vibration():
    res = simulate(SimConfig(noise_v=0.0, temp_noise_c=0.0, program="short", rate_hz=50.0))
    ctx = res.context
    a, moving = ctx.a_g, ctx.position_idx < 0
    np.testing.assert_allclose(np.linalg.norm(a[~moving], axis=1), 1.0, atol=1e-12)
    norm = np.linalg.norm(a[moving], axis=1)
    assert np.all(np.abs(norm - 1) < 3 * 3e-3 * np.sqrt(3)) and np.std(norm - 1) > 5e-4  # vibration, milli-g
    # Without vibration the angle from the start position grows monotonically through each move.
    quiet = simulate(SimConfig(noise_v=0.0, temp_noise_c=0.0, program="short", rate_hz=50.0, vibration_g=0.0))
    qa, t = quiet.context.a_g, quiet.context.t_s
    for seg in short_program().timetable().moves():
        m = (t >= seg.t_start_s) & (t <= seg.t_end_s)
        angle = np.arccos(np.clip(qa[m] @ gravity_vector_g(seg.from_position), -1, 1))
        assert np.all(np.diff(angle) >= -1e-12)
        assert angle[-1] == pytest.approx(
            np.arccos(np.clip(gravity_vector_g(seg.to_position) @ gravity_vector_g(seg.from_position), -1, 1)), abs=1e-9
        )


def test_reproducible_and_seeded(clean):
    a = simulate(SimConfig(program="short", seed=5))
    b = simulate(SimConfig(program="short", seed=5))
    c = simulate(SimConfig(program="short", seed=6))
    assert a.run.voltmeter.equals(b.run.voltmeter) and a.run.au_temperature.equals(b.run.au_temperature)
    assert not a.run.voltmeter.equals(c.run.voltmeter)
    # Same program, different unit: different constants.
    d = simulate(SimConfig(program="short", seed=5, unit_seed=1))
    assert d.truth["unit"]["label"] == "random:1"
    assert not np.allclose(d.run.u_v()[:10], a.run.u_v()[:10], atol=1e-4)


# ----------------------------------------------------------------------------------------------------------------
# Streams, fixture log, metadata, truth


def test_streams_and_rates(clean):
    run = clean.run
    start = parse_utc_ns("2026-11-01T00:00:00Z")
    assert start == 1793491200 * 10**9
    t = run.t_ns()
    assert t[0] == start and np.all(np.diff(t) == 100_000_000) and t.size == 592_601
    tt = run.au_temperature["t_ns"].to_numpy()
    assert tt[0] == start and np.all(np.diff(tt) == 1_000_000_000)
    assert run.chamber is not None and run.chamber.height == tt.size
    res = simulate(SimConfig(program="short", with_fixture_log=False, with_chamber=False, rate_hz=2.0))
    assert res.run.fixture is None and res.run.chamber is None
    assert np.all(np.diff(res.run.t_ns()) == 500_000_000)


def test_fixture_log_events(clean):
    fx = clean.run.fixture
    t = fx["t_ns"].to_numpy()
    pos = fx["position"].to_list()
    start = clean.run.t_ns()[0]
    assert pos[0] == "TP1" and t[0] == start
    assert np.all(np.diff(t) > 0)
    assert pos[1::2] == [MOVING] * 53 and len(pos) == 107
    arrivals = [p for p in pos if p != MOVING]
    holds = [h["position"] for h in clean.truth["holds"]]
    assert arrivals == holds  # consecutive holds are always in different positions here
    np.testing.assert_array_equal(t[2::2] - t[1::2], 20 * 10**9)  # 20 s moves
    for hold, t_arrive in zip(clean.truth["holds"][1:], t[2::2]):
        assert hold["t_start_ns"] == t_arrive
    # The voltages move only while the log says MOVING.
    moving = clean.context.position_idx < 0
    tv = clean.run.t_ns()
    idx = np.searchsorted(t, tv, side="right") - 1
    assert np.array_equal(np.array(pos, dtype=object)[idx] == MOVING, moving)


def test_metadata(clean):
    meta = clean.run.meta
    assert meta.unit_serial == "AU-0001" and meta.run_id == "sim-AU-0001-s0" and meta.station == "sim-ch1"
    assert meta.fixture == "tilt-6" and meta.normal_temp_c == 20.0 and meta.g_local_mps2 == 9.80665
    assert meta.started_utc == "2026-11-01T00:00:00Z" and meta.nominal_gain_v_per_g == -0.55
    strings = meta.to_strings()
    assert strings["g_local_mps2"] == "9.80665" and RunMeta.from_strings(strings) == meta
    other = simulate(
        SimConfig(program="short", unit_serial="AU-0042", seed=3, station="ch2", started_utc="2027-01-02T03:04:05Z")
    )
    assert other.run.meta.run_id == "sim-AU-0042-s3" and other.run.meta.station == "ch2"
    assert other.run.t_ns()[0] == parse_utc_ns("2027-01-02T03:04:05+00:00")


def test_truth_document(clean, tmp_path):
    res = simulate(
        SimConfig(
            program="short", effects=[("thermal_hysteresis", {"h_v_x": 1e-5}), ("fixture_face_error", {"seed": 4})]
        )
    )
    path = tmp_path / "truth.json"
    write_truth(res.truth, path)
    text = path.read_text()
    doc = json.loads(text)
    assert list(doc) == sorted(doc)
    assert doc["program"] == "short" and doc["case_lag_s"] == 120.0 and doc["run_id"] == "sim-AU-0001-s0"
    assert [e["id"] for e in doc["effects"]] == ["thermal_hysteresis", "fixture_face_error"]
    assert doc["effects"][0]["params"] == {"h_v": [1e-5, -40e-6, 30e-6]}
    assert set(doc["effects"][1]["params"]["delta_rad"]) == set(TP + VP)
    # The truth's unit evaluates to the simulated constants.
    unit = UnitTruth.from_dict(doc["unit"])
    for row in doc["unit_constants_at"]:
        k, u0 = unit.constants_at(np.array([row["temp_c"]]))
        np.testing.assert_allclose(k[0], row["K"], rtol=0, atol=1e-15)
    assert [row["temp_c"] for row in doc["unit_constants_at"]] == [-40.0, -10.0, 20.0, 45.0, 70.0]
    # Position vectors carry the face error, unit length.
    vp1 = np.array(doc["position_vectors_g"]["VP1"])
    assert np.linalg.norm(vp1) == pytest.approx(1.0, abs=1e-12)
    assert 0 < np.linalg.norm(vp1 - np.array(VERIFICATION_POSITIONS["VP1"])) < 1e-3
    h = doc["holds"][0]
    assert set(h) >= {"position", "t_start_ns", "t_end_ns", "setpoint_c"}
    assert h["position"] == "TP1" and h["t_end_ns"] - h["t_start_ns"] == 60 * 10**9
    assert doc["config"]["effects"][0] == ["thermal_hysteresis", {"h_v_x": 1e-5}]


def test_bad_configs_raise():
    with pytest.raises(ValueError, match="unknown effect"):
        simulate(SimConfig(program="short", effects=[("nope", {})]))
    with pytest.raises(ValueError, match="rate_hz"):
        simulate(SimConfig(rate_hz=0))
    with pytest.raises(ValueError, match="unknown chamber program"):
        simulate(SimConfig(program="long"))
    with pytest.raises(ValueError, match="ISO 8601"):
        simulate(SimConfig(program="short", started_utc="yesterday"))
