"""Calibration uses every static position it can name on every plateau the data support (issue 14): soaks too short
for the plateau test (the unit still settling: each position referred to its own temperature), a test position
missing at one temperature (least squares over the five there are), and a status that is never ``pass`` when the
verification does not exercise the thermal model over its range. ``diagnose`` on such runs names nothing, neither
against the passport fitted from the run nor against the unit's passport from another, standard run (0 false
alarms on clean runs, short-soak and missing-position programs included; the truth is never given to diagnose).

Runs: the standard program's sequence of temperatures and positions (docs/physics.md) at a 1 Hz voltmeter with 5 uV
noise, with shorter soaks or one position left out; the seed 000 unit's true constants are the reference.
"""

from __future__ import annotations

import json
from functools import cache

import numpy as np
import pytest

from pipeline.calibrate.tilt import calibrate
from pipeline.diagnose.diagnosis import diagnose_run, fit_passport
from pipeline.diagnose.signal import segment_settings_for
from pipeline.segment import segment_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.program import TP, VP, Program, Ramp, Soak, Stage, visit
from pipeline.simulate.unit import seed000_unit

PLAN = [(20.0, TP), (-40.0, TP), (-10.0, VP), (20.0, TP + VP), (45.0, VP), (70.0, TP), (20.0, TP + VP)]
TP_STAGES = [k for k, (_, pos) in enumerate(PLAN) if "TP1" in pos]


def program(
    soak_s: float = 3600.0,
    long_soak_s: float = 5400.0,
    drop: tuple[int, str] | None = None,
    vp_temps: tuple[float, ...] | None = None,
) -> Program:
    stages = []
    for k, (sp, pos) in enumerate(PLAN):
        pos = tuple(p for p in pos if (k, p) != drop)
        if vp_temps is not None and sp not in vp_temps:
            pos = tuple(p for p in pos if p not in VP)
        soak = long_soak_s if sp in (-40.0, 70.0) else soak_s
        stages.append(Stage(f"{sp:+.0f} C", (Ramp(sp, 1.0), Soak(soak)) + (visit(pos) if pos else ())))
    return Program("variant", tuple(stages), case_lag_s=600.0, air_lag_s=90.0)


@cache
def _run(soak_s: float, drop: tuple[int, str] | None = None, vp_temps=None, seed: int = 5):
    return simulate(
        SimConfig(seed=seed, rate_hz=1.0, program=program(soak_s, soak_s if soak_s < 3600 else 5400.0, drop, vp_temps))
    ).run


@cache
def _standard_passport_json() -> str:
    """The unit's passport from another run, on the standard program (what ``calibrate`` wrote some time ago)."""
    calib = simulate(SimConfig(seed=41, rate_hz=1.0)).run
    return json.dumps(fit_passport(calib, segment_run(calib, segment_settings_for(calib))).document)


def check_no_false_alarm(run) -> None:
    """diagnose names nothing, with the passport fitted from the run and with the unit's passport of another run."""
    for passport in (None, json.loads(_standard_passport_json())):
        rep = diagnose_run(run, passport).report
        assert rep["verdict"] == "consistent", (
            passport is not None,
            [(f["effect"], f["delta_bic"]) for f in rep["findings"]],
        )
        assert rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]


def check_constants(result):
    """Every TP plateau is used, and its constants are the unit's true ones at its temperature."""
    fits = result.fit.per_plateau
    assert len(fits) == 5
    unit = seed000_unit()
    for f in fits:
        k, u0 = unit.constants_at(np.array([f.temp_c]))
        np.testing.assert_allclose(f.K, k[0], atol=3e-6)  # V/g: a few ppm of a 0.55 V/g gain
        np.testing.assert_allclose(f.U0, u0[0], atol=3e-6)  # V
    assert result.passport["thermal_model"]["order"] == 2
    assert result.status == "pass"
    assert max(abs(r.dg_method1_g) for r in result.rows) < 2e-5


@pytest.mark.parametrize("soak_min", [20, 25, 30, 35])
def test_short_soaks_keep_every_plateau_and_diagnose_names_nothing(soak_min):
    run = _run(soak_min * 60.0)
    res = calibrate([run])
    check_constants(res)
    assert any(f.temp_c < -39 for f in res.fit.per_plateau) and any(f.temp_c > 69 for f in res.fit.per_plateau)
    check_no_false_alarm(run)


@pytest.mark.parametrize("stage", TP_STAGES)
def test_a_missing_position_at_each_temperature_is_fitted_by_least_squares(stage):
    position = TP[(stage + 3) % 6]
    run = _run(3600.0, (stage, position))
    res = calibrate([run])
    check_constants(res)
    fitted = [f for f in res.fit.per_plateau if position not in f.positions]
    assert len(fitted) == 1 and fitted[0].method == "least_squares"
    check_no_false_alarm(run)


def test_positions_that_cannot_determine_the_constants_are_said_so():
    from pipeline.calibrate.tilt import determines_constants

    assert determines_constants(["TP1", "TP2", "TP3", "TP5", "TP6"])
    assert determines_constants(["TP1", "TP2", "TP5", "TP6"])
    assert not determines_constants(["TP1", "TP3", "TP5", "TP6"])  # no y: K_iy undetermined
    assert not determines_constants(["TP6"])


def test_a_status_is_not_pass_when_the_vp_data_do_not_exercise_the_thermal_model():
    """VP positions only at +20 C (and VP6, carried through the +45 C soak, there): nothing verifies the model below
    T0 although it reaches -40 C."""
    res = calibrate([_run(3600.0, None, (20.0,))])
    assert all(r.temp_c > 15.0 for r in res.rows) and all(r.passed for r in res.rows)
    assert res.status == "unverified"
    assert any("does not exercise the thermal model below T0 (the model reaches -40" in w for w in res.warnings)
    assert res.passport["status"] == "unverified"
