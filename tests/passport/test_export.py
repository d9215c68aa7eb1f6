"""thermocal export (pipeline/passport/export.py): the PX4 and ArduPilot parameter files, read back as those
programs evaluate them (PX4: offset = sum X_n (T - TREF)^n, subtracted; ArduPilot: v - p(T - 35) + p(T_cal - 35),
p without constant term, coefficients x 1e6), reproduce the passport's own bias model over valid_temp_c; the residual
they state is the error left when the passport's full model is the truth; the CSV holds every number."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate import tilt
from pipeline.passport.document import build_passport, load_model
from pipeline.passport.export import export_passport
from pipeline.passport.registry import Registry
from pipeline.positions import TEST_POSITIONS, VERIFICATION_POSITIONS, gravity_vector_g
from pipeline.simulate.chamber import SimConfig, simulate


@pytest.fixture(scope="module")
def passports():
    res = simulate(SimConfig(seed=11, program="short", rate_hz=1.0))
    obs, _ = tilt.observe_run(res.run)
    out = {}
    for kind in ("auto", "piecewise"):
        fit = tilt.fit_unit("AU-0001", obs, tilt.CalibrationSettings(thermal_model=kind), 20.0)
        doc = build_passport(fit, [], "unverified", g_local_mps2=9.80665, plateaus=[])
        out[kind] = json.loads(json.dumps(doc))
    return out


def _bias_mps2(doc: dict, temps: np.ndarray) -> np.ndarray:
    """The passport's own model: reading error at a = 0 after the normal-temperature constants, m/s^2."""
    model = load_model(doc)
    K, U0 = model.constants_at(temps)
    return doc["g_local_mps2"] * np.linalg.solve(model.K0, (U0 - model.U00).T).T


def _px4_params(text: str) -> dict[str, float]:
    rows = [line.split("\t") for line in text.splitlines() if line and not line.startswith("#")]
    assert all(len(r) == 5 and r[0] == "1" and r[1] == "1" and r[4] in ("6", "9") for r in rows)
    return {r[2]: float(r[3]) for r in rows}


def _px4_offset(p: dict[str, float], temps: np.ndarray) -> np.ndarray:
    dt = np.clip(temps, p["TC_A0_TMIN"], p["TC_A0_TMAX"]) - p["TC_A0_TREF"]
    return np.stack([sum(p[f"TC_A0_X{n}_{i}"] * dt**n for n in range(4)) for i in range(3)], axis=1)


def _ardupilot_poly(p: dict[str, float], x: np.ndarray) -> np.ndarray:
    return np.stack([sum(p[f"INS_TCAL1_ACC{n}_{ax}"] * x**n for n in (1, 2, 3)) * 1e-6 for ax in "XYZ"], axis=1)


def test_px4_offsets_reproduce_the_passport_bias(passports):
    doc = passports["auto"]
    exp = export_passport(doc, "px4")
    p = _px4_params(exp.text)
    assert p["TC_A_ENABLE"] == 1 and p["TC_A0_TREF"] == 20.0
    assert (p["TC_A0_TMIN"], p["TC_A0_TMAX"]) == tuple(doc["valid_temp_c"]) == (-40.0, 70.0)
    temps = np.linspace(-40, 70, 221)
    want = _bias_mps2(doc, temps)
    assert np.abs(want).max() > 1e-3  # a real thermal bias, m/s^2
    assert np.abs(_px4_offset(p, temps) - want).max() < 1e-7  # float32 parameters, poly2 model: exact
    # outside the range PX4 clamps: the offset stays at the end value
    assert np.allclose(_px4_offset(p, np.array([90.0])), _px4_offset(p, np.array([70.0])))


def test_ardupilot_correction_reproduces_the_passport_bias(passports):
    doc = passports["auto"]
    exp = export_passport(doc, "ardupilot")
    p = {k: float(v) for k, v in (line.split() for line in exp.text.splitlines() if line and line[0] != "#")}
    assert p["INS_TCAL1_ENABLE"] == 1 and (p["INS_TCAL1_TMIN"], p["INS_TCAL1_TMAX"]) == (-40.0, 70.0)
    # the raw reading carries the passport's T0 constants: ArduPilot must refer the correction to T0 (left at
    # its default -300 C, the calibration temperature clamps to TMIN and every reading is off by the bias change
    # between TMIN and T0)
    assert p["INS_ACC1_CALTEMP"] == doc["normal_temp_c"] == 20.0
    temps = np.linspace(-40, 70, 221)
    for t_cal in (p["INS_ACC1_CALTEMP"], 31.5):  # the file's, then a vehicle's own later calibration temperature
        corr = _ardupilot_poly(p, temps - 35.0) - _ardupilot_poly(p, np.array([t_cal - 35.0]))
        want = _bias_mps2(doc, temps) - _bias_mps2(doc, np.array([t_cal]))
        assert np.abs(corr - want).max() < 1e-8


def test_ardupilot_correction_with_the_file_alone_leaves_only_the_unheld_terms(passports):
    """ArduPilot's correction as it runs with the exported file alone (T and CALTEMP clamped to TMIN/TMAX),
    applied to readings of the passport's full model at a = 0: the bias is removed to the fit's error."""
    doc = passports["auto"]
    exp = export_passport(doc, "ardupilot")
    p = {k: float(v) for k, v in (line.split() for line in exp.text.splitlines() if line and line[0] != "#")}
    temps = np.linspace(-40, 70, 111)
    clamp = lambda t: np.clip(t, p["INS_TCAL1_TMIN"], p["INS_TCAL1_TMAX"])  # noqa: E731
    corrected = (
        _bias_mps2(doc, temps)
        - _ardupilot_poly(p, clamp(temps) - 35.0)
        + _ardupilot_poly(p, clamp(np.array([p["INS_ACC1_CALTEMP"]])) - 35.0)
    )
    assert np.abs(corrected).max() < 1e-8 < np.abs(_bias_mps2(doc, temps)).max() * 1e-3
    assert "# INS_ACC1_CALTEMP = T0 (20 C)" in exp.text


def test_failed_passport_states_its_status_in_every_format(passports):
    doc = dict(passports["auto"], status="fail")
    for fmt in ("px4", "ardupilot"):
        head = [line for line in export_passport(doc, fmt).text.splitlines() if line.startswith("#")]
        assert "# status fail; approval unknown (not read from a registry)" in head
        assert any(line.startswith("# WARNING: this passport failed its verification") for line in head)
    rows = {r["quantity"]: r for r in csv.DictReader(io.StringIO(export_passport(doc, "csv").text))}
    assert rows["status"]["value"] == "fail" and rows["approval"]["value"].startswith("approval unknown")


def test_stated_residual_is_the_error_left_with_the_full_model_as_truth(passports):
    """Readings of the passport's full model (gains and cross-axis terms varying with T), corrected with the PX4
    file: the error left is the unheld scale/cross-axis part, bounded by the stated worst total and close to it."""
    doc = passports["auto"]
    exp = export_passport(doc, "px4")
    p = _px4_params(exp.text)
    model = load_model(doc)
    g = doc["g_local_mps2"]
    temps = np.linspace(-40, 70, 111)
    K, U0 = model.constants_at(temps)
    worst = 0.0
    for pos in [*TEST_POSITIONS, *VERIFICATION_POSITIONS]:
        a = gravity_vector_g(pos)
        u = np.einsum("nij,j->ni", K, a) + U0
        raw = g * np.linalg.solve(model.K0, (u - model.U00).T).T
        err = raw - _px4_offset(p, temps) - g * a
        worst = max(worst, float(np.abs(err).max()))
    stated = exp.residual["total_worst_mps2"]
    assert 0.3 * stated < worst <= stated * (1 + 1e-6)
    assert max(exp.residual["bias_fit_max_ug"]) < 0.01
    assert any("beta" in t and "gamma" in t for t in exp.not_held)


def test_piecewise_model_states_its_cubic_fit_error(passports):
    doc = passports["piecewise"]
    exp = export_passport(doc, "px4")
    p = _px4_params(exp.text)
    temps = np.linspace(-40, 70, 1101)
    fit_err = np.abs(_px4_offset(p, temps) - _bias_mps2(doc, temps)).max(axis=0)
    assert np.all(fit_err > 1e-7)  # a cubic cannot follow the kinks
    assert np.allclose(fit_err, exp.residual["bias_fit_max_mps2"], rtol=1e-3, atol=1e-9)
    assert any("piecewise" in t for t in exp.not_held)


def test_csv_holds_every_number_with_its_uncertainty(passports):
    doc = passports["auto"]
    rows = list(csv.DictReader(io.StringIO(export_passport(doc, "csv").text)))
    by = {(r["quantity"], r["key"], r["order"]): r for r in rows}
    assert float(by[("K", "xy", "")]["value"]) == doc["coefficients"]["K"][0][1]
    assert float(by[("K", "xy", "")]["std_uncertainty"]) == doc["uncertainty"]["coefficients"]["K"][0][1]
    assert float(by[("U0", "z", "")]["value"]) == doc["coefficients"]["U0"][2]
    assert float(by[("alpha", "x", "2")]["value"]) == doc["thermal_model"]["alpha"]["x"][1]
    assert float(by[("gamma", "zy", "1")]["std_uncertainty"]) == doc["uncertainty"]["thermal_model"]["gamma"]["zy"][0]
    assert by[("valid_temp_c", "", "")]["t_lo_c"] == "-40.0"
    assert len([r for r in rows if r["quantity"] in ("alpha", "beta", "gamma")]) == 24
    pw = list(csv.DictReader(io.StringIO(export_passport(passports["piecewise"], "csv").text)))
    assert len([r for r in pw if r["quantity"] == "alpha"]) == 6 and all(
        r["t_lo_c"] for r in pw if r["quantity"] == "beta"
    )


def test_cli_export_current_passport(passports, tmp_path):
    reg = Registry(tmp_path / "reg")
    reg.publish(passports["auto"], inputs=[{"path": "a", "sha256": "a" * 64}], settings={}, code_version="t")
    reg.publish(passports["piecewise"], inputs=[{"path": "b", "sha256": "b" * 64}], settings={}, code_version="t")
    reg.approve("AU-0001", 1, "A. Metrologist")
    exe = str(Path(sys.executable).parent / "thermocal")
    out = tmp_path / "au1.params"
    r = subprocess.run(
        [exe, "export", "AU-0001", "--registry", str(reg.root), "--format", "ardupilot", "--out", str(out), "--json"],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["version"] == 1 and summary["valid_temp_c"] == [-40.0, 70.0]  # the approved one
    assert summary["passport_used"]["approved_by"] == ["A. Metrologist"] and r.stderr == ""
    text = out.read_text()
    assert "INS_TCAL1_ACC1_X" in text and summary["residual"]["total_worst_ug"] > 100
    assert "# status unverified; approved by A. Metrologist" in text
    # a failed version, not approved: exported all the same, with one warning line and the status in the file
    failed = dict(passports["auto"], status="fail")
    reg.publish(
        {k: v for k, v in failed.items() if k not in ("signature", "content_sha256")},
        inputs=[{"path": "c", "sha256": "c" * 64}],
        settings={},
        code_version="t",
    )
    r = subprocess.run(
        [exe, "export", "AU-0001", "3", "--registry", str(reg.root), "--format", "px4"],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        timeout=120,
    )
    assert r.returncode == 0 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith("thermocal: warning: export of AU-0001 v3 failed its verification (status fail)")
    assert "# status fail; not approved" in r.stdout and "# WARNING: this passport failed" in r.stdout
    bad = subprocess.run(
        [exe, "export", "AU-0001", "--registry", str(reg.root), "--format", "betaflight"],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        timeout=120,
    )
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "--format" in bad.stderr
