"""Same data, same passport (issue 21, item 1): metamorphic, property-based tests (hypothesis).

A transformation that removes nothing the calibration needs leaves the passport the same within its stated
uncertainty (every coefficient within 4 standard uncertainties of both passports combined), with the same method and
status, and ``diagnose`` gives the same verdict. Transformations (:mod:`tests.acceptance.same_data`): a gap of any
length anywhere no hold is (soaks, ramps, sweeps, between poses) in all streams or in one, every stream's rate
changed (the thermosensor read every 2 s .. 1 min or interpolated to 10 Hz, the voltmeter decimated to 0.5 Hz or
simulated at up to 1 kHz, the chamber stream left out), all times shifted, the rows of every stream shuffled in the
files, an exact duplicate file, the run split into several files at any points and given in any order.

A gap over a hold does remove information: then no segment, plateau constant or verification row is made of the
missing time or names a position the unit was not in (never invents one), and the result says what is missing:
the plateau and the time without data, and the test position a plateau's constants lack.

Recordings: simulated runs of every program (standard, short, sweep, handheld, differential: small ones, at low
rates); the real recordings' properties are in test_same_data_real.py. Each recording's reference passport and
diagnose verdict are computed once per session (:func:`reference`, :func:`reference_verdict`).
By default (CI) every program takes every kind of transformation at once (:func:`every_kind`) at the hard corners
(:data:`CORNERS`: the slowest thermosensor and voltmeter with a long gap at the end of a soak, 10 Hz and an uneven
voltmeter rate with a long gap in a ramp, 3-5 files reversed or shuffled with a copy; :data:`CORNER_CASES`), the
standard, short and hand-held programs also in one drawn example (:data:`DRAWN`; the first draw is no identity);
each kind alone is searched with :data:`EXAMPLES` examples on the cheap recordings (the short and hand-held
programs). ``THERMOCAL_HYPOTHESIS_EXAMPLES=N`` searches N examples per property over every recording, and every
corner on every one (N=5: about 40 min at load 13).
"""

from __future__ import annotations

import dataclasses
import random
import re
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from pipeline.calibrate import inputs
from pipeline.io.runs import read_run, write_run
from pipeline.positions import POSITION_NAMES
from pipeline.run import NS_PER_S, Run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.program import get_program
from tests.acceptance import same_data as sd

DEEP = sd.DEEP
PROPERTY = sd.property_settings(2)
EXAMPLES = PROPERTY.max_examples
JOINS_FILES = hasattr(inputs, "join_runs")


@dataclass(frozen=True)
class Recording:
    """A recording to transform: its run, the program it follows (None: a real one) and the slowest voltmeter
    rate (Hz) whose samples still hold its poses (hand-turned poses of 3 s need tens of samples a second)."""

    name: str
    run: Run
    program: str | None
    min_voltmeter_hz: float

    @property
    def start_ns(self) -> int:
        return sd.start_ns(self.run)

    def holds_ns(self) -> list[tuple[int, int, str]]:
        """(start, end, position) of the program's holds, in the run's time (none for a real recording)."""
        if self.program is None:
            return []
        tt = get_program(self.program).timetable()
        return [
            (self.start_ns + int(h.t_start_s * NS_PER_S), self.start_ns + int(h.t_end_s * NS_PER_S), h.position)
            for h in tt.holds()
        ]

    def held_at(self, temp_c: float) -> set[str]:
        """The positions the program holds at the setpoint ``temp_c`` (within 2 C; all of them: a real one)."""
        if self.program is None:
            return set(POSITION_NAMES)
        tt = get_program(self.program).timetable()
        return {h.position for h in tt.holds() if abs(tt.setpoint_c(h.t_start_s) - temp_c) <= 2.0}

    def positions_at(self, t_ns) -> np.ndarray:
        """The program's position at ``t_ns`` (``MOVING`` during moves)."""
        tt = get_program(self.program).timetable()
        return tt.positions((np.asarray(t_ns, dtype=np.int64) - self.start_ns) / NS_PER_S)


SIMULATED = {
    # name: (SimConfig, slowest voltmeter rate that holds the program's poses)
    "standard": (SimConfig(seed=21, rate_hz=2.0), 0.5),
    "short": (SimConfig(seed=22, rate_hz=5.0, program="short"), 2.0),
    "sweep": (SimConfig(seed=23, rate_hz=1.0, program="sweep"), 0.5),
    "handheld": (SimConfig(seed=24, rate_hz=100.0, program="handheld", jitter_s=0.002), 25.0),
    "differential": (SimConfig(seed=25, rate_hz=1.0, program="differential"), 0.5),
}


#: the recordings every property is searched on by default (a few seconds per example)
CHEAP = ("short", "handheld")


#: the recordings whose properties also run in ``make test-fast`` (about a second per example); the others' are slow
FAST = ("handheld",)


def lean(cases):
    """``cases`` (names, or tuples starting with the name) as the default run takes them: the cheap recordings'
    only, every one with :data:`DEEP`; marked slow unless on a :data:`FAST` recording."""
    out = []
    for c in cases:
        name = c[0] if isinstance(c, tuple) else c
        if DEEP or name in CHEAP:
            values = c if isinstance(c, tuple) else (c,)
            out.append(pytest.param(*values, marks=() if name in FAST else pytest.mark.slow))
    return out


@cache
def recording(name: str) -> Recording:
    if name in SIMULATED:
        config, min_hz = SIMULATED[name]
        return Recording(name, simulate(config).run, name, min_hz)
    raise KeyError(name)


@cache
def reference(name: str):
    """The passport (as calibrate computes it) and the method of the untouched recording."""
    return sd.calibrate_runs([recording(name).run])


@cache
def reference_verdict(name: str) -> str:
    """diagnose's verdict on the untouched recording."""
    return sd.diagnose_verdict([recording(name).run])


def check_same(name: str, runs: list[Run], what: str, *, verdict: bool = True) -> None:
    """The passport of ``runs`` is the reference's within the stated uncertainty, same method and status; and
    diagnose gives the same verdict (``verdict``)."""
    ref, ref_method = reference(name)
    result, method = sd.calibrate_runs(runs)
    assert method == ref_method, (what, method, ref_method)
    diffs = sd.same_passport(ref.passport, result.passport)
    assert not diffs, (what, [str(d) for d in diffs[:6]])
    # the positions on each plateau: none invented, none of the program's holds there lost (a gap in a soak may
    # take the position the unit sat in through it: no hold of the program, and not needed)
    got, want = ([set(p["positions"]) for p in r.plateaus] for r in (result, ref))
    assert len(got) == len(want) and all(g <= w for g, w in zip(got, want)), (what, got, want)
    rec = recording(name)
    held = [rec.held_at(p["temp_c"]) for p in ref.plateaus]
    assert all(w & h <= g for g, w, h in zip(got, want, held)), (what, got, want)
    if verdict:
        assert sd.diagnose_verdict(runs) == reference_verdict(name), what


def free_spans(rec: Recording, margin_s: float) -> list[tuple[float, float]]:
    """The spans (s from the start) that no hold of the program touches, ``margin_s`` away from every hold: soaks,
    ramps, sweeps and the moves between poses (the whole record for a recording without holds)."""
    end = sd.duration_s(rec.run)
    holds = sorted(((a - rec.start_ns) / NS_PER_S, (b - rec.start_ns) / NS_PER_S) for a, b, _ in rec.holds_ns())
    out, t = [], 0.0
    for a, b in holds:
        if a - margin_s > t:
            out.append((t, a - margin_s))
        t = max(t, b + margin_s)
    if end > t:
        out.append((t, end))
    return out


# ---------------------------------------------------------------------------------------------------------------
# gaps


GAP_STREAMS = st.sampled_from([sd.STREAMS, ("voltmeter",), ("au_temperature",), ("voltmeter", "au_temperature")])


@pytest.mark.parametrize(
    ("name", "longest_s"),
    lean([("standard", 7200.0), ("short", 1800.0), ("sweep", 3600.0), ("handheld", 30.0), ("differential", 3600.0)]),
)
@PROPERTY
@given(where=st.floats(0.0, 1.0), length=st.floats(0.0, 1.0), pick=st.floats(0.0, 1.0), streams=GAP_STREAMS)
# found by the deep search: short, the thermosensor missing over the -10 C soak (3455..4605 s) where the unit sits in
# TP6 before the VP holds: TP6 gone from that plateau (no hold of the program there; the check now allows it)
@example(where=0.0728761799230724, length=0.7705929266389755, pick=0.30351573588168274, streams=("au_temperature",))
def test_a_gap_where_no_pose_is_held_changes_nothing(name, longest_s, where, length, pick, streams):
    """A gap of any length up to ``longest_s`` (a sweep's orientations last hours: a gap is at most an hour of
    one) anywhere no pose is held: in a soak, a ramp, a sweep, between two poses."""
    rec = recording(name)
    spans = free_spans(rec, margin_s=15.0 if name != "handheld" else 0.5)
    a, b = spans[min(int(pick * len(spans)), len(spans) - 1)]
    t0 = a + where * (b - a)
    t1 = min(b, t0 + length * longest_s)
    assume(t1 - t0 > 0.1)
    check_same(name, [sd.gap(rec.run, t0, t1, streams)], f"gap {t0:.0f}..{t1:.0f} s in {streams}")


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) for n in ("short", "standard")])
@PROPERTY
@given(hold=st.integers(0, 10_000), before=st.floats(0.0, 600.0), after=st.floats(0.0, 600.0), streams=GAP_STREAMS)
# found by the deep search: short, the last hold (VP6) and all after it gone: a shorter record, nothing to say
@example(hold=1943, before=50.784011622920666, after=458.82890594810334, streams=("voltmeter", "au_temperature"))
def test_a_gap_over_a_hold_is_said_and_invents_nothing(name, hold, before, after, streams):
    """A gap covering a whole hold of a chamber program removes that visit of the position: the result says on
    which plateau data are missing and when, a test position missing from a plateau's constants is named, no
    segment or verification row is made of the missing time, and none names a position the unit was not in."""
    rec = recording(name)
    holds = rec.holds_ns()
    h0, h1, position = holds[hold % len(holds)]
    lo, hi = h0 - int(before * NS_PER_S), h1 + int(after * NS_PER_S)
    run = sd.gap(rec.run, (lo - rec.start_ns) / NS_PER_S, (hi - rec.start_ns) / NS_PER_S, streams)
    from pipeline.segment import segment_run

    seg = segment_run(run)
    for s in seg.segments:
        assert s.t_end_ns < lo or s.t_start_ns > hi, ("a segment made of the gap", s)
        if s.position is not None:
            held = set(rec.positions_at([s.t_start_ns, (s.t_start_ns + s.t_end_ns) // 2, s.t_end_ns]))
            assert held == {s.position}, ("a position the unit was not in", s.position, held)
    result, _ = sd.calibrate_runs([run])
    said = " | ".join(result.warnings)
    gone = [w for w in result.warnings if w.startswith(("plateau ", "off every plateau")) and " data " in w]
    # the plateau (or none), the stream(s) and the time without data; a "gap" past either end of the record is a
    # shorter record, which nothing can tell from one that ended there
    assert gone or lo <= rec.start_ns or hi >= rec.start_ns + int(sd.duration_s(rec.run) * NS_PER_S), said
    for r in result.rows:
        assert r.t_end_ns < lo or r.t_start_ns > hi, ("a verification row made of the gap", r)
        held = set(rec.positions_at([r.t_start_ns, r.t_end_ns]))
        assert held == {r.position}, ("a verification of a position the unit was not in", r.position, held)
    if position.startswith("TP"):
        # a plateau fitted without the position names it missing
        named = {p for m in re.findall(r"missing ((?:TP\d(?:, )?)+)", said) for p in m.split(", ")}
        lacking = [f for f in result.fit.per_plateau if position not in f.positions]
        assert position in named or not lacking, said


# ---------------------------------------------------------------------------------------------------------------
# rates


@pytest.mark.parametrize(
    ("name", "longest_s"), lean([("standard", 60.0), ("short", 30.0), ("sweep", 60.0), ("differential", 60.0)])
)
@PROPERTY
@given(fraction=st.floats(0.0, 1.0))
# the derandomized search draws 0 and ~0 (every 2 s) first: the slowest reading is always tried
@example(fraction=1.0)
def test_the_thermosensor_read_every_2_s_to_a_minute_changes_nothing(name, longest_s, fraction):
    """Read every 2 s to a minute; the short program's unit follows the chamber with a 2-min lag after 5 C/min
    ramps, and readings half a minute apart are as sparse as still resolve it (0.05 C off a straight line between
    readings; a minute apart 0.18 C: calibrate gives the same passport, diagnose sees the rest as a mismatch)."""
    rec = recording(name)
    interval_s = 2.0 + fraction * (longest_s - 2.0)
    check_same(name, [sd.decimate(rec.run, "au_temperature", interval_s)], f"thermosensor every {interval_s:.1f} s")


@pytest.mark.parametrize("name", lean(["standard", "short", "handheld"]))
def test_the_thermosensor_at_10_hz_changes_nothing(name):
    rec = recording(name)
    check_same(name, [sd.interpolate(rec.run, "au_temperature", 10.0)], "thermosensor at 10 Hz")


@pytest.mark.parametrize("name", lean(["standard", "short", "sweep", "handheld", "differential"]))
@PROPERTY
@given(fraction=st.floats(0.0, 1.0))
# halfway: an uneven rate (the short program's 5-Hz samples kept 0.2 and 0.4 s apart at 3.5 Hz)
@example(fraction=0.5)
def test_the_voltmeter_read_slower_changes_nothing(name, fraction):
    """The voltmeter decimated to any rate from the recording's own down to the slowest that holds its poses
    (0.5 Hz for the chamber programs' 5-min holds and hour-long orientations)."""
    rec = recording(name)
    rate = SIMULATED[name][0].rate_hz
    target = rec.min_voltmeter_hz + fraction * (rate - rec.min_voltmeter_hz)
    assume(target < 0.95 * rate)
    check_same(name, [sd.decimate(rec.run, "voltmeter", 1.0 / target)], f"voltmeter at {target:.2f} Hz")


@pytest.mark.parametrize("name", lean(["standard", "short", "sweep", "differential"]))
def test_without_the_chamber_stream_nothing_changes(name):
    check_same(name, [sd.without(recording(name).run, "chamber")], "no chamber stream")


#: where a gap of the composite goes: a free span (:func:`free_spans`) or one of the program's soaks or ramps
GAP_PLACES = ("anywhere", "in a soak", "in a ramp", "at the end of a soak")
#: per recording: the longest gap (s) and the slowest thermosensor reading interval (s) the composite tries
EVERY_KIND = {
    "standard": (7200.0, 60.0),
    "short": (1800.0, 30.0),
    "sweep": (3600.0, 60.0),
    "handheld": (30.0, 60.0),
    "differential": (3600.0, 60.0),
}


def gap_span(rec: Recording, place: str, pick: float, where: float, length_s: float) -> tuple[float, float]:
    """The gap (s from the start) of ``length_s`` at most placed ``place`` (:data:`GAP_PLACES`): in the
    ``pick``-th such span, starting ``where`` through it (at its end for "at the end of a soak"). A program with no
    soak (a sweep, hand-held poses) takes its free spans instead; every span keeps away from every hold."""
    margin_s = 15.0 if rec.name != "handheld" else 0.5
    spans = free_spans(rec, margin_s)
    if place != "anywhere":
        kind = "ramp" if place == "in a ramp" else "soak"
        segs = [(s.t_start_s, s.t_end_s) for s in get_program(rec.program).timetable().segments if s.kind == kind]
        inside = [(max(a, c), min(b, d)) for a, b in spans for c, d in segs if min(b, d) - max(a, c) > 1.0]
        spans = inside or spans
    a, b = spans[min(int(pick * len(spans)), len(spans) - 1)]
    if place == "at the end of a soak":
        return max(a, b - length_s), b
    t0 = a + where * (b - a)
    return t0, min(b, t0 + length_s)


def as_files(runs: list[Run], folder, seed: int, duplicate: bool) -> list[Run]:
    """``runs`` written as Parquet run directories with every stream's rows shuffled (:func:`sd.write_shuffled`)
    and read back as ``calibrate`` reads them; ``duplicate``: the first one given a second time, an exact copy of
    its files under another name."""
    import shutil

    paths = [sd.write_shuffled(r, folder / f"part{k}", seed + k) for k, r in enumerate(runs)]
    if duplicate:
        paths.append(Path(shutil.copytree(paths[0], folder / "copy-of-part0")))
    return [read_run(p) for p in paths]


def every_kind(
    name, folder, *, place, pick, where, length, sensor, fast_sensor, voltmeter, chamber, days, earlier, cuts, order,
    seed, lone
) -> None:  # fmt: skip
    """Every kind of transformation in one recording of the program ``name``, calibrated and diagnosed as the
    reference (:func:`check_same`): a gap of ``length`` of the longest (:data:`EVERY_KIND`) placed ``place``
    (:func:`gap_span`), the thermosensor at 10 Hz (``fast_sensor``) or read every 2 s .. the slowest interval
    (``sensor`` 0..1), the voltmeter at the slowest rate that holds the poses .. its own (``voltmeter`` 0..1), the
    chamber stream kept or not, all times shifted ``days`` (``earlier``: back), the run cut at the fractions ``cuts``
    of its duration into files given in a shuffled order (seed ``order``; -1: reversed), each a Parquet run with its
    rows shuffled (``seed``), and the first file given twice (unless ``lone``)."""
    rec = recording(name)
    longest_s, sensor_s = EVERY_KIND[name]
    t0, t1 = gap_span(rec, place, pick, where, length * longest_s)
    run = sd.gap(rec.run, t0, t1)
    interval_s = 2.0 + sensor * (sensor_s - 2.0)
    run = sd.interpolate(run, "au_temperature", 10.0) if fast_sensor else sd.decimate(run, "au_temperature", interval_s)
    rate = SIMULATED[name][0].rate_hz
    target = rec.min_voltmeter_hz + voltmeter * (rate - rec.min_voltmeter_hz)
    if target < 0.95 * rate:
        run = sd.decimate(run, "voltmeter", 1.0 / target)
    if not chamber:
        run = sd.without(run, "chamber")
    run = sd.shift(run, (-days if earlier else days) * 86400.0)
    d = sd.duration_s(run)
    pieces = sd.split(run, [c * d for c in cuts])
    if order < 0:
        pieces.reverse()
    else:
        random.Random(order).shuffle(pieces)
    runs = as_files(pieces, folder, seed, duplicate=not lone)
    what = (
        f"gap {t0:.0f}..{t1:.0f} s {place}, thermosensor "
        f"{'at 10 Hz' if fast_sensor else f'every {interval_s:.1f} s'}, voltmeter at {min(target, rate):.2f} Hz, "
        f"{'with' if chamber else 'no'} chamber, shifted {-days if earlier else days:.1f} days, "
        f"{len(pieces)} files ({[p.meta.run_id[-2:] for p in pieces]}){'' if lone else ' + a copy'}"
    )
    check_same(name, runs, what)


@pytest.mark.slow
def test_a_differential_cycle_read_once_a_minute_keeps_its_thermal_terms():
    """The composite that found the differential method's chords (issue 21: pick 0.2, where 0.75, length 1/3, sensor
    1, voltmeter 0, +400 days) on the cheapest recording that shows them, the differential program read at 0.5 Hz:
    a 20-min gap at the start of the +70 -> +20 C ramp, the thermosensor read once a minute, no chamber stream,
    +400 days. Every coefficient within 2.5 combined standard uncertainties of the untouched recording's, the same
    model chosen. Before the thermosensor was interpolated with its slope (pipeline.dynamics.hermite) its chords
    moved alpha.x[1] by 3.99 and alpha.z[1] by 3.91 (1.95 and 1.45 since)."""
    config, _ = SIMULATED["differential"]
    run = simulate(dataclasses.replace(config, rate_hz=0.5)).run
    composite = sd.gap(run, 36177.5, 37377.5)
    composite = sd.shift(sd.without(sd.decimate(composite, "au_temperature", 60.0), "chamber"), 400 * 86400.0)
    (ref, ref_method), (result, method) = sd.calibrate_runs([run]), sd.calibrate_runs([composite])
    assert ref_method == method == "differential"
    chosen = [
        {k: p["differential"][k] for k in ("poly_order", "rate_order", "cross_axis")}
        for p in (ref.passport, result.passport)
    ]
    assert chosen[0] == chosen[1], chosen
    diffs = sd.same_passport(ref.passport, result.passport, k_sigma=2.5)
    assert not diffs, [str(d) for d in diffs[:6]]


#: the hard corners every default run tries
CORNERS = {
    # a long gap at the end of a soak (standard: the last 80 min of the -40 C soak; sweep: the last 40 min of the
    # first orientation's warming) with the slowest thermosensor and voltmeter, no chamber stream, 400 days later,
    # 4 files in reverse and a copy
    "slowest": dict(
        place="at the end of a soak", pick=0.2, where=0.0, length=2 / 3, sensor=1.0, fast_sensor=False, voltmeter=0.0,
        chamber=False, days=400.0, earlier=False, cuts=[0.2, 0.45, 0.8], order=-1, seed=1, lone=False,
    ),
    # a long gap inside a ramp with the thermosensor at 10 Hz, the voltmeter at an uneven rate halfway, no chamber
    # stream, 400 days earlier, 3 files in a shuffled order and a copy
    "fastest": dict(
        place="in a ramp", pick=0.5, where=0.3, length=1.0, sensor=0.0, fast_sensor=True, voltmeter=0.5,
        chamber=False, days=400.0, earlier=True, cuts=[0.6, 0.3], order=5, seed=2, lone=False,
    ),
    # the gap in the middle of a soak (differential: the +70 C soak of the second orientation), the thermosensor
    # every 30 s (short: 16 s), the voltmeter at the slowest rate, 5 files in a shuffled order
    "soak": dict(
        place="in a soak", pick=0.25, where=0.4, length=0.5, sensor=0.5, fast_sensor=False, voltmeter=0.0,
        chamber=True, days=37.5, earlier=True, cuts=[0.9, 0.1, 0.5, 0.7], order=11, seed=3, lone=True,
    ),
}  # fmt: skip
#: (recording, corner) tried by default: every corner on the cheap recordings, fewer on the long ones (a
#: calibration and a diagnosis of tens of seconds each); with DEEP every corner on every recording. The
#: differential's "slowest" corner (the whole -40 C soak of its second orientation missing, the thermosensor once a
#: minute, the voltmeter at 0.5 Hz) moved alpha.x[1] and alpha.z[1] by 6-9 combined sigma before fa93c3d and
#: f0afc53 (the thermosensor between readings a Hermite curve, not chords; the simplest model within a standard
#: error); its "fastest" (the thermosensor at 10 Hz: 1.2 million readings) costs three times as much
CORNER_CASES = [
    ("standard", "slowest"),
    ("standard", "fastest"),
    ("sweep", "slowest"),
    ("differential", "slowest"),
    *((n, c) for n in ("short", "handheld") for c in CORNERS),
]
if DEEP:
    CORNER_CASES += [("standard", "soak"), ("sweep", "fastest"), ("sweep", "soak")]
    CORNER_CASES += [("differential", "fastest"), ("differential", "soak")]
#: the recordings the drawn composite is searched on by default (the others with DEEP)
DRAWN = tuple(EVERY_KIND) if DEEP else ("standard", "short", "handheld")


@pytest.mark.parametrize(
    ("name", "corner"), [pytest.param(n, c, marks=() if n in FAST else pytest.mark.slow) for n, c in CORNER_CASES]
)
def test_every_kind_of_transformation_at_the_hard_corners(name, corner, tmp_path):
    """Every program, every kind of transformation in one recording, at the hard corners (:data:`CORNERS`)."""
    every_kind(name, tmp_path, **CORNERS[corner])


@pytest.mark.parametrize("name", [pytest.param(n, marks=() if n in FAST else pytest.mark.slow) for n in DRAWN])
@settings(PROPERTY, max_examples=max(1, EXAMPLES // 2))
@given(
    place=st.sampled_from(GAP_PLACES),
    pick=st.floats(0.0, 1.0),
    where=st.floats(0.0, 1.0),
    length=st.floats(0.05, 1.0),
    sensor=st.floats(0.0, 1.0),
    fast_sensor=st.booleans(),
    voltmeter=st.floats(0.0, 1.0),
    chamber=st.booleans(),
    days=st.floats(1.0, 400.0),
    earlier=st.booleans(),
    cuts=st.lists(st.floats(0.01, 0.99), min_size=1, max_size=4, unique=True),
    order=st.integers(0, 2**16),
    seed=st.integers(0, 2**32 - 1),
    lone=st.booleans(),
)
def test_every_kind_of_transformation_at_once(name, tmp_path_factory, **drawn):
    """Every program, every kind of transformation in one recording (:func:`every_kind`): a gap where no pose is
    held (in a soak, a ramp, a sweep, between poses; up to two hours), the thermosensor read every 2 s .. a minute or
    at 10 Hz, the voltmeter at any rate down to the slowest that holds the poses, the chamber stream left out or not,
    all times shifted by 1..400 days either way, the run split into 2..5 files at any points, given in any order,
    each written with its rows shuffled, one of them given twice. The search's first draw is none of the identities
    already (a gap of a 20th of the longest at the start of the record, every 2 s, the slowest voltmeter, no
    chamber, a day earlier, 2 files, a copy). Each kind alone: the properties below."""
    every_kind(name, tmp_path_factory.mktemp("every-kind"), **drawn)


# ---------------------------------------------------------------------------------------------------------------
# time, order, files


@pytest.mark.parametrize("name", lean(["standard", "short", "sweep", "handheld"]))
@PROPERTY
@given(days=st.floats(-400.0, 400.0))
@example(days=400.0)  # the derandomized search draws 0 and ~0 days first
def test_shifted_times_change_nothing(name, days):
    check_same(name, [sd.shift(recording(name).run, days * 86400.0)], f"shifted {days:.2f} days")


@pytest.mark.parametrize("name", lean(["standard", "handheld"]))
@PROPERTY
@given(seed=st.integers(0, 2**32 - 1))
def test_rows_in_any_order_in_the_files_change_nothing(name, seed, tmp_path_factory):
    """Every stream's rows shuffled in its Parquet file: the reader puts them in time order."""
    path = sd.write_shuffled(recording(name).run, tmp_path_factory.mktemp("shuffled") / "run", seed)
    check_same(name, [read_run(path)], f"rows shuffled ({seed})")


@pytest.mark.parametrize("name", lean(["standard", "handheld"]))
def test_an_exact_duplicate_file_changes_nothing(name, tmp_path):
    run = recording(name).run
    a, b = tmp_path / "a.mcap", tmp_path / "copy.mcap"
    write_run(run, a)
    b.write_bytes(a.read_bytes())
    check_same(name, [read_run(a), read_run(b)], "the file given twice")


@pytest.mark.skipif(not JOINS_FILES, reason="needs the files of one recording joined (issue 21 item 3, inputs)")
@pytest.mark.parametrize("name", lean(["standard", "short", "sweep", "handheld"]))
@PROPERTY
@given(cuts=st.lists(st.floats(0.01, 0.99), min_size=1, max_size=4, unique=True), order=st.randoms())
def test_a_run_split_into_files_at_any_points_in_any_order_changes_nothing(name, cuts, order):
    rec = recording(name)
    d = sd.duration_s(rec.run)
    pieces = sd.split(rec.run, [c * d for c in cuts])
    order.shuffle(pieces)
    check_same(name, pieces, f"split at {[round(c * d) for c in sorted(cuts)]} s")
