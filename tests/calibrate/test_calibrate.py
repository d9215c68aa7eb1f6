"""The calibration flow end to end: simulated runs (MCAP and Parquet, with and without a fixture log), seed 000's
Table 3, the real hand-held recording. Runs the real Prefect flow in local ephemeral mode (PREFECT_HOME is a
temporary folder, see conftest.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from pipeline.calibrate.tilt import CalibrationSettings, fit_unit, observe_run, verify_unit
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import UnitTruth
from tests.conftest import REPO, data_path, run_piece

T0 = 20.0


@pytest.fixture(scope="module")
def noise_free_run(tmp_path_factory):
    res = simulate(SimConfig(noise_v=0.0, temp_noise_c=0.0, seed=3))
    path = write_run(res.run, tmp_path_factory.mktemp("nf") / "noise_free.mcap", "mcap")
    return path, res.truth


@pytest.fixture(scope="module")
def noisy_runs(tmp_path_factory):
    """Standard program, default noise: MCAP with fixture log; Parquet without fixture log (another unit)."""
    d = tmp_path_factory.mktemp("noisy")
    a = simulate(SimConfig(seed=11))
    b = simulate(SimConfig(seed=12, unit_seed=7, unit_serial="AU-0007", with_fixture_log=False))
    return [(write_run(a.run, d / "a.mcap", "mcap"), a.truth), (write_run(b.run, d / "b_parquet", "parquet"), b.truth)]


@pytest.mark.slow  # the Prefect flow
def test_flow_piecewise_reproduces_table3_end_to_end(noise_free_run, seed000, tmp_path):
    """thermocal's flow on a noise-free simulated run of seed 000's unit reproduces Table 3 (all values)."""
    from flows.calibrate import run_calibrate
    from tests.test_thermal import _assert_table3

    path, _ = noise_free_run
    res = run_calibrate([str(path)], str(tmp_path / "reg"), CalibrationSettings(thermal_model="piecewise"))
    passport = json.loads(Path(res["passport"]).read_text())
    tm = passport["thermal_model"]
    assert tm["kind"] == "piecewise_linear"
    # breakpoints are the plateaus' measured temperatures (the case is still 0.006 C from -40 after the soak)
    _assert_table3(tm, seed000, temp_tol_c=0.05)
    # the normal-temperature constants are Table 1's +20 C row
    ref = seed000["table_1_2_constants"][0]
    np.testing.assert_allclose(passport["coefficients"]["K"], ref["K"], atol=2e-8)
    np.testing.assert_allclose(passport["coefficients"]["U0"], ref["U0"], atol=2e-8)
    schema = json.loads((REPO / "schemas" / "thermocal.passport.json").read_text())
    jsonschema.validate(passport, schema)
    assert Path(res["figure"]).exists() and Path(res["figure"]).stat().st_size > 10_000
    assert res["status"] in ("pass", "fail")
    assert {v["temp_c"] for v in res["verification"]} >= {-10.0, 45.0} or len(res["verification"]) >= 24


@pytest.mark.parametrize("which", [0, 1], ids=["mcap+fixture", "parquet-no-fixture-other-unit"])
def test_noisy_constants_within_noise_bound(noisy_runs, which):
    """Recovered constants vs. the simulator's truth.

    Bound: 5 uV per-sample noise over ~2700 samples per position gives ~1e-7 V per position mean; the six-position
    differences and the thermal fit over five plateaus keep it near that; the thermosensor's 0.01 C noise averaged
    over a position adds ~1e-4 V/C * 6e-4 C. We allow 1e-6 V (U0) and 1e-6 V/g (K, ~2 ppm of the gain): about ten
    times the noise-limited error, and two orders below the smallest temperature effect of interest.
    """
    path, truth = noisy_runs[which]
    run = read_run(path)
    obs, _ = observe_run(run)
    fit = fit_unit(run.meta.unit_serial, obs, CalibrationSettings(), T0)
    unit = UnitTruth.from_dict(truth["unit"])
    for p in fit.per_plateau:
        K, U0 = unit.constants_at(np.array([p.temp_c]))
        assert np.abs(p.K - K[0]).max() < 1e-6, p
        assert np.abs(p.U0 - U0[0]).max() < 1e-6, p
    K0, U00 = unit.constants_at(np.array([T0]))
    assert np.abs(fit.model.K0 - K0[0]).max() < 1e-6
    assert np.abs(fit.model.U00 - U00[0]).max() < 1e-6
    assert fit.model.order == 2
    # the thermal model reproduces the truth over the operating range (quadratic truth, order-2 model)
    Ts = np.linspace(-40, 70, 12)
    Km, U0m = fit.model.constants_at(Ts)
    Kt, U0t = unit.constants_at(Ts)
    assert np.abs(U0m - U0t).max() < 3e-6 and np.abs(Km - Kt).max() < 3e-6
    # compensation: VP errors at -10 and +45 C several times smaller than uncompensated
    rows, status = verify_unit(fit.model, obs, T0)
    for temp in (-10.0, 45.0):
        sel = [r for r in rows if abs(r.temp_c - temp) < 3]
        assert {r.position for r in sel} == {f"VP{k}" for k in range(1, 7)}  # (VP6 also during the soak)
        unc = max(abs(r.dg_uncompensated_g) for r in sel)
        m1 = max(abs(r.dg_method1_g) for r in sel)
        m2 = max(abs(r.dg_method2_g) for r in sel)
        assert unc > 4 * m1 and unc > 4 * m2, (temp, unc, m1, m2)
    assert status == "pass"


def test_piecewise_vs_polynomial_on_vp(noisy_runs):
    """Seed 000's two-sub-band model leaves errors the order-2 model removes (the truth is smooth, not broken)."""
    path, _ = noisy_runs[0]
    run = read_run(path)
    obs, _ = observe_run(run)
    pw = fit_unit("AU-0001", obs, CalibrationSettings(thermal_model="piecewise"), T0)
    p2 = fit_unit("AU-0001", obs, CalibrationSettings(thermal_model="poly2"), T0)
    rows_pw, _ = verify_unit(pw.model, obs, T0)
    rows_p2, _ = verify_unit(p2.model, obs, T0)
    far = lambda rows, key: max(abs(getattr(r, key)) for r in rows if abs(r.temp_c - T0) > 10)  # noqa: E731
    assert far(rows_pw, "dg_uncompensated_g") > 2.5 * far(rows_pw, "dg_method1_g")  # seed 000: 3-4x
    assert far(rows_p2, "dg_method1_g") < 0.3 * far(rows_pw, "dg_method1_g")


@pytest.mark.slow  # the Prefect flow
def test_real_recording_imucal(tmp_path):
    """The hand-held Ferraris session: six positions where its labels say, constants near its README, unverified."""
    from flows.calibrate import run_calibrate

    run_dir = data_path("real", "imucal_ferraris", "run")
    labels = json.loads((run_dir.parent / "labels.json").read_text())["labels"]
    run = read_run(run_dir)
    obs, _ = observe_run(run)
    for lab in labels:
        if not lab["position"].startswith("TP"):
            continue
        overlap = max(
            min(o.t_end_ns, lab["t_end_ns"]) - max(o.t_start_ns, lab["t_start_ns"])
            for o in obs
            if o.position == lab["position"]
        )
        assert overlap > 0.5 * (lab["t_end_ns"] - lab["t_start_ns"]), lab["position"]
    res = run_calibrate([str(run_dir)], str(tmp_path / "reg"), CalibrationSettings())
    assert res["status"] == "unverified"
    passport = json.loads(Path(res["passport"]).read_text())
    K = np.array(passport["coefficients"]["K"])
    np.testing.assert_allclose(np.diag(K), [9.777, 9.834, 10.039], atol=0.01)
    np.testing.assert_allclose(passport["coefficients"]["U0"], [0.551, -0.620, 0.386], atol=0.01)


@pytest.mark.slow  # the console script through the local Prefect server
def test_cli_calibrate_json_and_idempotence(tmp_path):
    """The console script: --json prints exactly one JSON object; the same inputs again make no new version."""
    sample = REPO / "sample_data" / "standard_short.mcap"
    if not sample.exists():
        pytest.skip("sample data not generated yet")
    env = dict(os.environ)
    exe = str(Path(sys.executable).parent / "thermocal")
    cmd = [exe, "calibrate", str(sample), "--registry", str(tmp_path / "reg"), "--json"]
    first = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr
    r1 = json.loads(first.stdout)
    assert r1["unit"] == "AU-0001" and r1["version"] == 1 and r1["status"] in ("pass", "fail", "unverified")
    assert len(r1["passport_sha256"]) == 64
    second = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    r2 = json.loads(second.stdout)
    assert r2["version"] == 1 and r2["passport_sha256"] == r1["passport_sha256"]
    bad = subprocess.run(
        [exe, "calibrate", str(tmp_path / "nope.mcap"), "--registry", str(tmp_path / "reg")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert bad.returncode != 0 and len(bad.stderr.strip().splitlines()) == 1 and "nope.mcap" in bad.stderr


@pytest.mark.slow  # the Prefect flow
def test_vp_only_run_verifies_tp_run(tmp_path):
    """Separate recordings of one unit: TP plateaus (+20, -40 C; +70, +20 C) in two, VP plateaus (-10 C; +45 C)
    in two VP-only runs; the VP runs verify the TP runs' passport."""
    from flows.calibrate import run_calibrate

    res = simulate(SimConfig(seed=21, program="short", rate_hz=5))
    holds = res.truth["holds"]
    t_start = res.run.voltmeter["t_ns"][0]
    vp_m10 = [h for h in holds if h["position"].startswith("VP") and h["setpoint_c"] == -10.0]
    vp_45 = [h for h in holds if h["position"].startswith("VP") and h["setpoint_c"] == 45.0]
    tp_m40_end = max(h["t_end_ns"] for h in holds if h["setpoint_c"] == -40.0)
    tp_70 = [h for h in holds if h["setpoint_c"] == 70.0 and h["position"].startswith("TP")]
    # TP run: +20 and -40 C; then the +70 C plateau through the end (+20 C again); VP run: -10 C ... +45 C
    tp_a = run_piece(res.run, t_start, tp_m40_end, "tp-part-a", closed="both")
    tp_70_from_ns = min(h["t_start_ns"] for h in tp_70) - 1_200_000_000_000
    tp_b = run_piece(res.run, tp_70_from_ns, 2**62, "tp-part-b", closed="both")
    vp = [
        run_piece(
            res.run,
            min(h["t_start_ns"] for h in hs) - 1_200_000_000_000,
            max(h["t_end_ns"] for h in hs),
            f"vp-only-{k}",
            closed="both",
        )
        for k, hs in enumerate((vp_m10, vp_45))
    ]
    paths = [str(write_run(r, tmp_path / f"{r.meta.run_id}.mcap", "mcap")) for r in (tp_a, tp_b, *vp)]
    out = run_calibrate(paths, str(tmp_path / "reg"), CalibrationSettings())
    temps_vp = {round(v["temp_c"]) for v in out["verification"]}
    assert {-10, 45} <= temps_vp
    assert out["status"] == "pass"
    passport = json.loads(Path(out["passport"]).read_text())
    # the four files are one recording of the unit (issue 21), its run_id theirs in time order
    recording = "tp-part-a+vp-only-0+vp-only-1+tp-part-b"
    assert {p["run_id"] for p in passport["per_plateau"]} == {recording}
    vp_rows = [v for v in passport["verification"] if min(abs(v["temp_c"] + 10), abs(v["temp_c"] - 45)) < 3]
    assert {v["run_id"] for v in vp_rows} == {recording} and len(vp_rows) >= 12
    spans = [(int(r.voltmeter["t_ns"].min()), int(r.voltmeter["t_ns"].max())) for r in vp]
    # the 12 VP holds are those of the VP-only files (tp-part-b may add the VP6 still held when it starts)
    assert sum(any(a <= v["t_start_ns"] < b for a, b in spans) for v in vp_rows) == 12
    assert len(passport["provenance"]["inputs"]) == 4


@pytest.mark.slow  # the Prefect flow
def test_flow_other_methods_record_method_and_compensate(tmp_path):
    """calibrate --method scalar / differential through the flow: passports say which method made them, the
    registry keeps them apart (same inputs, another method = another version) and compensation works for both."""
    from flows.calibrate import run_calibrate
    from pipeline.compensate import method1
    from pipeline.model import gravity_module_error_g, output_v
    from pipeline.passport.document import load_model

    reg = str(tmp_path / "reg")
    short = write_run(simulate(SimConfig(seed=5, program="short", rate_hz=2)).run, tmp_path / "short.mcap", "mcap")
    tilt = run_calibrate([str(short)], reg, CalibrationSettings())
    scal = run_calibrate([str(short)], reg, CalibrationSettings(), method="scalar")
    assert (tilt["version"], scal["version"]) == (1, 2) and scal["method"] == "scalar"
    diff_run = simulate(
        SimConfig(seed=6, program="differential", rate_hz=1, effects=[("fixture_face_error", {"sigma_deg": 1.5})])
    )
    diff_path = write_run(diff_run.run, tmp_path / "diff.mcap", "mcap")
    base = json.loads(Path(tilt["passport"]).read_text())
    diff = run_calibrate([str(diff_path)], reg, CalibrationSettings(), method="differential", base_passport=base)
    assert diff["version"] == 3
    unit = UnitTruth.from_dict(diff_run.truth["unit"])
    for res, temps in ((scal, [20.0]), (diff, [-30.0, 0.0, 20.0, 60.0])):
        doc = json.loads(Path(res["passport"]).read_text())
        assert doc["method"] == res["method"]
        model = load_model(doc)
        a = np.array([[0, 0, 1.0], [0.6, 0, 0.8], [0, -1.0, 0]])
        for T in temps:
            K, U0 = unit.constants_at(np.full(3, T))
            dg = gravity_module_error_g(method1(model, output_v(K, U0, a), np.full(3, T)))
            assert np.abs(dg).max() < 1e-4, (res["method"], T, dg)
