"""Standard uncertainties of the differential (seed 003) and scalar (seed 004) methods tested for coverage against the
simulator's truth over many noise seeds, as tests/test_uncertainty.py does for the tilt method: the chamber differential
(a base passport, six orientations with 1.5 degree face errors, one temperature cycle) and the sweep differential (no
base, three orientations, the temperature drifting 5 -> 25 C; its offsets at T0 from the orientations too). About 68 %
of the errors within 1 sigma and 95 % within 2 sigma, and the sigmas not absurdly wide (their median within a small
factor of the scatter of the estimates between seeds); terms the orientations cannot determine have no uncertainty and
the passport says why; ``passport diff`` of two differential passports marks a real change of a temperature coefficient
and not the noise. The scalar method's constants likewise, with its gauge-fixed entries named; and the tilt method's
referral of each position to its plateau's temperature is in its sigmas.

Tolerances: the z-scores of one run's coefficients are correlated (the orders of one constant's polynomial share the
same data), so a few hundred z-scores count as about a third as many independent ones; the binomial standard
deviation of a within-1-sigma fraction over ~150 independent values is 0.04, of a within-2-sigma fraction 0.017. The
bounds are about 2 of these standard deviations around 0.68 and 0.95."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from pipeline.calibrate import differential, scalar, tilt
from pipeline.calibrate.observations import plateau_groups
from pipeline.calibrate.tilt import fit_unit, observe_run
from pipeline.passport.document import build_passport
from pipeline.passport.registry import Registry
from pipeline.passport.significance import significant_changes
from pipeline.passport.text import diff_lines
from pipeline.simulate import chamber, program
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import UnitTruth, seed000_unit
from tests.calibrate.test_short_soaks_and_missing_positions import program as soak_program

pytestmark = pytest.mark.slow  # many simulated runs (coverage over noise seeds)

N_CHAMBER = 16  # chamber cycles at 1 Hz, about 1 s each to simulate and calibrate
N_SWEEP = 16  # sweeps at 0.5 Hz, about 0.6 s each
N_SCALAR = 24  # short programs at 1 Hz, about 0.12 s each
GROUPS = ("alpha", "beta", "gamma")


def _within(z: np.ndarray) -> tuple[float, float, float]:
    z = np.abs(np.asarray(z, dtype=float))
    return float(np.mean(z < 1.0)), float(np.mean(z < 2.0)), float(np.median(z))


@pytest.fixture(scope="module")
def base() -> dict:
    """The normal-temperature passport the chamber differential starts from (tilt, short program, 1 Hz)."""
    run = simulate(SimConfig(program="short", seed=8, rate_hz=1.0)).run
    obs, _ = observe_run(run)
    return build_passport(fit_unit("AU-0001", obs), [], "unverified", g_local_mps2=9.80665, plateaus=[])


def _cycle(seed: int, orientations=("TP1", "TP2", "TP3", "TP4", "TP5", "TP6"), rate_hz: float = 1.0):
    name = "coverage_cycle_" + "_".join(orientations)
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(program.PROGRAMS, name, lambda: program.differential_program(orientations))
        return simulate(
            SimConfig(
                program=name,
                seed=100 + seed,
                rate_hz=rate_hz,
                effects=[("fixture_face_error", {"sigma_deg": 1.5, "seed": 200 + seed})],
            )
        )


@pytest.fixture(scope="module")
def chamber_runs(base) -> list[dict]:
    """Differential passports of the seed 000 unit (quadratic in T; the fit is cubic with two rate terms), one per
    noise and face-error seed. The simulated element follows the thermosensor: the true rate terms are 0."""
    return [differential.calibrate([_cycle(s).run], base_passport=base).passport for s in range(N_CHAMBER)]


def _thermal_errors(doc: dict, truth: dict) -> tuple[list[float], list[float], list[str]]:
    """(estimate - truth) and sigma of every thermal coefficient with an uncertainty, and their names."""
    tm, sig = doc["thermal_model"], doc["uncertainty"]["thermal_model"]
    err, sd, names = [], [], []
    for group in GROUPS:
        for key, values in tm[group].items():
            for n, v in enumerate(values):
                if sig[group][key][n] is None:
                    continue
                want = truth[group][key]
                err.append(v - (want[n] if n < len(want) else 0.0))
                sd.append(sig[group][key][n])
                names.append(f"{group}.{key}[{n + 1}]")
    return err, sd, names


def test_chamber_differential_thermal_coefficients_cover_the_truth(chamber_runs):
    """Every alpha, beta and gamma coefficient (36 per run) against seed 000's unit: coverage and width."""
    truth = seed000_unit().relative_coefficients()
    per_run = [_thermal_errors(doc, truth) for doc in chamber_runs]
    assert all(len(e) == 36 for e, _, _ in per_run)  # six orientations determine every term
    err = np.array([e for e, _, _ in per_run])
    sd = np.array([s for _, s, _ in per_run])
    within1, within2, median = _within(err / sd)
    assert 0.60 <= within1 <= 0.78, within1
    assert 0.92 <= within2 <= 0.99, within2
    assert 0.5 <= median <= 0.85, median
    # not absurdly wide: per coefficient, the median sigma against the scatter of the estimates between seeds
    ratio = np.median(sd, axis=0) / err.std(axis=0, ddof=1)
    assert np.all((0.5 < ratio) & (ratio < 2.0)), dict(zip(per_run[0][2], ratio.round(2)))
    assert 0.8 < np.median(ratio) < 1.4, np.median(ratio)


def test_chamber_differential_rate_terms_cover_zero(chamber_runs):
    """The rate terms (selected by default: two orders, bias and scale) have true value 0 here; their sigmas
    cover it."""
    z = []
    for doc in chamber_runs:
        rt, rs = doc["rate_terms"], doc["uncertainty"]["rate_terms"]
        for group in ("alpha_rate", "beta_rate"):
            for key in rt[group]:
                z += list((np.array(rt[group][key]) / np.array(rs[group][key], dtype=float)).ravel())
    assert len(z) == 12 * N_CHAMBER
    within1, within2, median = _within(z)
    assert 0.55 <= within1 <= 0.80 and 0.90 <= within2 <= 1.0 and 0.45 <= median <= 0.9, (within1, within2, median)


def test_chamber_passport_constants_take_the_base_uncertainty(chamber_runs, base):
    """K and U0 at T0 are the base passport's, and so are their uncertainties; the lag was not fitted, and the
    passport says so rather than leaving a silent null."""
    u = chamber_runs[0]["uncertainty"]
    assert u["coefficients"] == base["uncertainty"]["coefficients"]
    assert u["rate_terms"]["lag_tau_s"] is None and "rate_terms.lag_tau_s" in u["undetermined"]
    assert set(u["undetermined"]) == {"rate_terms.lag_tau_s"}
    assert u["basis"]["cluster_s"] == differential.CLUSTER_S and u["basis"]["n_pairs"] > 1000


def test_terms_the_orientations_do_not_excite_have_no_uncertainty(base):
    """With the unit held only x down and x up (TP5, TP6), the y and z scale-factor terms and the cross-axis terms
    are not determined: their uncertainty is null and ``undetermined`` names each with its reason; what is fitted
    has a positive sigma."""
    doc = differential.calibrate([_cycle(0, ("TP5", "TP6"), rate_hz=0.5).run], base_passport=base).passport
    u = doc["uncertainty"]
    sig = u["thermal_model"]
    for key in ("yy", "zz"):
        assert sig["beta"][key] == [None] * 3
        assert "no orientation had gravity along" in u["undetermined"][f"beta.{key}"]
        assert u["rate_terms"]["beta_rate"][key] == [[None], [None]]
    assert all(v > 0 for v in sig["beta"]["xx"]) and all(v > 0 for ax in "xyz" for v in sig["alpha"][ax])
    for key, values in sig["gamma"].items():  # K_yx a_x and K_zx a_x are excited; the rest are not
        if key in ("yx", "zx"):
            assert all(v > 0 for v in values) and f"gamma.{key}" not in u["undetermined"]
        else:
            assert values == [None] * 3 and "do not excite" in u["undetermined"][f"gamma.{key}"]


# ---------------------------------------------------------------------------------------------------------------
# The sweep differential (no base passport)


def _identifiable_unit() -> UnitTruth:
    """Seed 000's unit with its cross-axis sensitivities set to 0: three orientations cannot separate an offset
    from the cross-axis constants, nor a cross-axis temperature term they do not excite from the bias (basis
    ``identification``), so coverage is tested on a unit whose temperature dependence the sweep's model holds."""
    u = seed000_unit()
    k = u.k_coef.copy()
    k[:, ~np.eye(3, dtype=bool)] = 0.0
    return UnitTruth(u.normal_temp_c, k, u.u0_coef, "seed000-diagonal")


@pytest.fixture(scope="module")
def sweep_runs() -> list[dict]:
    """Sweep passports (quadratic model, no rate terms, cross-axis terms the orientations excite), one per seed."""
    settings = dataclasses.replace(differential.SWEEP_SETTINGS, select_model=False, poly_order=2, rate_order=0)
    unit = _identifiable_unit()
    with pytest.MonkeyPatch.context() as mp, np.errstate(invalid="ignore"):  # the truth's gamma: 0 / 0
        mp.setattr(chamber, "unit_for", lambda config: unit)
        runs = [
            simulate(SimConfig(program="sweep", seed=300 + s, rate_hz=0.5, with_fixture_log=False)).run
            for s in range(N_SWEEP)
        ]
    return [differential.calibrate([r], differential=settings).passport for r in runs]


def test_sweep_differential_thermal_coefficients_cover_the_truth(sweep_runs):
    """alpha and beta of every axis, and the absolute cross-axis terms (true value 0), against the truth."""
    with np.errstate(invalid="ignore"):  # gamma = 0 / 0 for the zeroed cross-axis terms: not used
        truth = _identifiable_unit().relative_coefficients()
    err, sd = [], []
    for doc in sweep_runs:
        e, s, names = _thermal_errors(doc, truth)
        assert len(e) == 12 and not any(n.startswith("gamma") for n in names)
        cross, cross_sd = doc["rate_terms"]["cross_axis_abs"], doc["uncertainty"]["rate_terms"]["cross_axis_abs"]
        for key, values in cross.items():
            for v, sv in zip(values, cross_sd[key]):
                if sv is not None:
                    e.append(v)
                    s.append(sv)
        assert len(e) == 18  # three cross-axis terms of order 2 excited
        err.append(e)
        sd.append(s)
    err, sd = np.array(err), np.array(sd)
    within1, within2, median = _within(err / sd)
    assert 0.60 <= within1 <= 0.82, within1
    assert 0.92 <= within2 <= 1.0, within2
    assert 0.5 <= median <= 0.85, median
    ratio = np.median(sd, axis=0) / err.std(axis=0, ddof=1)
    assert 0.8 < np.median(ratio) < 1.5, ratio


def test_sweep_offsets_at_t0_cover_the_truth(sweep_runs):
    """Without a base passport the offsets at T0 come from the windows where the axis is horizontal (two per axis
    here), brought to T0 with the model: their sigma (spread between the windows, the model's covariance at the
    windows' temperatures, the noise of the window means) covers the truth. 48 values: tolerances of +-2.5
    binomial standard deviations (0.067 at 68 %). The gains, each given by one vertical window here, have no
    uncertainty and say why."""
    truth = _identifiable_unit().u0_coef[0]
    z = []
    for doc in sweep_runs:
        sig = doc["uncertainty"]["coefficients"]
        z += [(doc["coefficients"]["U0"][i] - truth[i]) / sig["U0"][i] for i in range(3)]
        assert all(sig["K"][i][i] is None for i in range(3))
        assert all("one orientation alone gives it" in doc["uncertainty"]["undetermined"][f"K.{a * 2}"] for a in "xyz")
    within1, within2, median = _within(z)
    assert 0.5 <= within1 <= 0.85 and within2 >= 0.85 and 0.4 <= median <= 1.0, (within1, within2, median)


def test_sweep_passport_names_what_it_cannot_determine(sweep_runs):
    """No base passport: the cross-axis constants are undetermined (null, with the reason), the relative gamma is
    replaced by the absolute cross-axis terms, unexcited ones are named, and the basis states that the numbers are
    statistical uncertainties of the model the orientations identify."""
    u = sweep_runs[0]["uncertainty"]
    for key in ("xy", "xz", "yx", "yz", "zx", "zy"):
        i, j = "xyz".index(key[0]), "xyz".index(key[1])
        assert u["coefficients"]["K"][i][j] is None
        assert "not determined by the orientations" in u["undetermined"][f"K.{key}"]
        assert f"gamma.{key}" in u["undetermined"]
    assert sum(k.startswith("rate_terms.cross_axis_abs.") for k in u["undetermined"]) == 3
    assert "identification" in u["basis"]
    # every null in the document has a reason
    K = u["coefficients"]["K"]
    nulls = [f"K.{a}{b}" for i, a in enumerate("xyz") for j, b in enumerate("xyz") if K[i][j] is None]
    nulls += [f"U0.{a}" for k, a in enumerate("xyz") if u["coefficients"]["U0"][k] is None]
    assert set(nulls) <= set(u["undetermined"])


# ---------------------------------------------------------------------------------------------------------------
# passport diff of two differential passports


def test_diff_of_differential_passports_marks_real_changes(chamber_runs, tmp_path):
    """Two calibrations from other noise and face-error seeds differ by noise: few of their 36 thermal coefficients
    and 12 rate terms are marked significant; a third version with alpha.x[1] moved by 0.05 micro-g/C (about 10 of
    its sigmas), beta.yy[1] by 1 ppm/C and the first bias rate term of z by 10 sigmas is marked there, in
    micro-g/C, ppm/C and micro-g/(C/min), and nothing else is; the readable diff says so."""
    reg = Registry(tmp_path / "reg")
    a, b = chamber_runs[1], chamber_runs[2]
    shifted = copy.deepcopy(b)
    gain_x = abs(shifted["coefficients"]["K"][0][0])
    shifted["thermal_model"]["alpha"]["x"][0] += 0.05e-6 * gain_x
    shifted["thermal_model"]["beta"]["yy"][0] += 1e-6
    rate_sigma = shifted["uncertainty"]["rate_terms"]["alpha_rate"]["z"][0][0]
    shifted["rate_terms"]["alpha_rate"]["z"][0][0] += 10 * rate_sigma
    for n, doc in enumerate((a, b, shifted)):
        reg.publish(doc, inputs=[{"path": f"cycle{n}.mcap", "sha256": f"{n:064x}"}], settings={}, code_version="t")
    noise = reg.diff("AU-0001", 1, 2)
    entries = noise["thermal_model"]
    assert len(entries) == 36 and all(e["significant"] is not None for e in entries)
    assert sum(e["significant"] for e in entries) <= 4
    rate = noise["rate_terms"]
    assert len(rate) == 12 and all(e["significant"] is not None for e in rate)
    assert sum(e["significant"] for e in rate) <= 2
    d = reg.diff("AU-0001", 2, 3)
    by_name = {e["name"]: e for e in d["thermal_model"] + d["rate_terms"]}
    assert set(by_name) == {"alpha.x[1]", "beta.yy[1]", "rate_terms.alpha_rate.z[1][0]"}
    assert {e["name"] for e in significant_changes(d)} == set(by_name)
    assert by_name["rate_terms.alpha_rate.z[1][0]"]["scaled_unit"] == "micro-g/(C/min)^1/C^0"
    text = "\n".join(diff_lines(d))
    assert "rate terms: 1 of 1 changes beyond 2 combined standard uncertainties" in text
    assert "thermal model coefficients: 2 of 2" in text
    assert by_name["alpha.x[1]"]["scaled_unit"] == "micro-g/C^1"
    assert by_name["alpha.x[1]"]["delta_scaled"] == pytest.approx(0.05, rel=1e-6)
    assert by_name["beta.yy[1]"]["delta_scaled"] == pytest.approx(1.0, rel=1e-6)
    assert by_name["alpha.x[1]"]["delta"] / by_name["alpha.x[1]"]["uncertainty"] > 5


# ---------------------------------------------------------------------------------------------------------------
# The tilt method: referring each position to its plateau's temperature


def test_referral_to_the_plateau_temperature_is_in_the_sigma_and_small(monkeypatch):
    """20-min soaks: the unit still settles, each position is referred to its plateau's mean temperature across
    about 1 C through the local model's slope. The slope's uncertainty, propagated to every segment
    (tilt._referral_errors), is in the stored per-plateau sigmas: they grow, but by less than 1 % (the referral
    error is ~0.005 micro-V against ~0.3 micro-V of a segment mean's noise), and the sigmas still cover the
    truth."""
    run = simulate(SimConfig(seed=603, rate_hz=1.0, program=soak_program(1200.0, 1200.0))).run
    obs, _ = observe_run(run)
    spread = [max(o.temp_c for o in rows) - min(o.temp_c for o in rows) for rows in plateau_groups(obs).values()]
    assert max(spread) > 0.8, spread
    with_ref = fit_unit("AU-0001", obs)
    monkeypatch.setattr(tilt, "_referral_errors", lambda *args: {})
    without = fit_unit("AU-0001", obs)
    s1 = np.concatenate([np.r_[p.K_sigma.ravel(), p.U0_sigma] for p in with_ref.per_plateau])
    s0 = np.concatenate([np.r_[p.K_sigma.ravel(), p.U0_sigma] for p in without.per_plateau])
    assert np.all(s1 >= s0) and np.any(s1 > s0 * (1 + 1e-7)), "the referral error is not included"
    assert np.max(s1 / s0) < 1.01
    truth = seed000_unit()
    z = []
    for p in with_ref.per_plateau:
        K, U0 = truth.constants_at(p.temp_c)
        z += list(((p.K - K[0]) / p.K_sigma).ravel()) + list((p.U0 - U0[0]) / p.U0_sigma)
    assert np.mean(np.abs(z) < 2) >= 0.9


# ---------------------------------------------------------------------------------------------------------------
# The scalar method


def test_scalar_constants_cover_the_truth_and_name_the_gauge():
    """K (lower-triangular gauge) and U0 of the scalar method (all static segments at +20 C of the short program,
    orientation-free) against the truth in that gauge: coverage and width per entry; the three upper entries of K
    are 0 by the rotation gauge, their uncertainty 0 and named in ``fixed_by_convention``; nothing is null."""
    err, sd = [], []
    for seed in range(N_SCALAR):
        cal = scalar.calibrate([simulate(SimConfig(seed=300 + seed, program="short", rate_hz=1.0)).run])
        p = cal.fit.per_plateau[0]
        K, U0 = seed000_unit().constants_at(p.temp_c)
        ok = p.K_sigma > 0
        assert ok.sum() == 6 and np.all(p.K_sigma[~ok] == 0) and np.all(p.K[~ok] == 0.0)
        err.append(np.r_[(p.K - scalar.lower_gauge(K[0]))[ok], p.U0 - U0[0]])
        sd.append(np.r_[p.K_sigma[ok], p.U0_sigma])
        unc = cal.passport["uncertainty"]
        assert sorted(unc["fixed_by_convention"]) == ["K.xy", "K.xz", "K.yz"]
        assert "gauge" in unc["fixed_by_convention"]["K.xy"] and unc["undetermined"] == {}
        assert unc["coefficients"]["K"][0][1] == 0.0
        assert all(v is not None for row in unc["coefficients"]["K"] for v in row)
    err, sd = np.array(err), np.array(sd)
    within1, within2, median = _within(err / sd)
    assert 0.58 <= within1 <= 0.80 and 0.90 <= within2 <= 1.0 and 0.5 <= median <= 0.85, (within1, within2, median)
    # not absurdly wide: median sigma against the rms error over the seeds, per entry (24 seeds: +-15 %)
    ratio = np.median(sd, axis=0) / np.sqrt(np.mean(err**2, axis=0))
    assert np.all((0.5 < ratio) & (ratio < 2.0)), ratio


# ---------------------------------------------------------------------------------------------------------------
# What people read: passport show, the certificate, the CSV export


def test_show_report_and_csv_print_the_differential_and_scalar_uncertainties(chamber_runs, sweep_runs):
    """``passport show`` and the certificate print the differential method's constants and temperature
    coefficients with their uncertainty, mark what has none (with the reason) and the scalar method's gauge-fixed
    entries as fixed by convention; the CSV export carries the same sigmas, and the PX4 export is unchanged by
    them."""
    from pipeline.passport.export import export_csv, export_px4
    from pipeline.passport.report import certificate_html
    from pipeline.passport.text import passport_summary

    chamber_doc, sweep_doc = chamber_runs[0], sweep_runs[0]
    text = passport_summary(chamber_doc)
    assert text.count("ppm") >= 9 and text.count(" ug") >= 3 and "(undetermined)" not in text
    html = certificate_html(chamber_doc)
    assert html.count("&plusmn;") >= 12 + 36  # constants and every alpha, beta, gamma coefficient
    sweep_text = passport_summary(sweep_doc)
    assert "(undetermined)" in sweep_text and "no uncertainty: K.xy, K.xz, K.yx, K.yz, K.zx, K.zy" in sweep_text
    scalar_doc = scalar.calibrate([simulate(SimConfig(seed=3, program="short", rate_hz=1.0)).run]).passport
    assert "fixed by convention: K.xy, K.xz, K.yz" in passport_summary(scalar_doc)
    assert certificate_html(scalar_doc).count("(by convention)") == 3
    rows = [r.split(",") for r in export_csv(chamber_doc).text.splitlines()]
    alpha = [r for r in rows if r[0] == "alpha"]
    assert len(alpha) == 9 and all(float(r[-1]) > 0 for r in alpha)
    stripped = copy.deepcopy(chamber_doc)
    stripped["uncertainty"] = None
    assert export_px4(stripped).text == export_px4(chamber_doc).text
