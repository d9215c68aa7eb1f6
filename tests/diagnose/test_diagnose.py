"""diagnose: the reduction of a recording, the fit terms, the extended model and its compensation, the command.

Fast cases on the short chamber program (about 3.5 h) at a 2 Hz voltmeter; the proof on concealed effects of the
whole catalogue is in test_diagnose_concealed.py.
"""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from flows.diagnose_cmd import diagnose_command, diagnose_text
from pipeline.diagnose.diagnosis import diagnose_run, fit_passport
from pipeline.diagnose.signal import make_blocks, segment_settings_for, static_record
from pipeline.dynamics import Thermosensor
from pipeline.effects.catalogue import make_effect
from pipeline.effects.model import ExtendedModel
from pipeline.errors import ThermocalError
from pipeline.io.runs import write_run
from pipeline.jsonable import to_jsonable
from pipeline.model import gravity_module_error_g
from pipeline.passport.canonical import canonical_json
from pipeline.passport.document import compensate_extended, load_extended
from pipeline.passport.registry import load_passport_file
from pipeline.passport.signing import sign_record
from pipeline.segment import segment_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.thermal import PolynomialModel, RateTerms
from tests.conftest import data_path


def short(effects=(), seed=0, **kw):
    return simulate(SimConfig(program="short", rate_hz=2.0, seed=seed, effects=list(effects), **kw))


def record(res):
    st = segment_settings_for(res.run)
    return static_record(res.run, segment_run(res.run, st), settings=st)


@pytest.fixture(scope="module")
def clean_short():
    return short(seed=3)


# ---------------------------------------------------------------------------------------------- the recording


@pytest.mark.parametrize("with_log", [True, False])
def test_record_moves_ramps_and_noise_from_the_data(with_log):
    res = short([("tilt_settling", {})], seed=1, with_fixture_log=with_log, with_chamber=with_log)
    rec = record(res)
    truth = res.context
    # every move found, arriving when the simulator says (the fixture log exactly; else from the signal, which
    # calls "arrived" 99.9 % of the turn, about 5 % of the move's 10 s before its end)
    assert rec.arrive_s.size == truth.arrive_s.size
    err = rec.arrive_s - truth.arrive_s
    if with_log:
        assert np.max(np.abs(err)) < 1e-6
    else:
        assert np.all((err < 0) & (err > -1.5)) and np.std(err) < 0.1
    # named stretches: the position of every micro-sample is the simulator's
    pos_truth = truth.position_idx[np.searchsorted(truth.t_s, rec.t_s)]
    assert np.all(rec.position_idx == pos_truth)
    # ramp direction: from the setpoint to a second; from the thermosensor wrong only where marked uncertain
    sign_truth = truth.ramp_sign[np.searchsorted(truth.t_s, rec.t_s)]
    wrong = rec.ramp_sign != sign_truth
    if with_log:
        assert rec.ramp_source == "chamber setpoint" and wrong.sum() <= 6 and not rec.ramp_uncertain.any()
    else:
        assert rec.ramp_source == "AU thermosensor" and not np.any(wrong & ~rec.ramp_uncertain)
    # per-sample noise of the simulator (5 uV) from first differences
    np.testing.assert_allclose(rec.sigma_sample_v, 5e-6, rtol=0.05)
    # the micro-samples hold every kept static sample once
    assert rec.count.sum() == pytest.approx(rec.size * 2, rel=0.02)


def test_blocks_partition_the_micro_samples(clean_short):
    rec = record(clean_short)
    b = make_blocks(rec, block_s=30.0)
    assert b.starts[0] == 0 and np.all(np.diff(b.starts) > 0) and b.n.sum() == rec.count.sum()
    # each block inside one stretch; fine blocks at each stretch start, 30 s ones later (a short tail merged)
    ends = np.concatenate((b.starts[1:], [rec.size])) - 1
    assert np.all(rec.stretch[b.starts] == rec.stretch[ends])
    span = b.t_end_s - b.t_start_s + 1.0
    assert np.all(span[b.since_start_s < 60] <= 32.5) and np.all(span <= 46.0)
    np.testing.assert_allclose(b.mean(rec.t_s), b.t_s)


# ---------------------------------------------------------------------------------------------- the model


def _truth_base(res) -> PolynomialModel:
    unit_doc = res.truth["unit"]
    k = np.asarray(unit_doc["K_coef"])
    u = np.asarray(unit_doc["U0_coef"])
    return PolynomialModel.from_dict(unit_doc["thermal_model"], k[0], u[0], unit_doc["normal_temp_c"])


def test_extended_model_reproduces_the_simulator_and_compensates_exactly():
    effects = [
        ("thermal_lag", {"tau_s": 90.0}),
        ("thermal_hysteresis", {}),
        ("time_drift", {}),
        ("warmup_transient", {}),
        ("temperature_curvature", {}),
        ("scale_nonlinearity", {}),
        ("tilt_settling", {}),
    ]
    res = short(effects, noise_v=0.0, temp_noise_c=0.0)
    ctx = res.context
    ext = ExtendedModel(_truth_base(res), [make_effect(e, p) for e, p in effects])
    u = res.run.u_v()
    # forward: the simulator's outputs to rounding, moves included
    assert np.max(np.abs(ext.output_v(ctx) - u)) < 1e-12
    # through the passport document and back, then compensation gives the true specific force
    doc = {"extended_model": json.loads(json.dumps(ext.to_dict()))}
    a = compensate_extended(doc, u, ctx)
    static = ctx.position_idx >= 0
    assert np.max(np.abs(a[static] - ctx.a_g[static])) < 1e-9
    assert np.max(np.abs(gravity_module_error_g(a[static]))) < 1e-9
    # without the effects, the base alone is off by the effects' size
    base_only = compensate_extended({"extended_model": ExtendedModel(ext.base, []).to_dict()}, u, ctx)
    assert np.max(np.abs(base_only[static] - ctx.a_g[static])) > 1e-4
    assert load_extended({}) is None


def test_fitted_parameters_match_the_concealed_truth():
    """Low-noise run with two effects: the fitted parameters are the simulator's (which diagnose never sees)."""
    hyst = {"h_v": [20e-6, -15e-6, 10e-6]}
    tilt = {"f": 1e-4, "tau_s": 20.0}
    res = short([("thermal_hysteresis", hyst), ("tilt_settling", tilt)], seed=2, noise_v=1e-6)
    rep = diagnose_run(res.run).report
    found = {f["effect"]: f["parameters"] for f in rep["findings"]}
    assert set(found) == {"thermal_hysteresis", "tilt_settling"}
    np.testing.assert_allclose(found["thermal_hysteresis"]["h_v"], hyst["h_v"], rtol=0.01)
    assert found["tilt_settling"]["f"] == pytest.approx(tilt["f"], rel=0.02)
    assert found["tilt_settling"]["tau_s"] == pytest.approx(tilt["tau_s"], rel=0.02)
    ext = rep["extended_model"]
    assert [e["effect"] for e in ext["effects"]] == [f["effect"] for f in rep["findings"]]


# ---------------------------------------------------------------------------------------------- the report


def test_clean_run_is_consistent_and_the_report_has_the_contract_shape(clean_short):
    rep = diagnose_run(clean_short.run).report
    assert rep["verdict"] == "consistent" and rep["findings"] == []
    json.dumps(rep)  # plain JSON, no numpy types
    # the model explains the data to the noise
    assert rep["rms_after_v"] < 1.2 * rep["rms_noise_v"]
    assert rep["rms_before_v"] < 1.5 * rep["rms_noise_v"]
    assert rep["vp"] and rep["vp_max_abs_dg_after_g"] < 5e-6
    # every candidate was scored and none passed
    assert {c["effect"] for c in rep["candidates"][0]} >= {"thermal_lag", "tilt_settling", "fixture_face_error"}
    assert all(c["delta_bic"] > -20 or c["implausible"] for c in rep["candidates"][0])


def test_a_passports_rate_terms_are_part_of_the_model_it_is_compared_with(clean_short):
    """A passport's rate terms (the differential method's: U0 += alpha r, r the smoothed thermosensor's rate in
    C/min) are part of the model diagnose compares a recording with: the recording plus exactly what they add (up to
    25 micro-V on the short program's 5 C/min ramps), diagnosed with them, departs from the passport as little as
    the plain recording from the passport without them (block RMS within 10 %); with a passport without them the
    same recording departs 5x as much (8.9x). (The added signal moves a few stretch edges, so the blocks differ.)"""
    run = clean_short.run
    passport = fit_passport(run, segment_run(run, segment_settings_for(run)))
    alpha_v = np.array([6e-6, -4e-6, 5e-6])  # V/(C/min)
    smooth_s = 301.0
    with_rate = copy.deepcopy(passport.document)
    with_rate["rate_terms"] = RateTerms(alpha_v.reshape(1, 1, 3), np.zeros((1, 1, 3)), smooth_s).to_dict()
    t_ns = run.voltmeter["t_ns"].to_numpy()
    _, rate = Thermosensor.from_run(run, smooth_s, t_ref_ns=int(t_ns[0])).at((t_ns - t_ns[0]) / 1e9)
    added = run.voltmeter.with_columns([pl.col(c) + alpha_v[i] * rate for i, c in enumerate(("ux", "uy", "uz"))])
    shifted = dataclasses.replace(run, voltmeter=added)
    plain = diagnose_run(run, passport).report
    held = diagnose_run(shifted, with_rate).report
    assert held["rms_before_v"] == pytest.approx(plain["rms_before_v"], rel=0.1)
    assert any("rate terms" in n for n in held["notes"])
    ignored = diagnose_run(shifted, passport).report
    assert ignored["verdict"] == "mismatch" and ignored["rms_before_v"] > 5 * plain["rms_before_v"]


def test_finding_has_the_contract_fields():
    res = short([("warmup_transient", {"a_v": [60e-6, -40e-6, 30e-6], "tau_s": 600.0})], seed=4)
    rep = diagnose_run(res.run).report
    assert rep["verdict"] == "mismatch"
    f = rep["findings"][0]
    assert f["effect"] == "warmup_transient"
    assert set(f) >= {"effect", "explanation", "where", "parameters", "rms_before_v", "rms_after_v"}
    assert set(f["where"]) >= {"windows", "axes", "temps_c", "positions"}
    # where: early in the run, at +20 C, first position
    t0 = int(res.run.t_ns()[0])
    start, end = f["where"]["windows"][0]
    assert start >= t0 and (end - t0) / 1e9 < 1800
    assert f["where"]["temps_c"] == [pytest.approx(20.0, abs=0.5)] and f["where"]["positions"][0] == "TP1"
    assert f["rms_after_v"] < 0.2 * f["rms_before_v"]
    assert "min" in f["explanation"] and "uV" in f["explanation"]
    assert f["parameters"]["tau_s"] == pytest.approx(600.0, rel=0.05)


def test_explanations_are_in_the_recordings_unit():
    """A recording whose outputs are in m/s^2 (gains about 9.8 per g, as the real tag's) is explained in mm/s^2, not
    uV: the same warm-up transient, its amounts written in the output unit's small unit (the V case: above)."""
    import dataclasses

    import polars as pl

    from pipeline.run import Run

    res = short([("warmup_transient", {"a_v": [60e-6, -40e-6, 30e-6], "tau_s": 600.0})], seed=4)
    scale = 9.80665 / 0.55  # the same recording (gains near -0.55 V/g), as a logger writing m/s^2
    r = res.run
    run = Run(
        meta=dataclasses.replace(r.meta, nominal_gain_v_per_g=r.meta.nominal_gain_v_per_g * scale),
        voltmeter=r.voltmeter.with_columns([pl.col(c) * scale for c in ("ux", "uy", "uz")]),
        au_temperature=r.au_temperature,
        chamber=r.chamber,
        fixture=r.fixture,
    )
    diag = diagnose_run(run)
    assert diag.passport.output_unit == "m/s^2"
    f = diag.report["findings"][0]
    assert f["effect"] == "warmup_transient"
    text = f["explanation"]
    assert "uV" not in text and "mm/s^2" in text, text
    a = f["parameters"]["a_v"]
    assert "settle by " + ", ".join(f"{ax} {x * 1e3:+.2f}" for ax, x in zip("xyz", a)) + " mm/s^2" in text
    peak = f["max_effect_v"] * 1e3
    assert f"{peak:.3g}" in text or f"{peak:.2f}" in text or f"{peak:.1f}" in text
    assert "uV" not in " ".join(diag.report["notes"])


def test_small_amounts_in_either_unit():
    """The one helper the sentences print amounts through, given the output unit: uV as before for volts; mm/s^2
    with three significant digits for m/s^2; the unit is always named by the caller (no hidden state)."""
    from pipeline.effects.base import vec_uv
    from pipeline.model import small

    assert small(12.34e-6, unit="V") == "12.3 uV" and small(2e-6, ".2f", "/g", unit="V") == "2.00 uV/g"
    assert small(0.7122582, unit="m/s^2") == "712.3 mm/s^2"
    assert small(5e-5, unit="m/s^2") == "0.0500 mm/s^2"
    assert small(0.0123, unit="m/s^2") == "12.3 mm/s^2" and small(0.0123, unit="V") == "12300.0 uV"
    assert vec_uv([1.2e-3, -3e-4, 0.0], "/h", unit="m/s^2") == "x +1.20, y -0.30, z +0.00 mm/s^2/h"
    assert vec_uv([1.2e-9, -3e-10, 0.0], "/h", unit="V") == "x +1.20, y -0.30, z +0.00 nV/h"
    with pytest.raises(TypeError):
        small(0.0123)  # the unit is a required keyword


# ---------------------------------------------------------------------------------------------- the command


def test_command_writes_figure_and_extended_passport(tmp_path: Path):
    calib = short(seed=5)  # a clean calibration run of the same unit
    passport = fit_passport(calib.run, segment_run(calib.run, segment_settings_for(calib.run))).document
    pp = tmp_path / "passport.json"
    pp.write_bytes(canonical_json(sign_record(to_jsonable(passport))))  # a loose file this station signed
    res = short([("scale_nonlinearity", {"k2_v_per_g2": [20e-6, -15e-6, 10e-6]})], seed=6)
    run_path = write_run(res.run, tmp_path / "run.parquet-dir", "parquet")
    rep = diagnose_command(run_path, pp, True, tmp_path / "fig" / "residual.png", out_dir=tmp_path / "out")
    assert rep["verdict"] == "mismatch" and rep["findings"][0]["effect"] == "scale_nonlinearity"
    assert rep["passport_source"] == str(pp) and rep["passport_used"]["verification"]["verified"]
    png = Path(rep["figure"])
    assert png == tmp_path / "fig" / "residual.png" and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ext_doc = json.loads(Path(rep["extended_passport"]).read_text())
    assert Path(rep["extended_passport"]) == tmp_path / "out" / "run.parquet-dir.diagnose.passport.json"
    assert load_passport_file(rep["extended_passport"])[1].verification.verified  # signed: apply takes it
    assert ext_doc["unit"] == passport["unit"] and ext_doc["coefficients"] == passport["coefficients"]
    ext = load_extended(ext_doc)
    assert [e.id for e in ext.effects] == ["scale_nonlinearity"]
    np.testing.assert_allclose(ext.effects[0].k2_v_per_g2, [20e-6, -15e-6, 10e-6], rtol=0.05)
    text = diagnose_text(rep)
    assert "scale_nonlinearity" in text and "mismatch" in text
    assert rep["output_unit"] == "V" and f"before {rep['rms_before_v'] * 1e6:.2f} uV" in text
    in_mps2 = diagnose_text({**rep, "output_unit": "m/s^2"})  # a logger recording m/s^2: no micro-volts
    assert f"before {rep['rms_before_v'] * 1e3:.2f} mm/s^2" in in_mps2 and " uV" not in in_mps2.split("\n")[1]


def test_command_refuses_bad_inputs_in_one_line(tmp_path: Path, monkeypatch):
    with pytest.raises(ThermocalError):
        diagnose_command(tmp_path / "missing.mcap", None, True, None)
    run_path = write_run(short(seed=7).run, tmp_path / "r.mcap", "mcap")
    bad = tmp_path / "not-a-passport.json"
    bad.write_text('{"schema": "something else"}')
    with pytest.raises(ThermocalError, match="not a thermocal.passport"):
        diagnose_command(run_path, bad, True, None)
    unsigned = tmp_path / "unsigned.json"
    passport = fit_passport(short(seed=5).run, segment_run(short(seed=5).run, segment_settings_for(short(seed=5).run)))
    unsigned.write_text(json.dumps(to_jsonable(passport.document)))
    with pytest.raises(ThermocalError, match="does not verify: not its canonical bytes") as info:
        diagnose_command(run_path, unsigned, True, None)
    assert "--unverified" in info.value.one_line()
    monkeypatch.chdir(tmp_path)  # nothing written where the data is: into the current folder by default
    rep = diagnose_command(run_path, unsigned, True, None, unverified=True)
    assert "UNVERIFIED" in rep["passport_source"] and not rep["passport_used"]["verification"]["verified"]
    assert Path(rep["figure"]).parent == tmp_path and "derived_from_unverified" in json.loads(
        Path(rep["extended_passport"]).read_text()
    )


def test_a_piecewise_passport_is_refined_not_blamed_on_the_catalogue(clean_short):
    """A piecewise-linear passport misses the unit's curvature between breakpoints: that is the passport's own
    model, so a clean run stays consistent (with a note), and a concealed effect is still named."""
    from pipeline.calibrate.tilt import CalibrationSettings

    st = segment_settings_for(clean_short.run)
    passport = fit_passport(
        clean_short.run, segment_run(clean_short.run, st), CalibrationSettings(thermal_model="piecewise", segment=st)
    )
    clean = diagnose_run(short(seed=8).run, passport).report
    assert clean["verdict"] == "consistent"
    assert clean["rms_before_v"] > 5 * clean["rms_after_v"]
    assert any("piecewise" in n for n in clean["notes"]) and any("not a left-out effect" in n for n in clean["notes"])
    hyst = diagnose_run(short([("thermal_hysteresis", {"h_v": [10e-6, 10e-6, -10e-6]})], seed=8).run, passport)
    assert [f["effect"] for f in hyst.report["findings"]] == ["thermal_hysteresis"]


def test_real_hand_held_recording_shows_its_face_errors():
    """imucal's Ferraris session (tests/data/real): six orientations held by hand. Hand-held "faces" are
    off by a fraction of a degree each, which is what diagnose finds, and modelling it improves the fit."""
    run_dir = data_path("real", "imucal_ferraris", "run")
    from pipeline.io.runs import read_run

    rep = diagnose_run(read_run(run_dir)).report
    assert rep["findings"][0]["effect"] == "fixture_face_error"
    worst = max(np.linalg.norm(v) for v in rep["findings"][0]["parameters"]["delta_rad"].values())
    assert np.radians(0.05) < worst < np.radians(1.0)
    assert rep["rms_after_v"] < 0.6 * rep["rms_before_v"]
