"""Standard uncertainties of the passport constants (pipeline/uncertainty.py), tested for coverage against the
simulator's truth over many noise seeds: about 68 % of the errors within 1 sigma and 95 % within 2 sigma, for the
constants per plateau, the normal-temperature constants and every thermal coefficient, and not absurdly wide."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.calibrate import tilt
from pipeline.passport.document import build_passport
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import random_unit, seed000_unit
from pipeline.uncertainty import estimator_matrix, plateau_sigma, regression_cov

N_SEEDS = 48


def _z_scores(fit, truth) -> dict[str, list[float]]:
    z: dict[str, list[float]] = {"per_plateau": [], "normal_temp": [], "thermal": []}
    for p in fit.per_plateau:
        K, U0 = truth.constants_at(p.temp_c)
        z["per_plateau"] += list(((p.K - K[0]) / p.K_sigma).ravel()) + list((p.U0 - U0[0]) / p.U0_sigma)
    K, U0 = truth.constants_at(fit.normal_temp_c)
    s = fit.uncertainty
    z["normal_temp"] += list(((fit.model.K0 - K[0]) / s.K0).ravel()) + list((fit.model.U00 - U0[0]) / s.U00)
    want, got = truth.relative_coefficients(), fit.model.to_dict()
    for group in ("alpha", "beta", "gamma"):
        for key, values in got[group].items():
            for n, v in enumerate(values):
                z["thermal"].append((v - want[group][key][n]) / s.thermal_model[group][key][n])
    return z


@pytest.fixture(scope="module")
def coverage():
    """Short programs at 1 Hz (seed 000's unit and a random unit), default noise, one calibration per seed."""
    z: dict[str, list[float]] = {"per_plateau": [], "normal_temp": [], "thermal": []}
    fits = []
    for seed in range(N_SEEDS):
        unit_seed = None if seed % 2 == 0 else 7
        res = simulate(SimConfig(seed=500 + seed, program="short", rate_hz=1.0, unit_seed=unit_seed))
        truth = seed000_unit() if unit_seed is None else random_unit(unit_seed)
        obs, _ = tilt.observe_run(res.run)
        fit = tilt.fit_unit(res.run.meta.unit_serial, obs, tilt.CalibrationSettings(), res.run.meta.normal_temp_c)
        fits.append(fit)
        for k, v in _z_scores(fit, truth).items():
            z[k] += v
    return {k: np.abs(np.array(v)) for k, v in z.items()}, fits


@pytest.mark.parametrize("what", ["per_plateau", "normal_temp", "thermal"])
def test_coverage_one_and_two_sigma(coverage, what):
    z = coverage[0][what]
    assert np.all(np.isfinite(z)) and len(z) >= 12 * N_SEEDS
    within1, within2 = np.mean(z < 1.0), np.mean(z < 2.0)
    assert 0.60 <= within1 <= 0.78, (what, within1)
    assert 0.92 <= within2 <= 0.99, (what, within2)
    # not absurdly wide: the errors are not all far inside their sigma (a normal's median |z| is 0.674)
    assert 0.5 <= np.median(z) <= 0.85, (what, np.median(z))


def test_sigma_magnitudes_in_engineering_units(coverage):
    """5 micro-V noise per sample, 1 Hz, 60 s holds: about a micro-g and a few ppm of gain per plateau."""
    for fit in coverage[1][:4]:
        gains = np.abs(np.diag(fit.model.K0))
        for p in fit.per_plateau:
            ppm = p.K_sigma / gains[:, None] * 1e6
            ug = p.U0_sigma / gains * 1e6
            assert np.all((0.1 < ppm) & (ppm < 10)), ppm
            assert np.all((0.05 < ug) & (ug < 5)), ug


def test_six_position_estimator_matches_closed_form_variance():
    """Closed form: K_ix = (U6 - U5)/2 has variance (s5^2 + s6^2)/4; U0 the mean of six has sum(s^2)/36."""
    names = ["TP1", "TP2", "TP3", "TP4", "TP5", "TP6"]
    var = np.arange(1, 19, dtype=float).reshape(6, 3) * 1e-12
    K_sig, U0_sig = plateau_sigma(estimator_matrix(names, "six_position"), var)
    assert np.allclose(K_sig[:, 0] ** 2, (var[4] + var[5]) / 4)
    assert np.allclose(K_sig[:, 2] ** 2, (var[0] + var[2]) / 4)
    assert np.allclose(U0_sig**2, var.sum(axis=0) / 36)
    # a repeated position is averaged first: its mean has half the variance
    K2, _ = plateau_sigma(estimator_matrix(names + ["TP6"], "six_position"), np.vstack([var, var[5]]))
    assert np.allclose(K2[:, 0] ** 2, (var[4] + var[5] / 2) / 4)


def test_passport_records_uncertainty_and_valid_range(coverage):
    fit = coverage[1][0]
    doc = build_passport(fit, [], "unverified", g_local_mps2=9.80665, plateaus=[])
    assert doc["valid_temp_c"] == [-40.0, 70.0]
    u = doc["uncertainty"]
    assert np.array(u["coefficients"]["K"]).shape == (3, 3) and len(u["coefficients"]["U0"]) == 3
    assert len(u["per_plateau"]) == len(doc["per_plateau"])
    assert [p["temp_c"] for p in u["per_plateau"]] == [p["temp_c"] for p in doc["per_plateau"]]
    tm, sig = doc["thermal_model"], u["thermal_model"]
    assert sig["kind"] == tm["kind"] and sig["order"] == tm["order"]
    for group in ("alpha", "beta", "gamma"):
        assert set(sig[group]) == set(tm[group])
        assert all(len(sig[group][k]) == len(tm[group][k]) for k in tm[group])


def test_piecewise_model_uncertainty_mirrors_segments():
    res = simulate(SimConfig(seed=3, program="short", rate_hz=1.0))
    obs, _ = tilt.observe_run(res.run)
    fit = tilt.fit_unit("AU-0001", obs, tilt.CalibrationSettings(thermal_model="piecewise"), 20.0)
    truth = seed000_unit()
    tm, sig = fit.model.to_dict(), fit.uncertainty.thermal_model
    assert sig["breakpoints_c"] == tm["breakpoints_c"] and len(sig["segments"]) == len(tm["segments"]) == 2
    K_nodes, U0_nodes = truth.constants_at(np.array(tm["breakpoints_c"]))
    for s, (seg, ss) in enumerate(zip(tm["segments"], sig["segments"])):
        span = seg["t_hi_c"] - seg["t_lo_c"]
        for i, ax in enumerate("xyz"):
            true_alpha = (U0_nodes[s + 1, i] - U0_nodes[s, i]) / span  # the chord of the true curve
            assert 0 < ss["alpha"][ax] < 1e-7
            assert abs(seg["alpha"][ax] - true_alpha) < 5 * ss["alpha"][ax]


def test_regression_cov_keeps_the_largest_of_several_clusterings():
    """Residuals correlated over 40 equations (a slowly read thermosensor's smoothed noise in 10-s blocks),
    clustered two ways (36 long stretches, 150 short ones): every coefficient's standard uncertainty is the largest
    of the two sandwiches and the noise floor, its correlations those of the first clustering; one clustering
    alone gives its own."""
    rng = np.random.default_rng(3)
    n = 6000
    t = np.arange(n)
    temp = 55.0 * np.sin(2 * np.pi * t / 1000.0)
    X = np.column_stack([temp, temp**2])
    resid = rng.normal(0.0, 1.0, n) + np.convolve(rng.normal(0.0, 1.0, n + 39), np.ones(40) / 6.0, "valid")
    floor = np.full(n, 0.5)
    long_, short = t // 170, t // 40
    each = [np.sqrt(np.diag(regression_cov(X, resid, floor, c))) for c in (long_, short)]
    both = regression_cov(X, resid, floor, np.vstack([long_, short]))
    alone = regression_cov(X, resid, floor, long_)
    noise = np.sqrt(np.diag(np.linalg.pinv(X.T @ X) @ (X.T * floor) @ X @ np.linalg.pinv(X.T @ X)))
    assert np.allclose(np.sqrt(np.diag(both)), np.maximum.reduce([each[0], each[1], noise]), rtol=1e-9)
    corr = both / np.outer(np.sqrt(np.diag(both)), np.sqrt(np.diag(both)))
    assert np.allclose(corr, alone / np.outer(each[0], each[0]), rtol=1e-9)
    assert not np.allclose(each[0], each[1], rtol=0.05)  # the two clusterings differ: the test tells them apart


def test_the_resolution_floor_is_what_averaging_leaves_of_the_rounding():
    """A segment mean of readings rounded to a step q: with no noise the rounding error stays (q^2 / 12 over an
    unknown position within a step); noise of a few steps dithers it away, so a 1-uV logger with 5 uV of noise is
    not stated 3x less precise than its float64 record (a 2-Hz standard run rounded to 1 uV: sigma K 1.0e-7 ->
    1.4e-7 V/g with the whole q^2 / 12). Against Monte Carlo: never below the mean-square error of the mean, and
    equal to it (within 20 %) from half a step of noise up."""
    from pipeline.uncertainty import segment_noise_var_v2

    rng = np.random.default_rng(7)
    q, n, m = 1e-6, 1000, 3000
    for noise in (0.0, 0.1, 0.3, 0.5, 1.0, 5.0):
        true_v = rng.uniform(0.0, q, m)
        read = np.round((true_v[:, None] + noise * q * rng.standard_normal((m, n))) / q) * q
        mse = np.mean((read.mean(axis=1) - true_v) ** 2)
        std = read.std(axis=1)
        stated = np.mean(segment_noise_var_v2(np.c_[std, std, std], np.full(m, n), np.full(3, q))[:, 0])
        assert stated / mse > 0.9, noise
        if noise == 0.0:
            assert abs(stated / (q**2 / 12) - 1) < 0.01
        if noise >= 0.5:
            assert abs(stated / mse - 1) < 0.2, (noise, stated / mse)
    # no resolution known: the noise alone
    np.testing.assert_allclose(
        segment_noise_var_v2(np.full((2, 3), 5e-6), np.array([100, 400])), [[2.5e-13] * 3, [6.25e-14] * 3]
    )
