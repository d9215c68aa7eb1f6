"""diagnose reads the voltmeter a slab at a time: the reduction is the straightforward one, whatever the slab size,
the table's chunks or the NaN samples, and the findings do not depend on the voltmeter rate.

The reference below is the whole-record computation (every static sample's index, time, stretch and temperature as
arrays, one ``np.add.reduceat`` per quantity, ``np.median`` of all the first differences) that
:func:`pipeline.diagnose.signal.static_record` replaces with slab-wise sums and exact order statistics.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from pipeline.diagnose import signal as diagnose_signal
from pipeline.diagnose.diagnosis import diagnose_run
from pipeline.diagnose.signal import exact_medians, segment_settings_for, static_record
from pipeline.run import Run
from pipeline.segment import SegmentSettings, for_rate, segment_run
from pipeline.simulate.chamber import SimConfig, simulate

NS = 1_000_000_000


def reference_record(run: Run, rec, micro_s: float = 1.0):
    """Micro-sample count, time, outputs, temperature and the per-sample noise of ``rec``'s stretches, from
    whole-record arrays."""
    t_ns = run.t_ns()
    u = run.u_v()
    t_s = (t_ns - t_ns[0]) / NS
    rate_hz = 1.0 / float(np.median(np.diff(t_s)))
    finite = np.all(np.isfinite(u), axis=1)
    idx, sid = [], []
    for k, s in enumerate(rec.stretches):
        ii = np.flatnonzero((t_s >= s.t_start_s) & (t_s <= s.t_end_s) & finite)
        idx.append(ii)
        sid.append(np.full(ii.size, k))
    idx, sid = np.concatenate(idx), np.concatenate(sid)
    t0 = np.array([s.t_start_s for s in rec.stretches])
    key = sid * (1 << 32) + np.floor((t_s[idx] - t0[sid]) / max(micro_s, 1.0 / rate_hz)).astype(np.int64)
    starts = np.flatnonzero(np.concatenate(([True], np.diff(key) != 0)))
    count = np.diff(np.append(starts, key.size)).astype(float)
    tt, temp = run.au_temperature["t_ns"].to_numpy(), run.au_temperature["temp_c"].to_numpy()
    temp_s = np.interp(t_ns[idx].astype(float), tt.astype(float), temp)
    same = (np.diff(idx) == 1) & (np.diff(sid) == 0)
    d = np.diff(u[idx], axis=0)[same]
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return dict(
        rate_hz=rate_hz,
        count=count,
        stretch=sid[starts],
        t_s=np.add.reduceat(t_s[idx], starts) / count,
        u_v=np.add.reduceat(u[idx], starts, axis=0) / count[:, None],
        temp_c=np.add.reduceat(temp_s, starts) / count,
        sigma_sample_v=np.maximum(1.4826 * mad / np.sqrt(2.0), 1e-9),
    )


def with_nan_and_chunks(run: Run, nan_at: np.ndarray, chunk: int) -> Run:
    """``run`` with NaN in ``ux`` or ``uz`` at ``nan_at``, its voltmeter table in chunks of ``chunk`` samples."""
    vm = run.voltmeter
    ux, uz = vm["ux"].to_numpy().copy(), vm["uz"].to_numpy().copy()
    ux[nan_at[::2]] = np.nan
    uz[nan_at[1::2]] = np.nan
    vm = vm.with_columns(pl.Series("ux", ux), pl.Series("uz", uz))
    vm = pl.concat([vm.slice(s, chunk) for s in range(0, vm.height, chunk)], rechunk=False)
    return dataclasses.replace(run, voltmeter=vm)


@pytest.fixture(scope="module")
def run10():
    """Short program at 10 Hz (126 k samples) without fixture log (arrivals read from the signal), with NaN samples
    (single ones, a run of 40, one at the start of a static stretch) in a table of 13 chunks of 9 999 samples."""
    res = simulate(SimConfig(program="short", rate_hz=10.0, seed=2, with_fixture_log=False))
    n = res.run.voltmeter.height
    rng = np.random.default_rng(1)
    t_s = res.context.t_s
    stretch_start = int(np.searchsorted(t_s, res.context.arrive_s[3] + 3.0))
    nan_at = np.unique(np.concatenate((rng.choice(n, 300, replace=False), np.arange(50_000, 50_040), [stretch_start])))
    return with_nan_and_chunks(res.run, nan_at, 9_999)


@pytest.mark.parametrize("slab", [1000, 997, None])
def test_slab_reduction_is_the_whole_record_one(run10, slab):
    run = run10
    assert run.voltmeter["ux"].n_chunks() == 13 and run.voltmeter["ux"].null_count() == 0
    assert np.isnan(run.voltmeter["ux"].to_numpy()).sum() > 100
    st = segment_settings_for(run)
    rec = static_record(run, segment_run(run, st), settings=st, slab_samples=slab)
    ref = reference_record(run, rec)
    assert rec.size > 5000 and len(rec.stretches) > 20
    assert rec.rate_hz == ref["rate_hz"]
    np.testing.assert_array_equal(rec.count, ref["count"])
    np.testing.assert_array_equal(rec.stretch, ref["stretch"])
    assert rec.count.min() < 10 and rec.count.sum() == ref["count"].sum()  # NaN samples left out
    np.testing.assert_allclose(rec.t_s, ref["t_s"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec.u_v, ref["u_v"], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(rec.temp_c, ref["temp_c"], rtol=1e-13, atol=1e-12)
    np.testing.assert_array_equal(rec.sigma_sample_v, ref["sigma_sample_v"])  # exact order statistics
    np.testing.assert_allclose(rec.sigma_sample_v, 5e-6, rtol=0.03)


def test_stretches_and_moves_do_not_depend_on_the_slab(run10):
    st = segment_settings_for(run10)
    seg = segment_run(run10, st)
    big = static_record(run10, seg, settings=st)
    tiny = static_record(run10, seg, settings=st, slab_samples=37)  # a move's gap crosses several slabs
    assert big.stretches == tiny.stretches and big.arrive_s.size > 20
    assert run10.fixture is None or run10.fixture.height == 0
    np.testing.assert_array_equal(big.move_start_s, tiny.move_start_s)
    np.testing.assert_array_equal(big.arrive_s, tiny.arrive_s)
    np.testing.assert_array_equal(big.sigma_sample_v, tiny.sigma_sample_v)
    np.testing.assert_array_equal(big.count, tiny.count)


def test_arrivals_read_from_the_signal_across_slab_boundaries(run10):
    """Moves arrive when the outputs have turned through 99.9 % of the angle: the gap is read from its end a slab
    at a time, and the crossing may fall on the last sample of a slab (then the next sample is in the slab after)."""
    st = segment_settings_for(run10)
    seg = segment_run(run10, st)
    stretches, kept = diagnose_signal._named_stretches(run10, seg, 0.5, [])
    start_ns = int(run10.t_ns()[0])
    ref = diagnose_signal._moves(run10, kept, stretches, start_ns, st.static_window_s, 1 << 20)
    for slab in (2, 3, 5):
        got = diagnose_signal._moves(run10, kept, stretches, start_ns, st.static_window_s, slab)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
    # from the signal, not the fallback (half a window before the stretch): within 1.5 s before the true arrival
    truth = simulate(SimConfig(program="short", rate_hz=10.0, seed=2, with_fixture_log=False)).context.arrive_s
    err = ref[1] - truth
    assert ref[1].size == truth.size and np.all((err < 0) & (err > -1.5))


def test_segment_settings_from_the_median_step():
    """The run's column gives for_rate's settings of its times (widened at 1 Hz, with jittered sample times)."""
    for rate_hz in (1.0, 10.0):
        run = simulate(SimConfig(program="short", rate_hz=rate_hz, seed=0)).run
        t_ns = run.t_ns() + np.random.default_rng(0).integers(-3_000, 3_000, run.voltmeter.height)
        run = dataclasses.replace(run, voltmeter=run.voltmeter.with_columns(pl.Series("t_ns", t_ns)))
        got = segment_settings_for(run)
        assert got == for_rate(SegmentSettings(), t_ns)
        assert (got.static_window_s > 2.0) == (rate_hz == 1.0)


def test_exact_medians_match_numpy():
    rng = np.random.default_rng(7)
    n = 200_001
    series = [
        rng.standard_t(2, n) * 1e-6,  # heavy tails
        np.round(rng.normal(0, 3, n)),  # few values, many ties
        np.full(n, 2.5),  # one value
        np.concatenate((rng.normal(0, 1, n // 2), rng.normal(50, 1, n - n // 2))),
    ]  # two modes

    def slabs(size):
        return lambda: ([x[s : s + size] for x in series] for s in range(0, n, size))

    truth = [np.median(x) for x in series]
    for size in (1000, 65_536):
        good = [x[::97] for x in series]
        np.testing.assert_array_equal(exact_medians(slabs(size), n, good), truth)
    # a sample that does not represent the series: the brackets miss, are widened, and the result is still exact
    bad = [x[:500] + 10.0 for x in series]
    np.testing.assert_array_equal(exact_medians(slabs(4096), n, bad), truth)
    # an even number of values: the mean of the two middle ones
    even = [x[:-1] for x in series]
    got = exact_medians(
        lambda: ([x[s : s + 777] for x in even] for s in range(0, n - 1, 777)), n - 1, [x[::50] for x in even]
    )
    np.testing.assert_array_equal(got, [np.median(x) for x in even])


@pytest.mark.parametrize(
    "effect", [("thermal_hysteresis", {"h_v": [10e-6, -8e-6, 6e-6]}), ("tilt_settling", {"f": 4e-5, "tau_s": 30.0})]
)
def test_diagnose_names_the_same_effect_at_100_hz(effect, monkeypatch):
    """The same concealed effect at 10 Hz and 100 Hz (1.3 M samples, read in slabs of 100 000): the same finding,
    of the same size."""
    monkeypatch.setattr(diagnose_signal, "SLAB_SAMPLES", 100_000)
    found = {}
    for rate_hz in (10.0, 100.0):
        res = simulate(SimConfig(program="short", rate_hz=rate_hz, seed=4, effects=[effect]))
        rep = diagnose_run(res.run).report
        found[rate_hz] = rep["findings"]
    assert [f["effect"] for f in found[10.0]] == [f["effect"] for f in found[100.0]] == [effect[0]]
    p10, p100 = found[10.0][0]["parameters"], found[100.0][0]["parameters"]
    for name, value in effect[1].items():
        np.testing.assert_allclose(p100[name], value, rtol=0.15)
        np.testing.assert_allclose(p10[name], value, rtol=0.25)
