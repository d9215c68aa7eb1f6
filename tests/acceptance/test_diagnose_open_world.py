"""Diagnosis that never forces a name (issue 14): a wrong or stale passport told apart from left-out physics,
mismatches outside the catalogue reported as such, catalogue parameters found inside their search ranges.

The runs are the standard program at a 1 Hz voltmeter (5 uV noise) made by the simulator, with catalogue effects or
disturbances outside the catalogue (``pipeline.simulate.disturbances``); the truth stays in this test. The passport,
when one is given, is fitted from another, clean run of the same unit (what ``calibrate`` wrote some time ago).
"""

from __future__ import annotations

import copy
import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from flows.diagnose_cmd import diagnose_command
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.diagnose.diagnosis import diagnose_run, fit_passport
from pipeline.diagnose.signal import segment_settings_for
from pipeline.effects.catalogue import EFFECTS
from pipeline.io.runs import write_run
from pipeline.passport.registry import Registry
from pipeline.segment import segment_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.disturbances import DISTURBANCES
from pipeline.simulate.unit import seed000_unit

pytestmark = pytest.mark.slow  # an end-to-end proof on long or many recordings

RATE_HZ = 1.0
UV = 1e-6


@cache
def _passport() -> str:
    calib = simulate(SimConfig(seed=41, rate_hz=RATE_HZ)).run
    return json.dumps(fit_passport(calib, segment_run(calib, segment_settings_for(calib))).document)


def passport() -> dict:
    return json.loads(_passport())


CASES = {  # name -> (catalogue effects, disturbances, noise seed, passport given)
    "clean:given": ([], [], 2, True),
    "clean11:given": ([], [], 11, True),
    "clean100:given": ([], [], 100, True),
    "curvature:given": (
        [
            (
                "temperature_curvature",
                {"c_v_per_c3": [0.3e-9, -0.2e-9, 0.2e-9], "c_rel_per_c3": [0.2e-9, 0.3e-9, -0.2e-9]},
            )
        ],
        [],
        24,
        True,
    ),
    "shift_u0:given": ([], [("constants_shift", {"du0_v": [20e-6, -15e-6, 10e-6]})], 3, True),
    "shift_gain:given": (
        [],
        [("constants_shift", {"du0_v": [0.0, 0.0, 0.0], "dgain_rel": [2e-4, 0.0, -1e-4]})],
        4,
        True,
    ),
    "drift_u0:given": (
        [],
        [("constants_shift", {"du0_v": [0.0, 0.0, 0.0], "du0_rate_v_per_h": [0.9e-6, 0.0, 0.0]})],
        21,
        True,
    ),
    "drift_gain:given": (
        [],
        [("constants_shift", {"du0_v": [0.0, 0.0, 0.0], "dgain_rate_rel_per_h": [0.0, 0.0, 6e-6]})],
        22,
        True,
    ),
    "shift_and_drift:given": (
        [],
        [("constants_shift", {"du0_v": [20e-6, 0.0, -10e-6], "du0_rate_v_per_h": [0.0, -1e-6, 0.0]})],
        23,
        True,
    ),
    "drift_u0": ([("time_drift", {"r_v_per_h": [0.9e-6, 0.0, 0.0]})], [], 21, False),
    "hysteresis:given": ([("thermal_hysteresis", {"h_v": [10e-6, -8e-6, 6e-6]})], [], 5, True),
    "step": ([], [("bias_step", {"t_h": 8.0, "step_v": [20e-6, -10e-6, 0.0]})], 6, False),
    "periodic": ([], [("periodic", {"amp_v": [20e-6, 20e-6, 0.0], "period_s": 1200.0})], 7, False),
    "walk": ([], [("bias_random_walk", {"sigma_v_per_sqrt_h": [3e-6, 3e-6, 3e-6]})], 8, False),
    "lag_0.3s": ([("thermal_lag", {"tau_s": 0.3})], [], 9, False),
    "warmup_3h": ([("warmup_transient", {"a_v": [60e-6, -40e-6, 30e-6], "tau_s": 3 * 3600.0})], [], 10, False),
}


@cache
def diagnosed(name: str) -> dict:
    effects, disturbances, seed, given = CASES[name]
    run = simulate(SimConfig(seed=seed, rate_hz=RATE_HZ, effects=effects, disturbances=disturbances)).run
    return diagnose_run(run, passport() if given else None).report


def named(rep: dict) -> list[str]:
    return [f["effect"] for f in rep["findings"]]


def test_disturbances_are_not_catalogue_ids():
    assert not set(DISTURBANCES) & set(EFFECTS)


@pytest.mark.parametrize("name", ["clean:given", "clean11:given", "clean100:given"])
def test_a_clean_run_agrees_with_the_passport_of_another_run(name):
    """Seeds 11 and 100 are runs where temperature_curvature took up the passport's own error at its calibration
    temperatures (delta-BIC -24 and -21 with the passport held): with its thermal model free to move the
    recording does not need it, and it is not named."""
    rep = diagnosed(name)
    assert rep["verdict"] == "consistent" and rep["findings"] == []
    assert rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]


def test_a_cubic_the_passport_lacks_is_still_named_against_it():
    rep = diagnosed("curvature:given")
    assert named(rep) == ["temperature_curvature"]
    np.testing.assert_allclose(rep["findings"][0]["parameters"]["c_v_per_c3"], [0.3e-9, -0.2e-9, 0.2e-9], atol=0.03e-9)


def test_shifted_offsets_are_a_constants_shift_with_their_amounts():
    rep = diagnosed("shift_u0:given")
    assert named(rep) == ["constants_shift"]
    p = rep["findings"][0]["parameters"]
    assert p["constants"] == "U0" and p["change"] == "at one time"
    np.testing.assert_allclose(p["dU0_v"], [20e-6, -15e-6, 10e-6], atol=0.3 * UV)
    assert all(0 < s < 0.2 * UV for s in p["dU0_sigma_v"])
    assert rep["rms_before_v"] > 10 * UV and rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]


def test_shifted_gains_are_a_constants_shift_of_k():
    rep = diagnosed("shift_gain:given")
    assert named(rep) == ["constants_shift"]
    p = rep["findings"][0]["parameters"]
    assert p["constants"] == "K and U0"
    kii = np.diagonal(seed000_unit().constants_at(np.array([20.0]))[0][0])
    np.testing.assert_allclose(np.diagonal(p["dK_v_per_g"]), kii * np.array([2e-4, 0.0, -1e-4]), atol=1 * UV)
    np.testing.assert_allclose(p["dU0_v"], 0.0, atol=0.3 * UV)


def test_only_the_constants_that_moved_are_named():
    """A gain shift of x alone (the test above): the report names K_xx, not "K, U0 and their thermal model"."""
    f = diagnosed("shift_gain:given")["findings"][0]
    assert f["parameters"]["moved"][:2] == ["K_xx", "K_zz"] and not any(
        m.startswith("U0") for m in f["parameters"]["moved"]
    )
    assert "K xx by" in f["explanation"] and "K zz by" in f["explanation"] and "U0 x by" not in f["explanation"]


@cache
def _poly1_passport() -> str:
    calib = simulate(SimConfig(seed=41, rate_hz=RATE_HZ)).run
    seg = segment_settings_for(calib)
    return json.dumps(
        fit_passport(calib, segment_run(calib, seg), CalibrationSettings(thermal_model="poly1", segment=seg)).document
    )


def test_a_passport_of_too_low_an_order_is_a_finding_not_a_silent_refit():
    """A passport whose thermal model is linear where the unit's is not (calibrate --thermal-model poly1; its
    stated uncertainty is large, honestly): against a clean recording of the unit it is off by ~860 uV. That is a
    constants_shift finding with the amounts (the power the passport lacks named), never `consistent` with the
    departure only in a note."""
    run = simulate(SimConfig(seed=2, rate_hz=RATE_HZ)).run
    rep = diagnose_run(run, json.loads(_poly1_passport())).report
    assert rep["verdict"] == "mismatch" and named(rep) == ["constants_shift"]
    f = rep["findings"][0]
    p = f["parameters"]
    assert p["constants"] == "K, U0 and their thermal model" and "power_2" in p["thermal_model_change"]
    assert p["within_passport_uncertainty"] and p["departure_rms_v"] > 100 * p["noise_rms_v"]
    assert any(m.endswith("power 2") for m in p["beyond_fit_uncertainty"])
    assert "polynomial of order 1" in f["explanation"] and "do not hold" in f["explanation"]
    assert rep["rms_before_v"] > 300 * UV and rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]


def test_a_passport_whose_thermal_model_is_off_is_named_as_such_not_as_physics():
    doc = passport()
    doc["thermal_model"]["alpha"]["x"][0] += 2e-6  # V/C: 120 uV off at -40 C
    run = simulate(SimConfig(seed=2, rate_hz=RATE_HZ)).run
    rep = diagnose_run(run, doc).report
    assert named(rep) == ["constants_shift"]
    p = rep["findings"][0]["parameters"]
    assert p["constants"] == "K, U0 and their thermal model"
    np.testing.assert_allclose(p["thermal_model_change"]["power_1"]["dU0_v_per_c"], [-2e-6, 0.0, 0.0], atol=0.02e-6)
    assert rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]


def test_offsets_drifting_within_the_recording_are_a_gradual_constants_shift():
    """U0 of x drifts by +15 uV over the 16.7 h run, from the passport's value: against the passport that is the
    constants moving (not the catalogue's time_drift), with the rate and the end value and their uncertainty."""
    rep = diagnosed("drift_u0:given")
    assert named(rep) == ["constants_shift"]
    f = rep["findings"][0]
    p = f["parameters"]
    assert p["change"] == "gradual" and p["drifting"] == "U0" and p["constants"] == "U0"
    assert not p["moved_before_the_recording"]
    np.testing.assert_allclose(p["dU0_rate_v_per_h"], [0.9e-6, 0.0, 0.0], atol=0.03e-6)
    assert all(0 < s < 0.03e-6 for s in p["dU0_rate_sigma_v_per_h"])
    np.testing.assert_allclose(p["dU0_end_v"], np.array([0.9e-6, 0.0, 0.0]) * p["duration_h"], atol=0.5 * UV)
    assert all(0 < s < 0.5 * UV for s in p["dU0_end_sigma_v"])
    assert "time_drift" in f["explanation"] and "drift" in f["explanation"]
    assert rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]
    # the extended model carries the drift as the catalogue's forward model of it
    eff = {e["effect"]: e["parameters"] for e in rep["extended_model"]["effects"]}
    np.testing.assert_allclose(eff["time_drift"]["r_v_per_h"], p["dU0_rate_v_per_h"])


def test_without_a_passport_the_same_drift_is_the_catalogues_time_drift():
    rep = diagnosed("drift_u0")
    assert named(rep) == ["time_drift"]
    np.testing.assert_allclose(rep["findings"][0]["parameters"]["r_v_per_h"], [0.9e-6, 0.0, 0.0], atol=0.03e-6)


def test_a_gain_drifting_within_the_recording_is_a_gradual_shift_of_k():
    """The z gain drifts by +100 ppm over the run (6 ppm/h): K and U0 drift, none moved before the recording."""
    rep = diagnosed("drift_gain:given")
    assert named(rep) == ["constants_shift"]
    p = rep["findings"][0]["parameters"]
    assert p["change"] == "gradual" and p["drifting"] == "K and U0"
    ppm = np.asarray(p["gain_drift_ppm_over_run"])
    np.testing.assert_allclose(ppm, [0.0, 0.0, 6.0 * p["duration_h"]], atol=5.0)
    assert all(0 < s < 5.0 for s in p["gain_drift_sigma_ppm_over_run"])
    kzz = np.diagonal(seed000_unit().constants_at(np.array([20.0]))[0][0])[2]
    assert np.diagonal(p["dK_rate_v_per_g_per_h"])[2] == pytest.approx(6e-6 * kzz, rel=0.1)
    assert rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]


def test_a_shift_before_the_recording_and_a_drift_within_it_are_told_apart():
    rep = diagnosed("shift_and_drift:given")
    assert named(rep) == ["constants_shift"]
    p = rep["findings"][0]["parameters"]
    assert p["change"] == "gradual" and p["moved_before_the_recording"] and p["constants"] == "U0"
    np.testing.assert_allclose(p["dU0_v"], [20e-6, 0.0, -10e-6], atol=0.5 * UV)
    np.testing.assert_allclose(p["dU0_rate_v_per_h"], [0.0, -1e-6, 0.0], atol=0.03e-6)
    end = np.array([20e-6, 0.0, -10e-6]) + np.array([0.0, -1e-6, 0.0]) * p["duration_h"]
    np.testing.assert_allclose(p["dU0_end_v"], end, atol=0.5 * UV)


def test_left_out_physics_on_top_of_a_good_passport_is_not_a_shift():
    rep = diagnosed("hysteresis:given")
    assert named(rep) == ["thermal_hysteresis"]
    np.testing.assert_allclose(rep["findings"][0]["parameters"]["h_v"], [10e-6, -8e-6, 6e-6], atol=0.5 * UV)


def test_a_bias_step_is_unexplained_and_located_in_time():
    rep = diagnosed("step")
    assert named(rep) == ["unexplained"]
    f = rep["findings"][0]
    assert f["parameters"]["empirical_correction"] == "step"
    assert abs(f["parameters"]["step_at_h"] - 8.0) < 0.25
    np.testing.assert_allclose(f["parameters"]["step_v"], [20e-6, -10e-6, 0.0], atol=1.5 * UV)
    assert f["where"]["axes"] == ["x", "y"]
    assert "step" in f["explanation"] and "empirical" in f["explanation"]
    shares = f["parameters"]["shares"]  # a step is a function of time (was time 0.86 + orientation 0.35)
    assert max(shares, key=shares.get) == "time" and shares["time"] > 0.85 and sum(shares.values()) <= 1 + 1e-6
    assert rep["rms_after_v"] < 1.1 * rep["rms_noise_v"] < 0.3 * rep["rms_before_v"]


def test_a_periodic_disturbance_is_unexplained_with_its_period():
    rep = diagnosed("periodic")
    assert named(rep) == ["unexplained"]
    p = rep["findings"][0]["parameters"]
    assert p["empirical_correction"] == "periodic" and abs(p["period_s"] / 1200.0 - 1) < 0.05
    assert rep["findings"][0]["where"]["axes"] == ["x", "y"]
    assert rep["rms_after_v"] < 1.15 * rep["rms_noise_v"]


#: out-of-catalogue disturbances at the simulator's own default sizes and at 10 Hz (a block noise of ~0.4 uV, where
#: a catalogue effect could nibble at any imperfection of the empirical correction): name -> (effects,
#: disturbances, noise seed, rate Hz, program)
OPEN = {
    "periodic:default:10hz": ([], [("periodic", {})], 7, 10.0, "standard"),
    "periodic:5uv:10hz:short": ([], [("periodic", {"amp_v": [5e-6, 5e-6, 0.0]})], 7, 10.0, "short"),
    "walk:default:10hz:short": ([], [("bias_random_walk", {})], 8, 10.0, "short"),
    "face_3deg": ([("fixture_face_error", {"sigma_deg": 3.0, "seed": 3})], [], 9, 1.0, "standard"),
}


@cache
def open_world(name: str) -> dict:
    effects, disturbances, seed, rate, program = OPEN[name]
    run = simulate(SimConfig(seed=seed, rate_hz=rate, program=program, effects=effects, disturbances=disturbances)).run
    return diagnose_run(run).report


def _signature(rep: dict) -> dict:
    """The unexplained finding's parameters, after checking it is the only finding."""
    assert named(rep) == ["unexplained"], [(f["effect"], f["explanation"]) for f in rep["findings"]]
    return rep["findings"][0]["parameters"]


@pytest.mark.parametrize("name", ["periodic:default:10hz", "periodic:5uv:10hz:short"])
def test_a_periodic_disturbance_at_10hz_forces_no_catalogue_name(name):
    """20 uV at 10 Hz was named face error (184 arcsec), warm-up, K2 +309 uV/g^2, curvature, hysteresis beside
    the unexplained; 5 uV a spurious warm-up. Now only unexplained, periodic with its period, a function of time."""
    rep = open_world(name)
    p = _signature(rep)
    assert p["empirical_correction"] == "periodic" and abs(p["period_s"] / 1200.0 - 1) < 0.005
    assert abs(p["dominant_period_s"] / 1200.0 - 1) < 0.005 and p["periodic_share"] > 0.8
    assert max(p["shares"], key=p["shares"].get) == "time" and p["shares"]["time"] > 0.9
    assert sum(p["shares"].values()) <= 1.0 + 1e-6
    assert p["axes"] == ["x", "y"]
    assert rep["rms_after_v"] < 1.3 * rep["rms_noise_v"] < 0.3 * rep["rms_before_v"]


def test_a_default_random_walk_at_10hz_forces_no_catalogue_name():
    """10 uV/sqrt(h) at 10 Hz was named face error (323 arcsec), curvature, hysteresis, K2, a 2 mV warm-up and a
    2.4 s lag beside the unexplained: each only nibbles at the wander (the residual where it shows stays at twice
    the noise), so none is named."""
    rep = open_world("walk:default:10hz:short")
    p = _signature(rep)
    assert p["empirical_correction"].startswith("time")
    assert max(p["shares"], key=p["shares"].get) == "time" and p["shares"]["time"] > 0.7
    assert p["axes"] == ["x", "y", "z"]
    assert rep["rms_after_v"] < 0.2 * rep["rms_before_v"]
    assert any("does not explain the mismatch beside the unexplained one" in n for n in rep["notes"])


def test_an_orientation_dependent_mismatch_is_a_function_of_orientation():
    """Face errors of degrees (beyond the catalogue's plausible 1 deg): unexplained, an offset per orientation."""
    rep = open_world("face_3deg")
    p = _signature(rep)
    assert p["empirical_correction"] == "orientation"
    assert max(p["shares"], key=p["shares"].get) == "orientation" and p["shares"]["orientation"] > 0.9
    assert "orientation" in rep["findings"][0]["explanation"]


def test_a_random_walk_is_unexplained_as_a_function_of_time():
    rep = diagnosed("walk")
    assert named(rep) == ["unexplained"]  # thermal_hysteresis would absorb part of it: not named
    f = rep["findings"][0]
    assert f["parameters"]["empirical_correction"].startswith("time")
    assert max(f["parameters"]["shares"], key=f["parameters"]["shares"].get) == "time"
    assert f["rms_after_v"] < 0.5 * f["rms_before_v"]


@pytest.mark.parametrize(
    "name, effect, tau_s", [("lag_0.3s", "thermal_lag", 0.3), ("warmup_3h", "warmup_transient", 3 * 3600.0)]
)
def test_time_constants_are_found_inside_the_search_range(name, effect, tau_s):
    rep = diagnosed(name)
    assert named(rep) == [effect]
    assert abs(rep["findings"][0]["parameters"]["tau_s"] / tau_s - 1) < 0.1


def test_diagnose_with_registry_uses_the_units_current_passport(tmp_path: Path):
    reg = Registry(tmp_path / "reg")
    old = passport()
    reg.publish(old, inputs=[], settings={"n": 1}, code_version="test")
    newer = copy.deepcopy(old)
    newer["coefficients"]["U0"] = (np.asarray(newer["coefficients"]["U0"]) + np.array([20e-6, -15e-6, 10e-6])).tolist()
    reg.publish(newer, inputs=[], settings={"n": 2}, code_version="test")
    run = simulate(SimConfig(seed=3, rate_hz=RATE_HZ)).run
    path = write_run(run, tmp_path / "run.mcap", "mcap")
    rep = diagnose_command(path, None, True, tmp_path / "d.png", tmp_path / "d.json", registry=tmp_path / "reg")
    assert "AU-0001 v2 (status " in rep["passport_source"]
    assert named(rep) == ["constants_shift"]
    np.testing.assert_allclose(rep["findings"][0]["parameters"]["dU0_v"], [-20e-6, 15e-6, -10e-6], atol=0.3 * UV)
