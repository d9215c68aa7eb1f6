"""Segmentation of a run with several units (pipeline.segment_units): the still times once for the run, the same
segments per unit as each unit alone; a unit turned on the table, or moving while the others hold still, is named
with the position and the time."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from pipeline.run import UnitRuns
from pipeline.segment import segment_run
from pipeline.segment_units import _majority, segment_units
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.units import simulate_units


@pytest.fixture(scope="module")
def four():
    return simulate_units(SimConfig(unit_serial="AU-0501", program="short", rate_hz=5.0), 4)[0]


def test_majority_of_spans():
    a = np.array([[0, 10], [20, 30]])
    b = np.array([[2, 12], [25, 40]])
    c = np.array([[5, 8]])
    whole = np.array([[0, 40]])
    assert _majority([a, b, c], [whole] * 3).tolist() == [[2, 10], [25, 30]]
    # c has no samples after 20: of the two units left, both must be still
    assert _majority([a, b, c], [whole, whole, np.array([[0, 20]])]).tolist() == [[2, 10], [25, 30]]
    # b has samples from 20 on (still from 25), c until 9: a and c decide 5 .. 8 and a alone 9 .. 10
    b, c = np.array([[25, 40]]), np.array([[5, 8]])
    got = _majority([a, b, c], [whole, np.array([[20, 40]]), np.array([[0, 9]])])
    assert got.tolist() == [[5, 8], [9, 10], [25, 30]]


def test_same_segments_as_each_unit_alone(four):
    """The segments a calibration uses (on a plateau or in its settling) are each unit's own, named alike, with the
    same averages (a consensus break may cut a hold on a ramp once more: such pieces are not observations)."""
    segs, warnings = segment_units(four.units)
    assert warnings == []

    def used(seg):
        return [s for s in seg.segments if s.plateau is not None or s.settling is not None]

    for serial, run in four.units.items():
        alone = segment_run(run)
        assert segs[serial].plateaus == alone.plateaus
        a, b = used(segs[serial]), used(alone)
        assert [(s.position, s.plateau, s.settling) for s in a] == [(s.position, s.plateau, s.settling) for s in b]
        assert len(a) > 40
        np.testing.assert_allclose([s.mean_v for s in a], [s.mean_v for s in b], atol=2e-6)


def test_a_unit_that_disagrees_is_named(four):
    u = four.units
    v = u["AU-0503"].voltmeter
    turned = dataclasses.replace(u["AU-0503"], voltmeter=v.with_columns(ux=-v["uy"], uy=v["ux"]))
    segs, warnings = segment_units(UnitRuns.of_units([u["AU-0501"], u["AU-0502"], turned, u["AU-0504"]]).units)
    assert len(warnings) == 1
    assert warnings[0].startswith("unit AU-0503: its signal names") and "t_ns=" in warnings[0]
    assert " where they hold TP" in warnings[0]
    assert warnings[0] in segs["AU-0503"].warnings and not segs["AU-0501"].warnings

    # AU-0502 shaken for 2 minutes in the middle of a hold, the others still
    alone = segment_run(u["AU-0502"])
    hold = max(alone.segments, key=lambda s: s.duration_s)
    mid = (hold.t_start_ns + hold.t_end_ns) // 2
    t = u["AU-0502"].voltmeter["t_ns"]
    shake = ((t - mid).abs() < 60_000_000_000).cast(pl.Float64) * (t.cast(pl.Float64) * 1e-9 * 3.0).sin() * 0.05
    shaken = dataclasses.replace(u["AU-0502"], voltmeter=u["AU-0502"].voltmeter.with_columns(ux=pl.col("ux") + shake))
    segs, warnings = segment_units(UnitRuns.of_units([u["AU-0501"], shaken, u["AU-0503"], u["AU-0504"]]).units)
    named = [w for w in warnings if w.startswith("unit AU-0502: not still in 1 of the")]
    assert len(named) == 1 and "(fixture: " in named[0], warnings
    # the others keep that hold; the shaken unit has no segment across the shaking
    assert any(s.t_start_ns <= mid <= s.t_end_ns for s in segs["AU-0501"].segments)
    assert not any(s.t_start_ns <= mid <= s.t_end_ns for s in segs["AU-0502"].segments)


def test_no_unit_named_for_drift_in_a_ramp_a_gap_or_a_turned_neighbour():
    """At 2 Hz the short program holds positions through its ramps (up to 4 C/min): a still unit's voltages drift
    with its temperature there and its own still stretches end up to a minute before the others' (not named: two
    of four clean units were); a unit with 200 s without samples is not "not still" in that gap; of three units,
    one turned, only the turned one is named (one other unit is no majority: the others were named too)."""
    u = simulate_units(SimConfig(unit_serial="AU-0701", program="short", rate_hz=2.0), 4)[0].units
    assert segment_units(u)[1] == []
    v1, v3 = u["AU-0701"].voltmeter, u["AU-0703"].voltmeter
    gappy = v1.filter((pl.col("t_ns") < v1["t_ns"][3000]) | (pl.col("t_ns") > v1["t_ns"][3400]))
    three = [
        dataclasses.replace(u["AU-0701"], voltmeter=gappy),
        dataclasses.replace(u["AU-0703"], voltmeter=v3.with_columns(ux=-v3["uy"], uy=v3["ux"])),
        u["AU-0704"],
    ]
    _, warnings = segment_units(UnitRuns.of_units(three).units)
    assert len(warnings) == 1 and warnings[0].startswith("unit AU-0703: its signal names"), warnings


def test_no_unit_named_for_holds_it_has_no_samples_in(four):
    """A unit whose voltmeter drops out for 5 minutes (whole holds without a sample) or ends early, or one of whose
    channels reads NaN from some time on, is not "not still" where it has no (finite) samples: that is missing data,
    named by the readers' and the segmenter's warnings (4, 24 and 41 holds were named); its other holds are its own
    as before."""
    u = four.units
    v1, v2, v3 = u["AU-0501"].voltmeter, u["AU-0502"].voltmeter, u["AU-0503"].voltmeter
    t0 = int(v1["t_ns"][0])
    gap = (pl.col("t_ns") < t0 + 3000 * 10**9) | (pl.col("t_ns") >= t0 + 3300 * 10**9)
    nan_z = pl.when(pl.col("t_ns") > t0 + 6000 * 10**9).then(float("nan")).otherwise(pl.col("uz"))
    units = {
        **u,
        "AU-0501": dataclasses.replace(u["AU-0501"], voltmeter=v1.filter(gap)),
        "AU-0502": dataclasses.replace(u["AU-0502"], voltmeter=v2.filter(pl.col("t_ns") < t0 + 7600 * 10**9)),
        "AU-0503": dataclasses.replace(u["AU-0503"], voltmeter=v3.with_columns(uz=nan_z)),
    }
    segs, warnings = segment_units(units)
    assert warnings == []
    assert not any(
        t0 + 3000 * 10**9 <= s.t_end_ns and s.t_start_ns < t0 + 3300 * 10**9 for s in segs["AU-0501"].segments
    )
    assert len(segs["AU-0501"].segments) > 40 and len(segs["AU-0502"].segments) > 20
    assert not any(s.t_end_ns > t0 + 6000 * 10**9 for s in segs["AU-0503"].segments)
    # the others' holds stay theirs: a unit without samples has no say in the consensus (with two units, one in its
    # gap, the other lost the 4 holds of the gap; with three of four missing data, the last lost 41)
    for run, others in ((u["AU-0504"], units), (u["AU-0502"], {"AU-0501": units["AU-0501"], "AU-0502": u["AU-0502"]})):
        on_plateaus = [(g.position, g.plateau) for g in segment_units(others)[0][run.meta.unit_serial].segments]
        alone = [(g.position, g.plateau) for g in segment_run(run).segments]
        assert [x for x in on_plateaus if x[1] is not None] == [x for x in alone if x[1] is not None]


def test_units_on_one_clock_share_its_times_and_segment_as_on_their_own(four, monkeypatch):
    """The units whose voltmeter times are the first unit's share one copy of them (and of their gaps and median
    interval); a unit with other times has its own. Sharing changes no segment: the same segmentations, field by
    field, as with a copy of the times per unit."""
    from pipeline import segment_units as su
    from pipeline.segment import unit_clock

    units = dict(four.units)
    last = list(units)[-1]
    v = units[last].voltmeter
    units[last] = dataclasses.replace(units[last], voltmeter=v.with_columns(pl.col("t_ns") + 1_000_000))
    clocks = su._clocks(units)
    first = clocks[next(iter(units))][0]
    assert all(clocks[s][0] is first for s in list(units)[1:-1]) and clocks[last][0] is not first
    assert np.array_equal(clocks[last][0], units[last].t_ns())
    shared = segment_units(units)
    # what the segmenter found from the shared times (the blocks of the static test) is in the clock, once
    found = clocks[next(iter(units))].found
    assert all(clocks[s].found is found for s in list(units)[1:-1]) and clocks[last].found is not found
    monkeypatch.setattr(su, "_clocks", lambda us: {s: unit_clock(r) for s, r in us.items()})
    assert segment_units(units) == shared


@pytest.mark.parametrize(
    "stretches",
    [
        (("uy", 2900, 1200, float("nan")),),
        (("ux", 1000, 100, float("nan")), ("uz", 1000, 100, float("inf")), ("uz", 5000, 300, float("nan"))),
    ],
    ids=["uy 20 min", "ux+uz, then uz"],
)
def test_non_finite_samples_are_named_by_unit_channel_and_seconds(four, stretches):
    """A channel NaN (or inf) for part of a run: one line per unit naming the unit (in a run with several), each
    channel with its count, and the stretches in seconds (how many, in all, the first and the longest: UTC, s after
    the start, duration), as a stuck channel's line. Was: "voltmeter: 6000 non-finite samples excluded (not
    static), first at t_ns=..." (no unit, no channel, no duration)."""
    from pipeline.utc import utc_span

    u = four.units
    run = u["AU-0503"]
    t = run.voltmeter["t_ns"].to_numpy()
    step_ns = float(np.median(np.diff(t)))
    bad = np.zeros(t.size, bool)
    v = run.voltmeter
    per = {}
    for c, a_s, dur_s, x in stretches:
        sel = (t >= t[0] + a_s * 10**9) & (t < t[0] + (a_s + dur_s) * 10**9)
        bad |= sel
        per[c] = per.get(c, np.zeros(t.size, bool)) | sel
        v = v.with_columns(pl.when(pl.Series(sel)).then(x).otherwise(pl.col(c)).alias(c))
    edited = dataclasses.replace(run, voltmeter=v)
    edge = np.flatnonzero(np.diff(np.concatenate(([0], bad.astype(np.int8), [0]))))
    runs = edge.reshape(-1, 2)  # [first, end) of each stretch
    dur = (t[runs[:, 1] - 1] - t[runs[:, 0]] + step_ns) / 1e9

    def one(k):
        a, b = runs[k]
        return (
            f"for {dur[k]:.1f} s from t_ns={t[a]} ({utc_span(int(t[a]), int(t[b - 1]))}, "
            f"{(t[a] - t[0]) / 1e9:.1f} s after the start)"
        )

    longest = int(np.argmax(dur))
    said = f"the first {one(0)}" + (f"; the longest {one(longest)}" if longest else "")
    channels = ", ".join(f"{c} {int(per[c].sum())}" for c in ("ux", "uy", "uz") if c in per)
    tail = (
        f"{int(bad.sum())} non-finite samples excluded (not static), {channels}, in {len(runs)} stretch(es), "
        f"{dur.sum():.1f} s in all: {said}"
    )
    segs, _ = segment_units({**u, "AU-0503": edited})
    assert [w for w in segs["AU-0503"].warnings if "non-finite" in w] == [f"voltmeter of unit AU-0503: {tail}"]
    assert not any("non-finite" in w for s, seg in segs.items() if s != "AU-0503" for w in seg.warnings)
    assert [w for w in segment_run(edited).warnings if "non-finite" in w] == [f"voltmeter: {tail}"]
    assert f"{dur.sum():.1f}" == f"{sum(d for _, d in {(a, d) for _, a, d, _ in stretches}):.1f}"  # 1200.0, 400.0


@pytest.mark.parametrize("with_nan", [False, True], ids=["uy frozen", "uy frozen, ux NaN 100 s"])
def test_a_stuck_stretch_is_not_counted_again_as_non_finite(four, tmp_path, with_nan):
    """uy of AU-0503 frozen at its last value for 1200 s from 2900 s (real Parquet files, read back): the readers
    name it ('uy stuck ... 1200.x s') and set it to NaN. Before, the segmenter counted those samples again:
    'voltmeter of unit AU-0503: 6001 non-finite samples excluded (not static), uy 6001, ...' beside the stuck line.
    Now no non-finite line for it; a stretch the file holds as NaN (ux, 100 s from 1000 s) is still named, alone."""
    from pipeline.io.runs import read_units, write_run
    from pipeline.utc import utc_span

    path = write_run(UnitRuns.of_units(list(four.units.values())), tmp_path / "run", "parquet")
    v = pl.read_parquet(path / "voltmeter.parquet")
    mine = pl.col("unit") == "AU-0503"
    rel = (pl.col("t_ns") - v["t_ns"].min()) / 1e9
    last = float(v.filter(mine & (rel < 2900))["uy"][-1])
    v = v.with_columns(pl.when(mine & (rel >= 2900) & (rel < 4100)).then(last).otherwise(pl.col("uy")).alias("uy"))
    if with_nan:
        v = v.with_columns(
            pl.when(mine & (rel >= 1000) & (rel < 1100)).then(float("nan")).otherwise(pl.col("ux")).alias("ux")
        )
    v.write_parquet(path / "voltmeter.parquet")
    runs = read_units(path)
    assert [w for w in runs.units["AU-0503"].warnings if " uy stuck " in w]
    segs, _ = segment_units(runs.units)
    said = [w for w in segs["AU-0503"].warnings if "non-finite" in w]
    if not with_nan:
        assert said == []
        return
    t = runs.units["AU-0503"].voltmeter["t_ns"].to_numpy()
    a = int(np.argmax(t >= t[0] + 1000 * 10**9))
    b = int(np.argmax(t >= t[0] + 1100 * 10**9))
    assert said == [
        f"voltmeter of unit AU-0503: {b - a} non-finite samples excluded (not static), ux {b - a}, in 1 stretch(es), "
        f"100.0 s in all: the first for 100.0 s from t_ns={t[a]} ({utc_span(int(t[a]), int(t[b - 1]))}, 1000.0 s "
        "after the start)"
    ]
