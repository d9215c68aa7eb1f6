"""Unit tests of diagnose's statistics on constructed inputs with known answers (pipeline/diagnose/fit.py, shift.py,
unexplained.py), apart from the end-to-end proofs of test_diagnose*.py.

One short simulated recording (2 Hz) gives the real structure the statistics work on: its static stretches,
positions, temperatures and blocks. The block values ``design.y`` are then replaced by the reference model plus a
planted term and noise of a known sigma, so every answer is known exactly: the coefficient and its standard
uncertainty (checked against an explicit least-squares solve of the same design matrix and over repeated noise
draws), the BIC decision on both sides of its threshold, the noise factor, the level and size of a constants
shift, the time of a step and the period of a periodic disturbance.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.diagnose.fit import Design, SelectionSettings, block_noise_factor, select_terms
from pipeline.diagnose.shift import find_shift, level_mask, levels, passport_sigma
from pipeline.diagnose.signal import make_blocks, segment_settings_for, static_record
from pipeline.diagnose.unexplained import best_period_s, best_step, time_basis
from pipeline.passport.document import SCHEMA_ID, Passport
from pipeline.segment import segment_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.thermal import PolynomialModel

SIGMA_V = 5e-7  # block sigma of the constructed data, V
PLANTED = "empirical:planted"


@pytest.fixture(scope="module")
def recording():
    res = simulate(SimConfig(program="short", rate_hz=2.0, seed=5))
    st = segment_settings_for(res.run)
    rec = static_record(res.run, segment_run(res.run, st), settings=st)
    return rec, make_blocks(rec)


def reference_model(order: int = 1) -> PolynomialModel:
    """A plain reference model (its values do not matter: the data are constructed on top of it)."""
    return PolynomialModel(
        np.diag([-0.55, -0.56, -0.54]), np.array([1e-3, -2e-3, 3e-3]), 20.0, order, np.zeros((order, 3)),
        np.zeros((order, 3, 3)),
    )  # fmt: skip


def design_of(recording, order: int = 1) -> Design:
    """A design on the recording's blocks with the reference model and a constant block sigma."""
    rec, blocks = recording
    return Design(rec, blocks, reference_model(order), np.full((blocks.size, 3), SIGMA_V))


def passport_with(uncertainty: dict) -> Passport:
    """A passport of the reference model stating the standard uncertainties ``uncertainty``."""
    ref = reference_model()
    return Passport(
        format=SCHEMA_ID, unit=None, method="tilt_six_position", version=None, normal_temp_c=ref.normal_temp_c,
        g_local_mps2=9.80665, K=ref.K0, U0=ref.U00, thermal_model=ref, uncertainty=uncertainty,
    )  # fmt: skip


def per_axis_time_columns(design: Design) -> np.ndarray:
    """(B, 3, 3): hours since the start on channel i for column i (a drift of each offset)."""
    t_h = design.blocks.t_s / 3600.0
    cols = np.zeros((design.blocks.size, 3, 3))
    for i in range(3):
        cols[:, i, i] = t_h
    return cols


def explicit_solution(design: Design, cols: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares written out: the block-diagonal base columns of the three channels and the term
    columns in one matrix, solved by numpy; (coefficients, their standard uncertainties)."""
    f = design.features(None)
    b, nb = f.shape
    p = cols.shape[2]
    x = np.zeros((3 * b, 3 * nb + p))
    for i in range(3):
        x[i::3, i * nb : (i + 1) * nb] = f
        x[i::3, 3 * nb :] = cols[:, i, :]
    xw = x / SIGMA_V
    yw = (y - design.reference(None)).reshape(-1) / SIGMA_V
    coef = np.linalg.lstsq(xw, yw, rcond=None)[0]
    return coef, np.sqrt(np.diag(np.linalg.inv(xw.T @ xw)))


# ------------------------------------------------------------------------------------------------- fit.py


def test_a_planted_linear_term_is_recovered_with_its_standard_uncertainty(recording):
    """The fit's coefficients and sigmas are those of the explicit least-squares solve (1e-6), and over 100
    noise draws the planted drift's z-scores scatter as a standard normal does."""
    d = design_of(recording)
    cols = per_axis_time_columns(d)
    d.extra[PLANTED] = ([f"r_{a}" for a in "xyz"], cols)
    truth = np.array([2e-6, -1e-6, 3e-6])  # V/h
    clean = d.reference(None) + np.einsum("bic,c->bi", cols, truth)
    rng = np.random.default_rng(7)
    d.y = clean + rng.normal(0.0, SIGMA_V, clean.shape)
    fr = d.fit(((PLANTED, None),))
    coef, sigma = explicit_solution(d, cols, d.y)
    assert fr.rank == coef.size  # every column determined on this program
    np.testing.assert_allclose(fr.coef, coef, rtol=1e-6, atol=1e-6 * np.abs(coef).max())
    np.testing.assert_allclose(fr.coef_sigma(), sigma, rtol=1e-6)
    sig = fr.coef_sigma()[fr.slices[PLANTED]]
    assert np.all(sig < 0.05 * np.abs(truth))  # the drifts are well determined: a test that can fail on its bias
    z = []
    for _ in range(100):
        d.y = clean + rng.normal(0.0, SIGMA_V, clean.shape)
        z.append((d.fit(((PLANTED, None),)).term_coef(PLANTED) - truth) / sig)
    z = np.concatenate(z)
    assert abs(z.mean()) < 0.2 and 0.85 < z.std() < 1.15
    assert 0.6 < np.mean(np.abs(z) < 1.0) < 0.76  # 68 % within 1 sigma (300 values: +-3 standard errors)


@pytest.mark.parametrize("side, accepted", [(-5.0, True), (+5.0, False)])
def test_the_bic_decision_on_both_sides_of_its_threshold(recording, side, accepted):
    """A drift of the x offset (catalogue ``time_drift``) planted without noise: without it the fit leaves
    chi2 = a^2 S, with it none, so dBIC = -a^2 S + 3 ln N exactly. Planted 5 below the threshold it is named,
    5 above it is not."""
    d = design_of(recording)
    _, cols = d.term_columns("time_drift", None)
    unit = cols[:, :, 0]  # r_x = 1 V/h
    d.y = d.reference(None) + unit
    s = d.fit(()).chi2  # S: the part of the column the base model cannot take, weighted
    ln_n = np.log(d.n_values)
    threshold = 20.0
    a = np.sqrt((threshold - side + 3 * ln_n) / s)  # dBIC = -threshold + side
    d.y = d.reference(None) + a * unit
    sel = select_terms(d, ["time_drift"], SelectionSettings(threshold=threshold))
    (trial,) = sel.rounds[0]
    assert trial["delta_bic"] == pytest.approx(-threshold + side, abs=0.1)
    assert [t.effect for t in sel.accepted] == (["time_drift"] if accepted else [])
    if accepted:
        np.testing.assert_allclose(sel.accepted[0].params["r_v_per_h"], [a, 0.0, 0.0], atol=1e-6 * a)


@pytest.mark.parametrize("scale", [1.0, 2.0])
def test_block_noise_factor_measures_the_scatter_against_the_stated_sigma(recording, scale):
    """Residuals scattering ``scale`` times the stated block sigma: the factor is ``scale`` (at least 1)."""
    d = design_of(recording)
    d.y = d.reference(None) + np.random.default_rng(11).normal(0.0, scale * SIGMA_V, (d.blocks.size, 3))
    factor = block_noise_factor(d, d.fit(()))
    assert factor.shape == (3,)
    np.testing.assert_allclose(factor, scale, rtol=0.15)
    assert np.all(factor >= 1.0)


# ------------------------------------------------------------------------------------------------- shift.py


def test_levels_and_masks_of_a_constants_shift():
    """Order 1: U0 and K-and-U0 drifting alone, then at one time U0, K and U0, and the thermal model, each with
    the drifts on top that move no more than moved at the start; a level's mask frees exactly its columns."""
    lv = levels(1)
    assert [(x.name, x.powers, x.drift) for x in lv] == [
        ("U0", 0, "U0"),
        ("K and U0", 0, "K and U0"),
        ("U0", 1, ""),
        ("U0", 1, "U0"),
        ("K and U0", 1, ""),
        ("K and U0", 1, "U0"),
        ("K and U0", 1, "K and U0"),
        ("K, U0 and their thermal model", 2, ""),
        ("K, U0 and their thermal model", 2, "U0"),
        ("K, U0 and their thermal model", 2, "K and U0"),
    ]
    assert level_mask(lv[2], 1).reshape(2, 4).tolist() == [[False, False, False, True], [False] * 4]
    assert level_mask(lv[4], 1).reshape(2, 4).tolist() == [[True] * 4, [False] * 4]
    assert level_mask(lv[7], 1).all()
    k, u = passport_sigma(
        passport_with({"coefficients": {"K": np.full((3, 3), 2e-6).tolist(), "U0": [1e-6, None, 3e-6]}})
    )
    assert np.all(k == 2e-6) and u[0] == 1e-6 and u[2] == 3e-6 and np.isfinite(u[1])  # a null keeps the default


PASSPORT = passport_with({"coefficients": {"K": np.full((3, 3), 1e-6).tolist(), "U0": [1e-6] * 3}})


@pytest.mark.parametrize("shift_v, named", [(4e-5, True), (0.0, False)])
def test_a_constants_shift_is_found_at_its_level_and_size(recording, shift_v, named):
    """An offset of the y channel moved by 40 micro-V (80 block sigmas) since the passport: the level is "U0" at
    one time, its size is found to its uncertainty; with nothing moved, no shift is named."""
    d = design_of(recording)
    d.set_base_mask(np.zeros_like(d.base_mask))  # the passport as it is
    rng = np.random.default_rng(3)
    d.y = d.reference(None) + np.array([0.0, shift_v, 0.0]) + rng.normal(0.0, SIGMA_V, (d.blocks.size, 3))
    res = find_shift(d, PASSPORT, threshold=20.0)
    if not named:
        assert res.level is None or not res.significant
        return
    assert res.significant and res.level is not None
    assert (res.level.name, res.level.powers, res.level.drift) == ("U0", 1, "")
    d_u0 = res.fit.base_coef[:, 0, 3]  # the change of U0 at T0 per channel, V
    sig = res.fit.coef_sigma()[[i * res.fit.base_coef[0].size + 3 for i in range(3)]]
    assert abs(d_u0[1] - shift_v) < 4 * sig[1] and np.all(np.abs(d_u0[[0, 2]]) < 4 * sig[[0, 2]])
    assert res.largest_z > 3.0


# ------------------------------------------------------------------------------------------------- unexplained.py


def test_a_step_is_found_at_its_time_with_its_size():
    """A step of (3, -2, 0) micro-V at t = 4000 s in noise of 0.5 micro-V: its time within one sample spacing, its
    size within 4 standard errors, and the share of the variance it explains as the step's variance says (0.81)."""
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0.0, 10_000.0, 400))
    size = np.array([3e-6, -2e-6, 0.0])
    r = np.where(t[:, None] > 4000.0, size, 0.0) + rng.normal(0.0, 5e-7, (t.size, 3))
    w = np.full((t.size, 3), 1.0 / 5e-7**2)
    t_step, found, share = best_step(t, r, w)
    spacing = np.max(np.diff(t))
    assert abs(t_step - 4000.0) < spacing
    se = 5e-7 * np.sqrt(1 / np.sum(t > 4000) + 1 / np.sum(t <= 4000))
    assert np.all(np.abs(found - size) < 4 * se)
    # the share of the weighted variance it explains: the step's variance p (1 - p) size^2 against it plus the noise
    p = np.mean(t > 4000.0)
    step_var = p * (1 - p) * np.sum(size**2)
    assert share == pytest.approx(step_var / (step_var + 3 * (5e-7) ** 2), abs=0.03)
    # with nothing in it, the best "step" explains only noise
    assert best_step(t, rng.normal(0.0, 5e-7, (t.size, 3)), w)[2] < 0.1


@pytest.mark.parametrize("period_s", [600.0, 1800.0])
def test_a_periodic_disturbance_is_found_at_its_period(period_s):
    """A sinusoid of the given period on one axis, 20 h of irregular samples: the periodogram's peak within
    0.5 % of it; a record too short for three of the shortest periods gives none."""
    rng = np.random.default_rng(9)
    t = np.sort(rng.uniform(0.0, 20 * 3600.0, 3000))
    r = np.zeros((t.size, 3))
    r[:, 2] = 2e-6 * np.sin(2 * np.pi * t / period_s + 0.3) + rng.normal(0.0, 5e-7, t.size)
    r[:, :2] = rng.normal(0.0, 5e-7, (t.size, 2))
    w = np.ones_like(r)
    assert best_period_s(t, r, w) == pytest.approx(period_s, rel=5e-3)
    assert best_period_s(t[t < 300.0], r[t < 300.0], w[t < 300.0]) is None


def test_time_basis_interpolates_piecewise_linear_functions_exactly():
    """The hat functions sum to one everywhere and reproduce a piecewise-linear function through the knots."""
    t = np.linspace(0.0, 7200.0, 500)
    basis = time_basis(t, knot_s=1800.0)
    assert basis.shape == (500, 5)
    np.testing.assert_allclose(basis.sum(axis=1), 1.0)
    knots_values = np.array([0.0, 2.0, -1.0, 3.0, 0.5])
    f = np.interp(t, np.linspace(0.0, 7200.0, 5), knots_values)
    np.testing.assert_allclose(basis @ knots_values, f, atol=1e-12)
