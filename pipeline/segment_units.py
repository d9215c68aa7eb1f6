"""Segmentation of a run with several units on one fixture (log-format.md, "Runs with several units"), done once
for the run where it can be and per unit where the signal must decide.

The fixture turns every unit together, so when the units are still and where they move is one question for the
run: each unit's static stretches are found from its own voltages (:func:`pipeline.segment.static_stretches`); the
run's still times are those where a majority of the units are still (a consensus of the units' signals), cut
where the fixture log says the table started moving. Each unit then averages over the still times that are its own
too (its stretches within the consensus), so every unit's segments cover the same holds and a unit that disagrees
only loses what it disagrees on. Per unit, as the signal must decide: the temperature plateaus (its own
thermosensor), the averages and the naming of each position from its own gravity direction
(:func:`pipeline.segment.segment_run`).

A unit whose signal disagrees with the others is named, in one warning line each (in the run's warnings and in the
unit's segmentation): a unit not still in holds where the others are, and a unit naming a position otherwise than
the majority of the units at the same time (a unit mounted turned on the table, a slipped clamp), with the
position and the time.
"""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import polars as pl

from pipeline.positions import MOVING
from pipeline.run import NS_PER_S, Run
from pipeline.segment import Segmentation, SegmentSettings, UnitClock, segment_run, static_stretches, unit_clock

#: threads segmenting units side by side (numpy's passes over the slabs release the GIL)
THREADS = min(2, os.cpu_count() or 1)
#: a unit is "not still" in a hold of the others when it is not still for longer than this many times the shortest
#: static stretch inside it (a window or so at the edges of a hold differs from unit to unit)
_NOT_STILL_MIN = 3.0
#: ... and its voltages move there: the median |step| between samples above this many times the record's own
_MOVING_STEP = 3.0


def segment_units(
    units: dict[str, Run], settings: SegmentSettings = SegmentSettings()
) -> tuple[dict[str, Segmentation], list[str]]:
    """Each unit's :class:`Segmentation`, and the run's warnings naming units that disagree (see the module doc).
    One unit: its own :func:`segment_run`, no consensus. The units' passes over their samples run in
    :data:`THREADS` threads."""
    if len(units) < 2:
        return {s: segment_run(r, settings) for s, r in units.items()}, []
    with ThreadPoolExecutor(THREADS) as pool:
        return _segment_units(units, settings, pool)


def _segment_units(units: dict[str, Run], settings: SegmentSettings, pool) -> tuple[dict, list[str]]:
    clocks = _clocks(units)
    own = dict(zip(units, pool.map(lambda s: static_stretches(units[s], settings, clocks[s]), units)))
    times = {s: clock[0] for s, clock in clocks.items()}
    spans = {s: _spans_ns(times[s], st.stretches) for s, st in own.items()}
    min_ns = int(max(st.settings.static_min_s for st in own.values()) * NS_PER_S)
    present = [_present_ns(clocks[s]) for s in units]
    consensus = _cut_at_moves(_majority(list(spans.values()), present), _fixture_moves_ns(units))
    consensus = consensus[consensus[:, 1] - consensus[:, 0] >= min_ns]
    warnings: list[str] = []

    def unit_segmentation(serial: str) -> Segmentation:
        mine = _intersect(spans[serial], consensus)
        t = times[serial]
        i0 = np.searchsorted(t, mine[:, 0], side="left")
        i1 = np.searchsorted(t, mine[:, 1], side="right")
        keep = (i1 > i0) & (mine[:, 1] - mine[:, 0] >= int(own[serial].settings.static_min_s * NS_PER_S))
        stretches = [(int(a), int(b)) for a, b in zip(i0[keep], i1[keep])]
        return segment_run(units[serial], settings, dataclasses.replace(own[serial], stretches=stretches), unit=serial)

    segs: dict[str, Segmentation] = dict(zip(units, pool.map(unit_segmentation, units)))
    for serial in units:
        line = _not_still(serial, spans[serial], consensus, units[serial], times[serial], _NOT_STILL_MIN * min_ns)
        if line:
            warnings.append(line)
            segs[serial].warnings.append(line)
    for serial, line in _name_disagreements(segs).items():
        warnings.append(line)
        segs[serial].warnings.append(line)
    return segs, warnings


def _clocks(units: dict[str, Run]) -> dict[str, UnitClock]:
    """Each unit's voltmeter times and gaps (:func:`pipeline.segment.unit_clock`): one copy for the units whose
    times are the first unit's (one logger sampling them all together: 47 MB a unit at 100 Hz over the standard
    program, copied and searched for gaps once, and what the segmenter finds from them alone found once), a copy
    of its own for a unit with other times."""
    out: dict[str, UnitClock] = {}
    first: pl.Series | None = None
    for serial, run in units.items():
        col = run.voltmeter["t_ns"]
        if first is not None and _same_times(col, first):
            out[serial] = out[next(iter(out))]
        else:
            out[serial] = unit_clock(run)
            first = col if first is None else first
    return out


def _same_times(a: pl.Series, b: pl.Series) -> bool:
    if len(a) != len(b):
        return False
    return not len(a) or (a[0] == b[0] and a[-1] == b[-1] and a.equals(b))


def _spans_ns(t_ns: np.ndarray, stretches: list[tuple[int, int]]) -> np.ndarray:
    """(k, 2) int64 [first, last] sample times of index stretches."""
    if not stretches:
        return np.zeros((0, 2), dtype=np.int64)
    a = np.array(stretches, dtype=np.int64)
    return np.column_stack((t_ns[a[:, 0]], t_ns[a[:, 1] - 1]))


def _present_ns(clock: UnitClock) -> np.ndarray:
    """(k, 2) int64 [first, last] sample times of a unit's voltmeter between its gaps: where it has samples."""
    t, after = clock[0], np.asarray(clock[1], dtype=np.intp)
    if not t.size:
        return np.zeros((0, 2), dtype=np.int64)
    return np.column_stack((t[np.concatenate(([0], after + 1))], t[np.concatenate((after, [t.size - 1]))]))


def _majority(spans: list[np.ndarray], present: list[np.ndarray]) -> np.ndarray:
    """Time intervals (k, 2) where more than half of the units that have samples then (``present``: each unit's
    (k, 2) times between its gaps) are inside one of their ``spans`` (a sweep over the spans' ends). A unit in a
    gap, or whose record has ended, has no say: the others' holds stay theirs."""
    starts = np.concatenate([s[:, 0] for s in spans])
    ends = np.concatenate([s[:, 1] for s in spans])
    if starts.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    p0 = np.concatenate([p[:, 0] for p in present])
    p1 = np.concatenate([p[:, 1] for p in present])
    t = np.concatenate((starts, ends, p0, p1))
    n, m = starts.size, p0.size
    step = np.concatenate((np.ones(n, np.int64), -np.ones(n, np.int64), np.zeros(2 * m, np.int64)))  # still
    here = np.concatenate((np.zeros(2 * n, np.int64), np.ones(m, np.int64), -np.ones(m, np.int64)))  # sampled
    order = np.argsort(t, kind="stable")
    t, count, units = t[order], np.cumsum(step[order]), np.cumsum(here[order])
    last = np.flatnonzero(np.concatenate((t[1:] != t[:-1], [True])))  # the counts after all of one time's ends
    t, count, units = t[last], count[last], units[last]  # and starts: touching spans stay joined
    inside = count * 2 > units
    rising = np.flatnonzero(inside & ~np.concatenate(([False], inside[:-1])))
    falling = np.flatnonzero(~inside & np.concatenate(([False], inside[:-1])))
    return np.column_stack((t[rising], t[falling])).astype(np.int64)


def _fixture_moves_ns(units: dict[str, Run]) -> np.ndarray:
    """Times the shared fixture log says the table started moving (empty without a log)."""
    fx = next(iter(units.values())).fixture
    if fx is None or fx.height == 0:
        return np.zeros(0, dtype=np.int64)
    return np.sort(fx.filter(fx["position"] == MOVING)["t_ns"].to_numpy())


def _cut_at_moves(spans: np.ndarray, moves_ns: np.ndarray) -> np.ndarray:
    """``spans`` cut where a logged move starts inside one (the log may be late or missing, so it only cuts)."""
    if spans.size == 0 or moves_ns.size == 0:
        return spans
    out = []
    for a, b in spans:
        inner = moves_ns[(moves_ns > a) & (moves_ns < b)]
        edges = np.concatenate(([a], inner, [b]))
        out += [(edges[k], edges[k + 1] - (1 if k + 1 < len(edges) - 1 else 0)) for k in range(len(edges) - 1)]
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def _intersect(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection of two sorted lists of disjoint closed intervals (k, 2)."""
    out = []
    i = j = 0
    while i < len(a) and j < len(b):
        lo, hi = max(a[i, 0], b[j, 0]), min(a[i, 1], b[j, 1])
        if lo <= hi:
            out.append((lo, hi))
        if a[i, 1] < b[j, 1]:
            i += 1
        else:
            j += 1
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def _uncovered_ns(spans: np.ndarray, a: int, b: int) -> np.ndarray:
    """The parts (k, 2) of [a, b] that the sorted disjoint ``spans`` leave uncovered (ns; empty parts included)."""
    inside = spans[(spans[:, 1] >= a) & (spans[:, 0] <= b)]
    edges = np.concatenate(([a], np.clip(inside, a, b).ravel(), [b]))
    return np.column_stack((edges[0::2], edges[1::2]))


def _median_step_v(run: Run, t_ns: np.ndarray, a: int, b: int) -> np.ndarray | None:
    """Per channel, the median |step| between the unit's successive finite samples in [a, b] (V); None with < 3
    there (a sample with a channel not finite is missing data, as a gap is)."""
    i0, i1 = int(np.searchsorted(t_ns, a, side="left")), int(np.searchsorted(t_ns, b, side="right"))
    if i1 - i0 < 3:
        return None
    slab = np.column_stack(run.voltmeter_slab(i0, i1))
    finite = slab[np.isfinite(slab).all(axis=1)]
    if len(finite) < 3:
        return None
    return np.median(np.abs(np.diff(finite, axis=0)), axis=0)


def _moving(run: Run, t_ns: np.ndarray, parts: np.ndarray, still: np.ndarray) -> bool:
    """Whether the unit's voltages move in one of the ``parts`` (k, 2) of a hold: the median |step| between its
    samples there exceeds :data:`_MOVING_STEP` x that in its own ``still`` spans of the hold, on some channel (samples
    there but no still span in the hold: moving). A still unit's drift with its temperature through a ramp, or a
    gap without samples (a hold inside a dropout, the holds after a unit's record ends), is not motion."""
    steps = [m for m in (_median_step_v(run, t_ns, int(x), int(y)) for x, y in parts) if m is not None]
    if not steps:
        return False
    noise = [m for m in (_median_step_v(run, t_ns, int(x), int(y)) for x, y in still) if m is not None]
    if not noise:
        return True
    floor = _MOVING_STEP * np.median(np.array(noise), axis=0)
    return any(bool(np.any(m > floor)) for m in steps)


def _fixture_label_at(run: Run, t_ns: int) -> str | None:
    fx = run.fixture
    if fx is None or fx.height == 0:
        return None
    ft = fx["t_ns"].to_numpy()
    k = int(np.searchsorted(ft, t_ns, side="right")) - 1
    return str(fx["position"][k]) if k >= 0 else None


def _not_still(
    serial: str, mine: np.ndarray, consensus: np.ndarray, run: Run, t: np.ndarray, limit_ns: float
) -> str | None:
    """A line naming ``serial`` when it is not still for longer than ``limit_ns`` within one of the run's still
    times (the others are) and its voltages move there (:func:`_moving`): a still unit's own static stretches may
    end early in a hold through a ramp (its voltages drift with its temperature, a unit with larger thermal
    coefficients sooner than the others), and a gap has no samples. ``t``: the unit's voltmeter times (ns)."""

    def missed_in(a: int, b: int) -> bool:
        parts = _uncovered_ns(mine, a, b)
        parts = parts[parts[:, 1] - parts[:, 0] > limit_ns]
        return bool(parts.size) and _moving(run, t, parts, _intersect(mine, np.array([[a, b]], dtype=np.int64)))

    missed = [(int(a), int(b)) for a, b in consensus if missed_in(int(a), int(b))]
    if not missed:
        return None
    a, b = missed[0]
    label = _fixture_label_at(run, (a + b) // 2)
    where = f" (fixture: {label})" if label and label != MOVING else ""
    return (
        f"unit {serial}: not still in {len(missed)} of the {len(consensus)} holds where the other units are, first "
        f"at t_ns={a}..{b}{where}: its signal disagrees with the others' positions; those holds are left out of it"
    )


def _name_disagreements(segs: dict[str, Segmentation]) -> dict[str, str]:
    """A line per unit that names a position otherwise than a majority of the units holding one at the same time
    (the middle of its segment; the unit itself counted among them), with its first such position and time."""
    spans = {
        s: np.array([(g.t_start_ns, g.t_end_ns) for g in seg.segments], dtype=np.int64).reshape(-1, 2)
        for s, seg in segs.items()
    }
    named = {s: np.array([g.position for g in seg.segments], dtype=object) for s, seg in segs.items()}
    mids = {s: (v[:, 0] + v[:, 1]) // 2 for s, v in spans.items()}
    has_name = {s: np.array([x is not None for x in v], dtype=bool) for s, v in named.items()}
    out: dict[str, str] = {}
    for serial, seg in segs.items():
        # the positions the other units hold at each segment's middle: (segment, name) pairs, all units at once
        mine, theirs_at = mids[serial], []
        for other in segs:
            if other == serial or not len(mids[other]):
                continue
            k = np.searchsorted(mids[other], mine)
            for j in (k - 1, k):
                ok = (j >= 0) & (j < len(mids[other]))
                jj = np.where(ok, j, 0)
                h = spans[other][jj]
                ok &= (h[:, 0] <= mine) & (mine <= h[:, 1])
                ok &= has_name[other][jj]
                theirs_at.append((np.flatnonzero(ok), named[other][jj[ok]]))
        at = np.concatenate([i for i, _ in theirs_at]) if theirs_at else np.zeros(0, dtype=np.intp)
        held = np.concatenate([n for _, n in theirs_at]) if theirs_at else np.zeros(0, dtype=object)
        first, count = None, 0
        for i, g in enumerate(seg.segments):
            if g.position is None:
                continue
            names = held[at == i]
            if not names.size:
                continue
            values, counts = np.unique(names, return_counts=True)
            top = values[np.argmax(counts)]
            # a majority of all the units holding a position then, this one included (one other unit, turned or
            # in a gap of the rest, is no majority)
            if counts.max() * 2 > names.size + 1 and top != g.position:
                count += 1
                if first is None:
                    first = (g.position, top, g.t_start_ns, g.t_end_ns)
        if first is not None:
            pos, theirs, a, b = first
            out[serial] = (
                f"unit {serial}: its signal names {count} of its {len(seg.segments)} positions otherwise than the "
                f"other units, first {pos} at t_ns={a}..{b} where they hold {theirs}: mounted turned on the "
                "fixture, or a slipped clamp? (its own naming is used)"
            )
    return out
