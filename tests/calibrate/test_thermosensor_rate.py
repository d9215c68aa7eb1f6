"""The thermosensor's noise in each hold's temperature is in the tilt sigmas (:func:`pipeline.segment.
interpolated_mean_weight2`, :attr:`pipeline.segment.StaticSegment.temp_sigma_c`, ``tilt._temperature_noise_v``).

Each hold's mean output is referred to its plateau's mean temperature through the model's slope (about 1e-4 V/C of
U0), so the noise of the hold's mean temperature enters the hold: 0.01 C over the 50 readings of a 1-Hz thermosensor
is 0.0014 C (0.14 micro-V), over the one or two readings of one read once a minute up to 0.01 C (1 micro-V, beyond
the 0.22 micro-V of a 60-s hold's mean at 10 Hz). Before, that term was not in the sigmas (only the pooled excess
scatter of the fits caught some of it): thinning the thermosensor to once a minute moved K at T0 by 2-3 of the
1-Hz run's sigmas."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from pipeline.calibrate.tilt import calibrate
from pipeline.segment import interpolated_mean_weight2, segment_run, thermosensor_noise_c
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import UnitTruth


def _thinned(run, every_s: float):
    """``run`` with its thermosensor read every ``every_s`` seconds (the readings on that grid kept)."""
    th = run.au_temperature
    t = th["t_ns"].to_numpy()
    keep = ((t - t[0]) % int(every_s * 1e9)) < int(0.5e9)
    return dataclasses.replace(run, au_temperature=th.filter(pl.Series(keep)))


def test_weights_of_an_interpolated_mean():
    xp = np.arange(0.0, 11.0)  # readings at 0..10 s
    # every point halfway between readings 3 and 4: weights 1/2, 1/2
    assert interpolated_mean_weight2(xp, np.full(7, 3.5)) == pytest.approx(0.5, abs=1e-15)
    # on reading 5 itself: one reading
    assert interpolated_mean_weight2(xp, np.full(4, 5.0)) == pytest.approx(1.0, abs=1e-15)
    # one point on each of the readings 0..10: 1/11
    assert interpolated_mean_weight2(xp, xp.copy()) == pytest.approx(1 / 11, abs=1e-15)
    # before the first reading the first one is held
    assert interpolated_mean_weight2(xp, np.array([-5.0, -1.0])) == pytest.approx(1.0, abs=1e-15)
    # any points: the brute force through np.interp's linearity
    rng = np.random.default_rng(1)
    x = np.sort(rng.uniform(2.2, 6.9, 500))
    w = np.array([np.interp(x, xp, e).mean() for e in np.eye(xp.size)])
    assert interpolated_mean_weight2(xp, x) == pytest.approx(float(w @ w), rel=1e-12)


@pytest.mark.parametrize("rate_hz, every_s", [(100.0, 1.0), (100.0, 60.0), (1000.0, 1.0), (10.0, 7.0)])
def test_weights_of_an_interpolated_mean_in_closed_form(rate_hz, every_s):
    """:func:`interpolated_mean_weight2` on a hold's samples (jittered, whole ns, as float64 like the segmentation's)
    and thermosensor readings (from before the hold to after it): the sum of squared weights as exact fractions give
    it (to 2 ulp), taking no memory beyond one copy of the points' times plus 1/8 (it took 5 copies and more,
    per-point interval indices and fractions: 0.48 s of segment_run's 1.61 s on one unit of a 100-Hz run)."""
    import bisect
    import tracemalloc
    from fractions import Fraction

    rng = np.random.default_rng(int(rate_hz + every_s))
    n = int(rate_hz * 20.0)
    t0_ns = 1_764_000_000_000_000_000
    x_ns = t0_ns + np.sort(((np.arange(n) + rng.uniform(-0.3, 0.3, n)) * (1e9 / rate_hz)).astype(np.int64))
    xp_ns = t0_ns + int(rng.integers(0, 10**6)) + (np.arange(-1, 20.0 / every_s + 2) * every_s * 1e9).astype(np.int64)
    x, xp = x_ns.astype(np.float64), xp_ns.astype(np.float64)
    readings = [int(v) for v in xp]
    w = [Fraction(0)] * len(readings)
    for v in (int(t) for t in x):
        j = min(max(bisect.bisect_right(readings, v) - 1, 0), len(readings) - 2)
        lam = min(max(Fraction(v - readings[j], readings[j + 1] - readings[j]), Fraction(0)), Fraction(1))
        w[j] += 1 - lam
        w[j + 1] += lam
    exact = float(sum(a * a for a in w) / (n * n))
    assert interpolated_mean_weight2(xp, x) == pytest.approx(exact, rel=4.5e-16, abs=0.0)
    tracemalloc.start()
    try:
        interpolated_mean_weight2(xp, x)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= 1.25 * x.nbytes + 20_000, (peak, x.nbytes)


def test_thermosensor_noise_through_a_ramp():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 3600.0)
    temp = 20.0 + 0.02 * t + 1e-6 * t**2 + rng.normal(0.0, 0.01, t.size)
    assert thermosensor_noise_c(temp) == pytest.approx(0.01, rel=0.05)
    assert thermosensor_noise_c(temp[:9]) == 0.0


@pytest.mark.parametrize("every_s", [1.0, 60.0])
def test_each_holds_temperature_carries_its_standard_error(every_s):
    run = _thinned(simulate(SimConfig(program="short", seed=5)).run, every_s)
    seg = segment_run(run)
    tt, temp = run.thermosensor()
    spans = [
        (int(np.searchsorted(tt, p.t_start_ns)), int(np.searchsorted(tt, p.t_end_ns, "right"))) for p in seg.plateaus
    ]
    noise_c = thermosensor_noise_c(temp, spans)
    # the simulator's 0.01 C at either rate, from the plateaus (all the readings: 0.022 C once a minute, the ramps'
    # curvature)
    assert noise_c == pytest.approx(0.01, rel=0.15)
    t_ns = run.t_ns()
    xp = tt.astype(np.float64)
    on = [s for s in seg.segments if s.plateau is not None and s.position is not None]
    assert len(on) >= 30
    for s in on:
        x = t_ns[(t_ns >= s.t_start_ns) & (t_ns <= s.t_end_ns)].astype(np.float64)
        near = np.flatnonzero((xp >= x[0] - 2 * every_s * 1e9) & (xp <= x[-1] + 2 * every_s * 1e9))
        w = np.array([np.interp(x, xp[near], e).mean() for e in np.eye(near.size)])
        assert s.temp_sigma_c == pytest.approx(noise_c * np.sqrt(float(w @ w)), rel=1e-9)
    sig = np.median([s.temp_sigma_c for s in on])
    if every_s == 1.0:
        assert 0.001 < sig < 0.002  # 0.01 C / sqrt(~50 readings)
    else:
        assert 0.005 < sig < 0.01  # the one or two readings of a minute


@pytest.mark.slow  # 4 seeds x 4 thermosensor rates of the short program, about 1 s each
def test_constants_within_3_sigma_across_thermosensor_rates():
    """K and U0 at T0 within 3 stated sigmas of the truth for the thermosensor read every 1, 10, 30, 60 s, and the
    sigmas grow as it is read less often."""
    sig: dict[float, list[float]] = {1.0: [], 10.0: [], 30.0: [], 60.0: []}
    for seed in (1, 2, 3, 4):
        sim = simulate(SimConfig(program="short", seed=seed))
        for every_s in sig:
            doc = calibrate([_thinned(sim.run, every_s)]).passport
            K_t, U0_t = UnitTruth.from_dict(sim.truth["unit"]).constants_at(np.array([doc["normal_temp_c"]]))
            sK = np.array(doc["uncertainty"]["coefficients"]["K"], dtype=float)
            sU = np.array(doc["uncertainty"]["coefficients"]["U0"], dtype=float)
            zK = np.abs(np.array(doc["coefficients"]["K"]) - K_t[0]) / sK
            zU = np.abs(np.array(doc["coefficients"]["U0"]) - U0_t[0]) / sU
            assert zK.max() <= 3.0 and zU.max() <= 3.0, (seed, every_s, zK.max(), zU.max())
            sig[every_s].append(float(np.median(sK)))
    assert np.median(sig[60.0]) > 1.5 * np.median(sig[1.0])
