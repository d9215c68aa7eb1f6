"""Segmentation works in time, not samples (issue 21, item 2): windows, thresholds and minimum durations are seconds
that hold for any stream rate (the thermosensor read every minute to 10 times a second, the voltmeter at 0.5 Hz
to 1 kHz), and a gap is missing data: no static stretch, segment or verification spans one, no plateau's length
counts one, no fixture label is carried across one against the signal, and the result says on which plateau data
are missing.

The cases of the issue, as they failed before: a 40-min logger dropout in the -40 C soak running into the first
position there (a "VP1 at -39.9 C" made of the gap: |dg| 273,000 micro-g, constants off by 3e-2 V/g, FAIL;
diagnose ``mismatch``); the thermosensor read every 5-10 s (the run judged a temperature sweep, ``--method auto``
picking differential, K off by 2e-2 V/g).
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from pipeline.diagnose.diagnosis import diagnose_run
from pipeline.positions import ALL_POSITIONS
from pipeline.run import NS_PER_S
from pipeline.segment import (
    SegmentSettings,
    classify_temperature,
    find_plateaus,
    find_static,
    for_rate,
    gap_spans,
    remove_spans,
    segment_run,
    slope_window_s,
    split_runs,
)
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.program import standard_program
from pipeline.simulate.unit import seed000_unit
from tests.acceptance import same_data as sd

STANDARD_C = [20.0, -40.0, -10.0, 20.0, 45.0, 70.0, 20.0]


@cache
def _standard(rate_hz: float = 1.0, seed: int = 3):
    return simulate(SimConfig(seed=seed, rate_hz=rate_hz)).run


def _check_constants(result, atol_v: float = 1e-6) -> None:
    """Every plateau's constants are the simulated unit's at its temperature."""
    unit = seed000_unit()
    for f in result.fit.per_plateau:
        k, u0 = unit.constants_at(np.array([f.temp_c]))
        np.testing.assert_allclose(f.K, k[0], atol=atol_v)
        np.testing.assert_allclose(f.U0, u0[0], atol=atol_v)


# ---------------------------------------------------------------------------------------------------------------
# static stretches: a gap cuts them, at any rate


@pytest.mark.parametrize("rate_hz", [0.5, 1.0, 10.0, 100.0, 1000.0])
def test_no_static_stretch_spans_a_gap_at_any_rate(rate_hz):
    """TP1 held for 5 min, a 2-min gap in which the unit was turned to TP2, TP2 held for 5 min: two stretches, the
    gap between them; without the gap (the turn recorded) the same two."""
    rng = np.random.default_rng(1)
    t_s = np.arange(0.0, 720.0, 1.0 / rate_hz)
    g = np.where((t_s < 360.0)[:, None], ALL_POSITIONS["TP1"], ALL_POSITIONS["TP2"])
    u = -0.55 * g + rng.normal(0.0, 5e-6, g.shape)
    keep = (t_s < 300.0) | (t_s > 420.0)
    t_ns = (t_s[keep] * NS_PER_S).astype(np.int64)
    runs = find_static(t_ns, u[keep], for_rate(SegmentSettings(), t_ns))
    assert len(runs) == 2, runs
    (a0, b0), (a1, b1) = runs
    assert t_ns[b0 - 1] < 300.5 * NS_PER_S and t_ns[a1] > 419.5 * NS_PER_S
    for a, b in runs:
        assert np.ptp(u[keep][a:b, 1]) < 1e-3  # one position each


def test_a_short_gap_does_not_cut_a_stretch():
    """A gap shorter than half the static window (2 s at 10 Hz; a 0.7-s gap, which inspect lists) is no cut."""
    t_s = np.arange(0.0, 300.0, 0.1)
    keep = (t_s < 150.0) | (t_s > 150.55)
    t_ns = (t_s[keep] * NS_PER_S).astype(np.int64)
    u = np.tile(-0.55 * np.asarray(ALL_POSITIONS["TP1"]), (t_ns.size, 1))
    u += np.random.default_rng(2).normal(0.0, 5e-6, u.shape)
    assert len(find_static(t_ns, u, for_rate(SegmentSettings(), t_ns))) == 1


def test_split_runs_and_remove_spans():
    runs = np.array([[0, 10], [12, 20]])
    assert split_runs(runs, np.array([5, 12, 15])).tolist() == [[0, 5], [5, 10], [12, 15], [15, 20]]
    t_ns = np.arange(20, dtype=np.int64) * NS_PER_S
    # samples strictly inside (3 s, 7 s) and (14 s, 16 s) are removed
    spans = np.array([[3, 7], [14, 16]], dtype=np.int64) * NS_PER_S
    assert remove_spans(t_ns, runs, spans) == [(0, 4), (7, 10), (12, 15), (16, 20)]
    assert gap_spans(np.array([0, 1, 2, 30, 31, 32]) * NS_PER_S, 2.0).tolist() == [[2 * NS_PER_S, 30 * NS_PER_S]]


def test_the_issues_dropout_in_the_minus_40_soak_makes_no_position():
    """A 40-min dropout of every stream from the -40 C soak into the first position there (TP1): before, the
    static stretch ran from TP6 in the soak across the gap into TP1 and was named VP1; now nothing is made of the
    gap, TP1's rest after the gap is TP1, the constants are the unit's, the status pass, diagnose consistent."""
    run = _standard(10.0)
    gapped = sd.gap(run, 12300.0, 14700.0)
    seg = segment_run(gapped)
    lo, hi = sd.start_ns(run) + 12300 * NS_PER_S, sd.start_ns(run) + 14700 * NS_PER_S
    assert not [s for s in seg.segments if s.t_start_ns < hi and s.t_end_ns > lo]
    minus40 = [s for s in seg.segments if s.plateau is not None and seg.plateaus[s.plateau].temp_c < -30]
    assert {s.position for s in minus40} == {f"TP{i}" for i in range(1, 7)}
    said = [w for w in seg.warnings if w.startswith("plateau 1 at -40.0 C: no ")]
    assert len(said) == 1 and "voltmeter" in said[0] and "au_temperature" in said[0], seg.warnings
    result, method = sd.calibrate_runs([gapped])
    assert method == "tilt" and result.status == "pass"
    assert not [r for r in result.rows if r.temp_c < -30]
    _check_constants(result)
    assert diagnose_run(gapped).report["verdict"] == "consistent"


def test_a_stale_fixture_label_after_a_gap_is_no_label():
    """The fixture log lost the move in the gap: the label before it (TP6) is not carried onto what the unit did
    after it (TP1): no label conflict, no implausible-fixture warning; named from gravity."""
    run = _standard(1.0)
    seg = segment_run(sd.gap(run, 12300.0, 14700.0))
    after = [s for s in seg.segments if s.t_start_ns > sd.start_ns(run) + 14700 * NS_PER_S][0]
    assert after.position == "TP1" and after.fixture_label is None and after.label_source == "gravity"
    assert not any("conflict" in w for w in seg.warnings)


# ---------------------------------------------------------------------------------------------------------------
# plateaus: the thermosensor at any rate, with gaps


@pytest.mark.parametrize("interval_s", [0.1, 1.0, 5.0, 10.0, 30.0, 60.0])
def test_plateaus_for_a_thermosensor_read_every_minute_to_ten_times_a_second(interval_s):
    run = _standard(1.0)
    run = (
        sd.interpolate(run, "au_temperature", 1.0 / interval_s)
        if interval_s < 1
        else sd.decimate(run, "au_temperature", interval_s)
    )
    t, temp = run.thermosensor()
    plateaus = find_plateaus(t, temp)
    assert [round(p.temp_c) for p in plateaus] == pytest.approx(STANDARD_C, abs=0.5)
    assert classify_temperature(t, temp, plateaus).kind == "plateaus"


def test_slope_window_grows_with_the_thermosensor_interval():
    def window(interval_s):
        return slope_window_s((np.arange(100) * interval_s * NS_PER_S).astype(np.int64))

    assert window(0.1) == window(1.0) == 75.0  # the default (plateau_min_s / 4)
    assert window(5.0) == pytest.approx(75.0 * 5 ** (1 / 3))  # the slope's noise as at 1 s
    assert window(30.0) == pytest.approx(75.0 * 30 ** (1 / 3))
    assert window(60.0) == 300.0  # five samples


@pytest.mark.parametrize("interval_s", [1.0, 5.0, 10.0])
def test_the_issues_thermosensor_at_one_reading_every_few_seconds_is_a_plateau_program(interval_s):
    """Before: at 0.2 Hz the -40 C and +70 C soaks broke into pieces chained as a drift: a sweep, the differential
    method, K off by 2e-2 V/g. Now: seven plateaus, tilt, the unit's constants, pass."""
    run = sd.decimate(_standard(10.0), "au_temperature", interval_s)
    result, method = sd.calibrate_runs([run])
    assert method == "tilt" and result.status == "pass"
    assert len(result.fit.per_plateau) == 5
    _check_constants(result)


def test_a_plateau_across_a_thermosensor_gap_is_one_plateau_with_its_gap():
    """A 30-min gap of the thermosensor alone inside the -40 C soak (the unit stable on both sides): one plateau,
    its gap listed, its length of data without it; no segment has samples inside the gap (no temperature there)."""
    run = _standard(1.0)
    gapped = sd.gap(run, 12000.0, 13800.0, ("au_temperature",))
    seg = segment_run(gapped)
    cold = [p for p in seg.plateaus if p.temp_c < -30]
    assert len(cold) == 1 and len(cold[0].gaps) == 1
    (a, b), t0 = cold[0].gaps[0], sd.start_ns(run)
    assert abs(a - t0 - 12000 * NS_PER_S) <= NS_PER_S and abs(b - t0 - 13800 * NS_PER_S) <= NS_PER_S
    assert cold[0].covered_s == pytest.approx(cold[0].duration_s - (b - a) / NS_PER_S)
    assert not [s for s in seg.segments if s.t_start_ns < b and s.t_end_ns > a]
    assert seg.gaps_ns["au_temperature"] == [(a, b)]


# ---------------------------------------------------------------------------------------------------------------
# the voltmeter at 0.5 Hz .. 1 kHz


@pytest.mark.parametrize("rate_hz", [0.5, 2.0])
def test_the_standard_program_at_a_slow_voltmeter(rate_hz):
    run = sd.decimate(_standard(10.0), "voltmeter", 1.0 / rate_hz)
    result, method = sd.calibrate_runs([run])
    assert method == "tilt" and result.status == "pass"
    _check_constants(result, atol_v=3e-6)  # fewer samples: 5 uV of noise over 150 of them


@pytest.mark.slow
def test_the_short_program_at_1_khz():
    """3.5 h at 1 kHz (12.7 M samples): the static window stays 2 s, the segments the holds."""
    run = simulate(SimConfig(seed=4, rate_hz=1000.0, program="short", vibration_g=1e-3)).run
    seg = segment_run(run)
    assert seg.static_window_s == 2.0
    assert [round(p.temp_c) for p in seg.plateaus] == pytest.approx(STANDARD_C, abs=0.5)
    result, method = sd.calibrate_runs([run])
    assert method == "tilt" and result.status == "pass"
    _check_constants(result, atol_v=1e-6)


def test_standard_program_has_its_seven_plateaus_and_no_gap():
    """The reference: the standard program as simulated has no gap and its seven plateaus (nothing listed)."""
    seg = segment_run(_standard(1.0))
    assert [round(p.temp_c) for p in seg.plateaus] == pytest.approx(STANDARD_C, abs=0.5)
    assert seg.gaps_ns == {"voltmeter": [], "au_temperature": []}
    assert all(not p.gaps for p in seg.plateaus)
    assert standard_program().timetable().duration_s == pytest.approx(59260.0)


def test_a_gap_over_a_whole_hold_names_the_position_it_took():
    """A voltmeter gap over the whole VP5 hold at -10 C (short program, 1 Hz): the plateau's line names VP5 from the
    fixture log; a gap inside the VP3 hold (the rest of it still held) and the same gap without a fixture log name
    no position; the thermosensor lost over the whole soak (no plateau found) names what the log held then.
    Before: 'a position held only then is missing' in every case, VP5 nowhere in the result."""
    import dataclasses

    import polars as pl

    run = simulate(SimConfig(seed=5, rate_hz=1.0, program="short")).run
    t0 = int(run.voltmeter["t_ns"].min())

    def without(r, a_s: float, b_s: float):
        lo, hi = t0 + int(a_s * NS_PER_S), t0 + int(b_s * NS_PER_S)
        return dataclasses.replace(r, voltmeter=r.voltmeter.filter((pl.col("t_ns") < lo) | (pl.col("t_ns") > hi)))

    def line(r):
        (w,) = [w for w in segment_run(r).warnings if w.startswith("plateau 2 at -10")]
        return w

    # the fixture log: VP5 from 4900 s, moving at 4960 s; VP3 4760..4820 s
    assert line(without(run, 4895.0, 4965.0)).endswith("(VP5, held only then (fixture log), is missing)")
    assert line(without(run, 4770.0, 4790.0)).endswith("(a position held only then is missing)")
    no_log = dataclasses.replace(run, fixture=None)
    assert line(without(no_log, 4895.0, 4965.0)).endswith("(a position held only then is missing)")
    # the thermosensor lost over the whole -10 C soak: no plateau there; the line says what the log held then
    lo, hi = t0 + 4000 * NS_PER_S, t0 + 5600 * NS_PER_S
    no_soak = dataclasses.replace(
        run, au_temperature=run.au_temperature.filter((pl.col("t_ns") < lo) | (pl.col("t_ns") > hi))
    )
    seg = segment_run(no_soak)
    assert [round(p.temp_c) for p in seg.plateaus] == [20, -40, 20, 45, 70, 20]
    (off,) = [w for w in seg.warnings if w.startswith("off every plateau")]
    assert off.endswith("(the fixture log held TP6, VP1, VP2, VP3, VP4, VP5, VP6 then)")


def test_a_gap_inside_a_hold_leaves_one_hold_unless_the_fixture_log_shows_a_move():
    """A 61-s gap of every stream inside the VP3 hold at -10 C and inside the TP3 hold at -40 C (standard program,
    1 Hz): one VP row and one TP3 observation per hold (the two pieces pooled), the same VP rows as the clean run
    and the same passport within its stated uncertainty. Before: VP3 at -10 C twice (25 rows), TP3 at -40 C twice.
    A move logged in the gap (MOVING, then VP3 again) makes two holds."""
    import dataclasses

    import polars as pl

    from pipeline.calibrate.observations import observe_run

    run = _standard(1.0)
    t0 = sd.start_ns(run)
    clean, _ = sd.calibrate_runs([run])
    # fixture log: TP3 at -40 C 15160..15460 s, VP3 at -10 C 22480..22780 s
    gapped = sd.gap(sd.gap(run, 22600.0, 22661.0), 15300.0, 15361.0)
    result, _ = sd.calibrate_runs([gapped])

    def rows(r):
        return [(x.position, x.plateau, round(x.temp_c)) for x in r.rows]

    assert len(rows(clean)) == 24 and rows(result) == rows(clean)
    assert not sd.same_passport(clean.passport, result.passport)
    obs, _ = observe_run(gapped)
    tp3 = [o for o in obs if o.position == "TP3" and o.plateau == 1]
    assert len(tp3) == 1 and tp3[0].t_start_ns < t0 + 15300 * NS_PER_S < t0 + 15361 * NS_PER_S < tp3[0].t_end_ns
    (vp3,) = [r for r in result.rows if r.position == "VP3" and round(r.temp_c) == -10]
    (vp3_clean,) = [r for r in clean.rows if r.position == "VP3" and round(r.temp_c) == -10]
    assert abs(vp3.dg_method1_g - vp3_clean.dg_method1_g) < 5e-6  # the hold's own noise (a few micro-g)
    # the segments themselves still stop at the gap
    seg = segment_run(gapped)
    lo, hi = t0 + 22600 * NS_PER_S, t0 + 22661 * NS_PER_S
    assert not [s for s in seg.segments if s.t_start_ns < hi and s.t_end_ns > lo]
    # a move logged in the gap: two holds, two rows
    moved = pl.DataFrame(
        {"t_ns": [t0 + 22620 * NS_PER_S, t0 + 22640 * NS_PER_S], "position": ["MOVING", "VP3"]},
        schema={"t_ns": pl.Int64, "position": pl.String},
    )
    fixture = pl.concat([gapped.fixture, moved]).sort("t_ns")
    two, _ = sd.calibrate_runs([dataclasses.replace(gapped, fixture=fixture)])
    assert [r[0] for r in rows(two) if r[2] == -10].count("VP3") == 2
