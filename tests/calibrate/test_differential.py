"""Differential specific-force thermal calibration (seed 003) on simulated temperature-cycle runs with thermal lag
and fixture face errors of 1.5 degrees (1 sigma per rotation component): the orientation windows, the recovered
temperature coefficients against the simulator's truth, the 10 s standard deviation over the full cycle with and
without the rate terms, and passports of method ``differential``."""

from __future__ import annotations

import json

import jsonschema
import numpy as np
import pytest

from pipeline import compensate
from pipeline.calibrate import differential
from pipeline.calibrate.differential_fit import (
    DifferentialModel,
    DifferentialSettings,
    block_data,
    compensate_blocks,
    compensate_run,
    fit_differential,
    window_std_g,
)
from pipeline.calibrate.tilt import fit_unit, observe_run, verify_unit
from pipeline.errors import CalibrationError
from pipeline.passport.document import build_passport, load_model, load_passport
from pipeline.passport.registry import Registry
from pipeline.positions import TEST_POSITIONS
from pipeline.simulate import program
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import seed000_unit
from pipeline.thermal import PolynomialModel
from tests.conftest import REPO

T0 = 20.0
TAU_S = 120.0
RATE_HZ = 2.0  # 10 s blocks of 20 samples: 5 uV / sqrt(20) = 1.1 uV, about 2 micro-g per block
SIX = tuple(TEST_POSITIONS)


def _cycle_run(seed: int, face_seed: int, orientations=SIX):
    """The unit held in each orientation while the chamber cycles +20 -> -40 -> +70 -> +20 C at 1 C/min
    (program.differential_program), element lag 120 s, face errors 1.5 deg."""
    name = "differential_test_" + "_".join(orientations)
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(program.PROGRAMS, name, lambda: program.differential_program(orientations))
        return simulate(
            SimConfig(
                program=name,
                seed=seed,
                rate_hz=RATE_HZ,
                effects=[
                    ("thermal_lag", {"tau_s": TAU_S}),
                    ("fixture_face_error", {"sigma_deg": 1.5, "seed": face_seed}),
                ],
            )
        )


@pytest.fixture(scope="module")
def runs():
    return _cycle_run(2, 4).run, _cycle_run(3, 5).run  # fit, held-out (other noise and face errors)


@pytest.fixture(scope="module")
def base():
    """The normal-temperature calibration the method starts from: a tilt passport of a short-program run."""
    run = simulate(SimConfig(program="short", seed=8)).run
    obs, _ = observe_run(run)
    fit = fit_unit("AU-0001", obs)
    rows, status = verify_unit(fit.model, obs, T0)
    return run, build_passport(fit, rows, status, g_local_mps2=9.80665, plateaus=[])


@pytest.fixture(scope="module")
def blocks(runs, base):
    K0, U0 = _k0_u0(base[1])
    return block_data(runs[0], K0, U0), block_data(runs[1], K0, U0)


def _k0_u0(passport):
    return np.asarray(passport["coefficients"]["K"]), np.asarray(passport["coefficients"]["U0"])


def test_orientation_windows_found_without_positions(blocks):
    """Six windows, one per orientation, found from the signal: each a0 has |a0| = 1 within 3e-3 (the uncompensated
    temperature error, up to 5 mg, averaged over the cycle), points within 8 degrees of its nominal axis (face errors
    1.5 deg per component) and covers the cycle's temperatures."""
    d = blocks[0]
    assert len(d.windows) == 6
    for w, p in zip(d.windows, SIX):
        a0 = np.asarray(w.a0_g)
        assert abs(np.linalg.norm(a0) - 1) < 3e-3
        cos = a0 @ np.asarray(TEST_POSITIONS[p]) / np.linalg.norm(a0)
        assert 0.1 < np.degrees(np.arccos(min(cos, 1.0))) < 8.0
        assert w.temp_min_c < -30 and w.temp_max_c > 60
        assert (w.t_end_ns - w.t_start_ns) / 1e9 > 5 * 3600


def _std_max_ug(model, data):
    return float(window_std_g(data, compensate_blocks(model, data)).max() * 1e6)


MODELS = {
    "static": DifferentialSettings(rate_order=0),
    "paper": DifferentialSettings(),
    "rate_dt": DifferentialSettings(rate_dt_order=1),
    "lag": DifferentialSettings(rate_order=0, lag_fit=True),
}


@pytest.fixture(scope="module")
def fits(blocks, base):
    K0, U0 = _k0_u0(base[1])
    return {name: fit_differential([blocks[0]], K0, U0, T0, st) for name, st in MODELS.items()}


def test_rate_terms_matter_and_the_lag_model_reaches_10_micro_g(blocks, base, fits):
    """10 s standard deviation over the full cycle, max over the six orientations and three axes, on the held-out
    run (element lag 120 s, 1 C/min ramps, seed 000's curved bias): uncompensated about 5 mg; polynomial without
    rate terms about 430 ug; with the paper's rate terms (order 2) clearly less, about 250 ug; with the rate terms
    also times dT about 70 ug; with the fitted element lag at the noise floor (2 ug per 10 s block at 2 Hz), under
    the paper's 10 ug."""
    K0, U0 = _k0_u0(base[1])
    held = blocks[1]
    none = DifferentialModel(PolynomialModel(K0, U0, T0, 0, np.zeros((0, 3)), np.zeros((0, 3, 3))))
    std = {"uncompensated": _std_max_ug(none, held)}
    std.update({name: _std_max_ug(f.model, held) for name, f in fits.items()})
    assert std["uncompensated"] > 4000
    assert 300 < std["static"] < 600
    assert std["paper"] < 0.7 * std["static"]
    assert std["rate_dt"] < 0.4 * std["paper"]
    assert std["lag"] < 3.0


def test_coefficients_against_truth(fits):
    """With the lag model: tau within 2 s of 120 s; U0(T) within 5 uV of the truth and K(T) (gains and cross-axis
    terms) within 2e-6 of the gain over -40..+70 C (what the 2 ug blocks and the base calibration's own error allow);
    the third-order coefficients near zero (the truth is quadratic); every channel has bias, scale and both
    cross-axis terms. The paper's model (no lag) misses U0(T) by about 0.1-0.3 mV: its polynomials absorb part of
    the lag."""
    unit = seed000_unit()
    temps = np.linspace(-40.0, 70.0, 111)
    Kt, Ut = unit.constants_at(temps)
    fit = fits["lag"]
    assert fit.model.lag_tau_s == pytest.approx(TAU_S, abs=2.0)
    Kf, Uf = fit.model.constants_at(temps)
    assert np.abs(Uf - Ut).max() < 5e-6
    assert np.abs(Kf - Kt).max() / 0.55 < 2e-6
    assert np.abs(fit.model.static.alpha[2]).max() < 2e-9  # V/C^3 (alpha_2 is about 1e-6 V/C^2)
    for c, terms in enumerate(fit.terms):
        assert sorted(terms) == sorted(["bias", "scale"] + [f"cross_{a}" for a in "xyz" if a != "xyz"[c]])
    _, Up = fits["paper"].model.constants_at(temps)
    assert 5e-5 < np.abs(Up - Ut).max() < 5e-4


def test_passport_of_method_differential(runs, base, tmp_path):
    """``differential.calibrate`` makes a schema-valid passport (method, polynomial thermal model of order 3,
    rate_terms with the lag); ``compensate_run`` on the held-out run gives 10 s block std under 10 ug at every
    orientation; ``pipeline.compensate`` works on the same passport (without lag: hundreds of ug)."""
    fit_run, held = runs
    mc = differential.calibrate(
        [fit_run], base_passport=base[1], differential=DifferentialSettings(rate_order=0, lag_fit=True)
    )
    doc = mc.passport
    assert doc["method"] == "differential" and doc["thermal_model"]["order"] == 3
    assert doc["rate_terms"]["lag_tau_s"] == pytest.approx(TAU_S, abs=2.0)
    pub = Registry(tmp_path / "reg").publish(doc, inputs=[], settings={"method": "differential"}, code_version="test")
    stored = json.loads(pub.path.read_text())
    jsonschema.validate(stored, json.loads((REPO / "schemas" / "thermocal.passport.json").read_text()))

    t_ns, a = compensate_run(stored, held)
    d = block_data(held, *_k0_u0(base[1]))
    for w in d.windows:
        inside = (t_ns >= w.t_start_ns) & (t_ns <= w.t_end_ns)
        n = inside.sum() // 20 * 20
        blocks10 = a[inside][:n].reshape(-1, 20, 3).mean(axis=1)
        assert blocks10.std(axis=0).max() < 10e-6
    model = load_model(stored)
    a1 = compensate.method1(model, d.u_v, d.temperature()[0])
    assert 5e-5 < window_std_g(d, a1).max() < 1e-3


def test_rate_terms_round_trip_through_the_passport_form(base, fits):
    """The paper's model (default settings: rate order 2) written as the passport's ``rate_terms`` and read back
    gives the same constants at any temperature and rate."""
    K0, U0 = _k0_u0(base[1])
    fit = fits["paper"]
    assert fit.model.rate.order == 2 and fit.model.lag_tau_s == 0.0
    doc = {
        "coefficients": {"K": K0.tolist(), "U0": U0.tolist()},
        "normal_temp_c": T0,
        "thermal_model": fit.model.static.to_dict(),
        "rate_terms": fit.model.rate.to_dict(),
    }
    back = load_passport(json.loads(json.dumps(doc))).compensation_model()
    assert isinstance(back, DifferentialModel)
    temps, rates = np.array([-40.0, 0.0, 20.0, 70.0]), np.array([-1.0, 0.5, 0.0, 1.0])
    for x, y in zip(back.constants_at(temps, rates), fit.model.constants_at(temps, rates)):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15)


def test_three_orientations_leave_one_scale_undetermined(base):
    """With TP1, TP3, TP6 (program.differential_program's default) the y channel never has gravity along it:
    its scale-factor terms are not fitted and a note says so; x and z get theirs."""
    run = _cycle_run(4, 6, ("TP1", "TP3", "TP6")).run
    K0, U0 = _k0_u0(base[1])
    fit = fit_differential([block_data(run, K0, U0)], K0, U0, T0, DifferentialSettings(rate_order=0))
    assert "scale" in fit.terms[0] and "scale" in fit.terms[2] and "scale" not in fit.terms[1]
    assert any("channel y" in n for n in fit.notes)
    assert np.all(fit.model.static.rel[:, 1, 1] == 0)


def test_run_without_long_orientation_raises(base):
    K0, U0 = _k0_u0(base[1])
    with pytest.raises(CalibrationError, match="no orientation held"):
        block_data(base[0], K0, U0)
