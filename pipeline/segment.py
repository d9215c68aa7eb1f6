"""Temperature plateaus and named static positions, found from the data of one chamber run.

A chamber run (docs/physics.md) alternates temperature ramps and soaks; on each soaked plateau the tilt fixture
holds the unit in a sequence of positions. This module finds both from the recorded signals, not from a timetable:

- plateaus from the AU thermosensor: the local regression slope of the temperature stays below
  ``plateau_rate_c_per_min`` for at least ``plateau_min_s`` and the temperature stays within ``plateau_band_c`` of
  the plateau's median (a run whose temperature is stable throughout is one plateau, however short); before each,
  its settling (the unit still approaching the plateau after a short soak: slope below ``settle_rate_c_per_min``,
  within ``settle_band_c``): positions held there belong to the plateau, each at its own temperature, where the
  stable part lacks them;
- static stretches from the voltages: the standard deviation of each channel over ``static_window_s`` stays below a
  threshold set by the run's own noise floor (a multiple of a low quantile of that rolling standard deviation);
- each static stretch is cut at plateau boundaries (the unit stays in its last position through ramps and soaks),
  trimmed of the settling after a move, averaged, and named: from the fixture log where it agrees with the direction
  of gravity seen in the signal, otherwise from that direction alone.

Everything is in time, not samples, for any stream rate (the thermosensor read once a minute to ten times a
second, the voltmeter at 0.5 Hz to kHz): the static window and the shortest segment widen to hold enough samples
(:func:`for_rate`), the plateau slope window to keep its noise (:func:`slope_window_s`), and durations are of
data (:func:`data_clock_s`). A gap is missing data (:func:`gap_indices`: an interval a window cannot see across):
no static stretch or segment spans a gap of the voltmeter, none holds samples inside a gap of the thermosensor
(their temperature is unknown), a fixture label logged before a gap names nothing after it that the signal
contradicts, and a plateau whose soak has a gap is the data on both sides (its ``gaps`` listed, a warning saying
which plateau lacks data when); soaks too short for the unit ever to be stable are plateaus all the same where
the temperature slows down as an approach does (:func:`find_plateaus`).

Voltage statistics use short time blocks (``static_window_s / 10``), each reduced exactly (two-pass mean and
squared deviations, no cumulative sums that lose precision on long runs), and combined into rolling windows with
the parallel-variance formula. All passes over the samples are vectorised and read the voltages a slab of about
1 M samples at a time from the run's table (:class:`Channels`): besides the table, segmenting a run holds its
times (8 bytes per sample) and a few masks (1 byte per sample), not a copy of the voltages.
"""

from __future__ import annotations

import bisect
import dataclasses
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import polars as pl

from pipeline.io.checks import gap_indices as reader_gap_indices
from pipeline.model import vector3
from pipeline.positions import (
    ALL_POSITIONS,
    TEST_POSITIONS,
    gravity_vector_g,
    nearest_position,
)
from pipeline.run import NS_PER_S as _NS
from pipeline.run import SLAB_SAMPLES as _SLAB_SAMPLES
from pipeline.run import Run, slab_of
from pipeline.settling import HoldMoments, Settling, hold_moments, settling_fit

#: blocks per static window (the time resolution of static detection is static_window_s / this)
_BLOCKS_PER_WINDOW = 10
#: the static threshold is this multiple of the low quantile below of the rolling standard deviation
_NOISE_MULTIPLE = 4.0
_NOISE_QUANTILE = 0.05
#: absolute floor of the static threshold, relative to the signal's spread (noise-free runs)
_NOISE_FLOOR_REL = 1e-5
#: the plateau slope is a local linear regression over this fraction of plateau_min_s
_SLOPE_WINDOW_FRACTION = 0.25
#: smallest tolerance (C) of the plateau end refinement (noise-free thermosensor)
_PLATEAU_TOL_FLOOR_C = 1e-3
#: at most this fraction of a segment is trimmed at its start, and this fraction at its end
_MAX_START_TRIM = 0.25
_MAX_END_TRIM = 0.05
#: pairs of test positions with opposite gravity, by the axis that is vertical in them (+ first)
_OPPOSITE_TP = {0: ("TP6", "TP5"), 1: ("TP4", "TP2"), 2: ("TP1", "TP3")}
#: how the warning of a run without any temperature plateau begins (a method for ramps leaves it out)
NO_PLATEAU_WARNING = "au_temperature: no temperature plateau found"


@dataclass(frozen=True)
class SegmentSettings:
    """Thresholds of plateau and static-position detection."""

    plateau_rate_c_per_min: float = 0.02  # |dT/dt| below this (smoothed) counts as stable
    plateau_min_s: float = 300.0  # a plateau lasts at least this long (unless the whole run is stable)
    plateau_band_c: float = 0.5  # ... and stays within this band around its median
    settle_rate_c_per_min: float = 0.3  # before a plateau, the unit still settling towards it: |dT/dt| below
    settle_band_c: float = 3.0  # ... this and within this of the plateau's temperature
    static_window_s: float = 2.0  # rolling window for voltage statistics
    static_min_s: float = 3.0  # shortest static segment kept
    settle_trim_s: float = 10.0  # trimmed from the start of each static segment (1/10 of it from the end),
    # never more than 25 % (start) + 5 % (end) of a segment
    max_label_angle_deg: float = 15.0  # a gravity direction further than this from every position: unnamed


@dataclass(frozen=True)
class Plateau:
    """A stretch of stable AU temperature: first and last thermosensor sample times, mean and std (C)."""

    index: int
    t_start_ns: int
    t_end_ns: int
    temp_c: float
    temp_std_c: float
    #: start of the settling before the stable part (the unit still approaching the plateau's temperature)
    settle_start_ns: int | None = None
    #: the thermosensor's gaps inside the plateau (:func:`gap_spans`), (last sample before, first after) in ns: a
    #: soak whose two sides are stable at one temperature is one plateau, but nothing is known (no segment is
    #: made) in between
    gaps: tuple[tuple[int, int], ...] = ()

    @property
    def duration_s(self) -> float:
        return (self.t_end_ns - self.t_start_ns) / _NS

    @property
    def missing_s(self) -> float:
        """Time (s) of the plateau without thermosensor data (its gaps)."""
        return sum(b - a for a, b in self.gaps) / _NS

    @property
    def covered_s(self) -> float:
        """Time (s) of the plateau with thermosensor data: its duration less its gaps."""
        return self.duration_s - self.missing_s


@dataclass(frozen=True)
class StaticSegment:
    """One static segment (after trimming), its name and its averages.

    ``position`` is TP1..TP6 / VP1..VP6 or None; ``label_source`` says where the name came from (``fixture``,
    ``gravity`` or ``none``); ``fixture_label`` is the position the fixture log gave for the segment's middle (None
    if no log or MOVING); ``label_conflict`` is True where that label disagrees with the signal (then the name comes
    from gravity). ``plateau`` is the index of the plateau the segment lies on, None on a ramp. ``mean_v``,
    ``std_v`` and ``count`` are over the finite voltmeter samples of the segment (V); ``temp_c`` and ``temp_std_c``
    the AU temperature interpolated at those samples (C); ``direction_g`` the rough unit gravity vector (AU axes)
    used for naming (NaN when it cannot be estimated). ``settling`` is the plateau a segment off every plateau
    begins in the settling of (None otherwise): a hold begun while the unit still settled is one segment, even
    where it goes on into the stable part.
    """

    index: int
    t_start_ns: int
    t_end_ns: int
    position: str | None
    label_source: str
    fixture_label: str | None
    label_conflict: bool
    plateau: int | None
    mean_v: tuple[float, float, float]
    std_v: tuple[float, float, float]
    count: int
    temp_c: float
    temp_std_c: float
    direction_g: tuple[float, float, float]
    settling: int | None = None
    #: the index of the segment this one continues across a gap (:func:`_continued_holds`: the same hold in two
    #: pieces separated only by missing data; one observation is made of both), None otherwise
    continues: int | None = None
    #: the standard error (C) of ``temp_c`` from the thermosensor's white noise (:func:`thermosensor_noise_c`)
    #: through the interpolation onto the segment's samples: 0.01 C over 50 readings is 0.0014 C, over the one or two
    #: readings of a thermosensor read once a minute up to 0.01 C (:func:`interpolated_mean_weight2`)
    temp_sigma_c: float = 0.0

    @property
    def duration_s(self) -> float:
        return (self.t_end_ns - self.t_start_ns) / _NS


@dataclass
class Segmentation:
    """Plateaus and static segments of one run, and one warning line per thing worth telling the user."""

    plateaus: list[Plateau]
    segments: list[StaticSegment]
    warnings: list[str] = field(default_factory=list)
    #: the untrimmed static stretches (:func:`find_static`) as voltmeter sample index ranges [i0, i1), in the
    #: time-sorted order of the samples (the table's order when it is in time order)
    stretches: list[tuple[int, int]] = field(default_factory=list)
    #: the static window (s) and shortest static stretch (s) the recording was segmented with (they adapt to the
    #: rate and to the length of the poses)
    static_window_s: float | None = None
    static_min_s: float | None = None
    #: the static window (s) and shortest stretch (s) of the most lenient static detection tried at this rate
    #: (:func:`_lenient_static`): a hold shorter than their sum leaves no static stretch (:func:`short_holds`)
    lenient_static_s: tuple[float, float] | None = None
    #: the gaps no segment spans, by stream (``voltmeter``, ``au_temperature``): (last sample before, first after)
    #: in ns (:func:`gap_spans`: longer than half the static window, and than half the plateau slope window)
    gaps_ns: dict[str, list[tuple[int, int]]] = field(default_factory=dict)
    #: the readings' resolution per channel (V, :func:`reading_resolution`): the step below which a recorded value
    #: says nothing, and so a floor of every mean's uncertainty
    resolution_v: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: the creep after each move taken out of the segments' means (:func:`pipeline.settling.settling_fit`, its holds
    #: the segments by index), None where none was: what a method averaging its own stretches of the samples takes
    #: out too (:func:`pipeline.calibrate.ramp.cut_pieces`)
    settling: Settling | None = None

    def on_plateau(self, i: int) -> list[StaticSegment]:
        """Segments on plateau ``i``, in time order."""
        return [s for s in self.segments if s.plateau == i]

    def on_ramps(self) -> list[StaticSegment]:
        """Segments off every plateau (ramps, early soaks)."""
        return [s for s in self.segments if s.plateau is None]

    def named(self, position: str) -> list[StaticSegment]:
        """Segments named ``position``, in time order."""
        return [s for s in self.segments if s.position == position]


# ---------------------------------------------------------------------------------------------------------------
# plateaus


def find_plateaus(t_ns: np.ndarray, temp_c: np.ndarray, settings: SegmentSettings = SegmentSettings()) -> list[Plateau]:
    """Plateaus of the AU temperature ``temp_c`` (C) sampled at ``t_ns``; non-finite samples are ignored.

    The slope is a local linear regression over :func:`slope_window_s` (``plateau_min_s / 4``, longer for a sparse
    or noisy thermosensor) centred on each sample; within half a window of the record's ends, where that window
    is cut to a half, the slower of the half window's slope and the slope over the record's first (last) whole
    window (the half window alone is 2.8 times noisier: a flat 0.02-C record read once a second was a plateau in
    37 of 40 seeds at 290-299 s, under the whole-record rule for records shorter than ``plateau_min_s``, and in 13
    at 301 s, 27 at 310 s; the slower of the two keeps a record still approaching its plateau at its end, which
    the half window sees slow down, as it was). Stable samples (|slope| below ``plateau_rate_c_per_min``) form
    runs; a run lasting ``plateau_min_s`` (or the whole record) is kept, restricted to the samples within
    ``plateau_band_c`` of its median, and split where they are not; runs less than that window apart that stay
    within the band together are one plateau (the slope rose over the threshold for a moment between them); its
    ends are then moved out to where the temperature leaves its value by more than the sensor noise.

    Durations are of data: the thermosensor's gaps (:func:`gap_spans`) do not count towards a plateau's length nor
    towards the distance between two runs. A soak whose both sides of a gap are stable at one temperature is one
    plateau (its ``gaps`` list the missing spans); a gap has no slope, so no stable run is made of one.

    A soak too short for the unit ever to be stable (its temperature still approaching the setpoint when the
    program moves on) is a plateau where the temperature slows down as an approach does (:func:`_approaches`).
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    temp_c = np.asarray(temp_c, dtype=np.float64)
    ok = np.isfinite(temp_c)
    t_ns, temp_c = t_ns[ok], temp_c[ok]
    if t_ns.size == 0:
        return []
    t_s = (t_ns - t_ns[0]) / _NS
    window_s = slope_window_s(t_ns, settings)
    after = gap_indices(t_ns, window_s / 2)
    clock_s = data_clock_s(t_ns, after)
    record_s = float(clock_s[-1])
    # within half a window of the record's ends, the slope over the half window left there, or over the record's
    # first (last) whole window where that one is slower (:func:`_local_slope_c_per_s`)
    rate_c_per_min = (
        np.minimum(
            np.abs(_local_slope_c_per_s(t_s, temp_c, window_s)),
            np.abs(_local_slope_c_per_s(t_s, temp_c, window_s, whole=True)),
        )
        * 60.0
    )
    stable = _bridge_flicker(rate_c_per_min, clock_s, window_s, settings)
    min_s = min(settings.plateau_min_s, record_s)
    found: list[tuple[int, int]] = []
    for i0, i1 in _pieces_of_soaks(split_runs(_runs(stable), after + 1), after, clock_s, temp_c, settings, window_s):
        if clock_s[i1 - 1] - clock_s[i0] < min_s:
            continue
        seg = temp_c[i0:i1]
        in_band = np.abs(seg - np.median(seg)) <= settings.plateau_band_c
        found += [(i0 + j0, i0 + j1) for j0, j1 in _runs(in_band) if clock_s[i0 + j1 - 1] - clock_s[i0 + j0] >= min_s]
    if not found and _short_record_stable(t_s, temp_c, record_s, settings, stable, window_s):
        found = [(0, temp_c.size)]
    found = _join_interrupted(found, clock_s, temp_c, settings, window_s)
    found = sorted(found + _approaches(rate_c_per_min, clock_s, temp_c, found, settings))
    out: list[Plateau] = []
    for k, (a, b) in enumerate(found):
        lo = found[k - 1][1] if k > 0 else 0
        hi = found[k + 1][0] if k + 1 < len(found) else temp_c.size
        a, b = _extend_plateau(t_s, temp_c, a, b, lo, hi, window_s)
        mean_c = float(np.mean(temp_c[a:b]))
        settling = (
            (rate_c_per_min[lo:a] < settings.settle_rate_c_per_min)
            & (np.abs(temp_c[lo:a] - mean_c) < settings.settle_band_c)
        )[::-1]
        n_settle = int(np.argmin(settling)) if not settling.all() else settling.size
        if out:  # the settling starts after the previous plateau (whose end moved out)
            n_settle = min(n_settle, max(0, a - int(np.searchsorted(t_ns, out[-1].t_end_ns, side="right"))))
        inside = after[(after >= a) & (after < b - 1)]
        out.append(
            Plateau(
                k,
                int(t_ns[a]),
                int(t_ns[b - 1]),
                mean_c,
                float(np.std(temp_c[a:b])),
                int(t_ns[a - n_settle]) if n_settle > 0 else None,
                tuple((int(t_ns[i]), int(t_ns[i + 1])) for i in inside),
            )
        )
    return out


def _short_record_stable(
    t_s: np.ndarray,
    temp_c: np.ndarray,
    record_s: float,
    settings: SegmentSettings,
    stable: np.ndarray,
    window_s: float,
) -> bool:
    """A record shorter than ``plateau_min_s`` (a hand-turned recording of a few minutes) is one plateau when its
    temperature's slope over the whole record (one least-squares line, s) is below ``plateau_rate_c_per_min``,
    every reading lies within ``plateau_band_c`` of the median, and every sample whose slope window (``window_s``,
    s) lies wholly inside the record is ``stable`` (its local slope below the threshold). The local slopes of
    :func:`find_plateaus` ask each sample to be stable over ``slope_window_s``, and at the record's ends that window
    is one-sided: its slope is noisier there (a 160-s record at 20.00 +- 0.01 C read once a second crossed
    0.02 C/min at its last samples, so no stable run spanned the record and the recording had no plateau). Inside
    the record the local slopes still rule: the one line's slope alone is blind to a dip and return (a 240-s record
    falling 0.4 C and back at up to 0.3 C/min has a whole-record slope near 0)."""
    if record_s >= settings.plateau_min_s or temp_c.size < MIN_SLOPE_SAMPLES:
        return False
    inside = (t_s >= t_s[0] + window_s / 2) & (t_s <= t_s[-1] - window_s / 2)
    if not np.all(stable[inside]):
        return False
    slope_c_per_min = abs(float(_local_slope_c_per_s(t_s, temp_c, 4.0 * (t_s[-1] - t_s[0]) + 1.0)[0])) * 60.0
    return slope_c_per_min < settings.plateau_rate_c_per_min and bool(
        np.all(np.abs(temp_c - np.median(temp_c)) <= settings.plateau_band_c)
    )


#: the plateau slope window holds at least this many thermosensor samples
MIN_SLOPE_SAMPLES = 5
#: the thermosensor interval (s) the default slope window was made for
_SLOPE_REFERENCE_S = 1.0


def slope_window_s(t_ns, settings: SegmentSettings = SegmentSettings()) -> float:
    """The window (s) of the plateau test's local slope for a thermosensor sampled at ``t_ns`` (sorted, ns):
    ``plateau_min_s / 4`` (75 s) for a sensor read every second or faster; a sparser one gets a window as much
    longer as keeps the slope's noise what it is at 1 s (the slope of samples h apart over a window L has a
    standard deviation proportional to sqrt(h / L^3): L grows as h^(1/3)), and at least
    :data:`MIN_SLOPE_SAMPLES` samples. A sensor read every 5 s gets 128 s, every 10 s 162 s, every minute 293
    s."""
    base = settings.plateau_min_s * _SLOPE_WINDOW_FRACTION
    if len(t_ns) < 3:
        return base
    h_s = median_interval_ns(t_ns) / _NS
    if not h_s > 0:
        return base
    return float(max(base, base * (h_s / _SLOPE_REFERENCE_S) ** (1.0 / 3.0), MIN_SLOPE_SAMPLES * h_s))


def gap_indices(t_ns, min_gap_s: float, readers: np.ndarray | None = None) -> np.ndarray:
    """Indices ``i`` of the sorted times ``t_ns`` (ns) after which comes a gap the segmenter does not look across:
    ``t_ns[i + 1] - t_ns[i]`` longer than ``min_gap_s`` and than the readers' gap (``GAP_FACTOR`` median
    intervals, :func:`pipeline.io.checks.gap_indices`: every gap cut here is one ``inspect`` lists). ``readers``:
    the readers' gaps of ``t_ns`` when already found (a pass over every interval)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if t_ns.size < 2:
        return np.empty(0, dtype=np.intp)
    readers = reader_gap_indices(t_ns) if readers is None else readers
    if not readers.size:
        return readers
    return readers[t_ns[readers + 1] - t_ns[readers] > np.int64(min_gap_s * _NS)]


def thermosensor_gaps(t_ns, settings: SegmentSettings = SegmentSettings(), within=None) -> np.ndarray:
    """The thermosensor's gaps (:func:`gap_spans`, (k, 2) ns) for the segmenter: intervals longer than half the
    plateau test's slope window (:func:`slope_window_s`), across which neither the slope nor a sample's temperature
    is known. ``t_ns``: the sorted times of the finite samples. ``within`` (first, last ns of another stream, e.g.
    the voltmeter): also the spans of it before the first reading and after the last (no temperature there either:
    the readings are interpolated, never extrapolated), as (first - 1, first reading) and (last reading, last + 1).
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    gaps = gap_spans(t_ns, slope_window_s(t_ns, settings) / 2)
    if within is None or not t_ns.size:
        return gaps
    first, last = int(within[0]), int(within[1])
    edges = []
    if t_ns[0] > first:
        edges.append((first - 1, int(t_ns[0])))
    if t_ns[-1] < last:
        edges.append((int(t_ns[-1]), last + 1))
    if not edges:
        return gaps
    out = np.concatenate([gaps, np.array(edges, dtype=np.int64)])
    return out[np.argsort(out[:, 0], kind="stable")]


def gap_spans(t_ns, min_gap_s: float, readers: np.ndarray | None = None) -> np.ndarray:
    """The gaps of :func:`gap_indices` as (k, 2) int64 ns: the last sample before and the first after each."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    i = gap_indices(t_ns, min_gap_s, readers)
    return np.column_stack((t_ns[i], t_ns[i + 1])) if i.size else np.zeros((0, 2), dtype=np.int64)


def data_clock_s(t_ns: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Time (s) since the first sample of ``t_ns`` (sorted, ns) counted over data only: each gap after the
    indices ``after`` counts as one median interval. Durations and distances of the segmenter are read on it."""
    t_s = (np.asarray(t_ns, dtype=np.int64) - t_ns[0]) / _NS
    if not after.size:
        return t_s
    step_s = median_interval_ns(t_ns) / _NS
    lost = np.zeros(t_s.size)
    lost[after + 1] = (t_s[after + 1] - t_s[after]) - step_s
    return t_s - np.cumsum(lost)


def _pieces_of_soaks(
    runs: np.ndarray,
    after: np.ndarray,
    clock_s: np.ndarray,
    temp_c: np.ndarray,
    settings: SegmentSettings,
    window_s: float,
) -> list[tuple[int, int]]:
    """Stable runs ([i0, i1), cut at the thermosensor's gaps, the gaps after the indices ``after``) with the runs
    either side of a gap joined where less than a slope window of data (``window_s`` on ``clock_s``: the slope
    beside a gap sees one side only, and flickers) separates them and the temperature on both stays within
    ``plateau_band_c`` of their median: one soak with missing data, not two (nor a run from one soak into the next
    soak at another temperature)."""
    out: list[tuple[int, int]] = []
    for a, b in runs:
        if out:
            a0, b0 = out[-1]
            across = np.any((after >= b0 - 1) & (after < a))
            if across and clock_s[a] - clock_s[b0 - 1] < window_s:
                span = temp_c[a0:b]
                if np.max(np.abs(span - np.median(span))) <= settings.plateau_band_c:
                    out[-1] = (a0, int(b))
                    continue
        out.append((int(a), int(b)))
    return out


def _approaches(
    rate_c_per_min: np.ndarray,
    clock_s: np.ndarray,
    temp_c: np.ndarray,
    found: list[tuple[int, int]],
    settings: SegmentSettings,
) -> list[tuple[int, int]]:
    """Soaks too short for the unit ever to be stable: [i0, i1) runs of samples settling towards one temperature
    (|slope| below ``settle_rate_c_per_min``, within ``settle_band_c`` of where the run ends) that last
    ``plateau_min_s`` of data, hold no stable plateau, and slow down as an approach does: the slope in their first
    quarter is over :data:`_APPROACH_SLOWING` times the slope in their last, one sign throughout (a turn of the
    temperature with no soak slows down less). A drift slows down
    no such way. The positions held there are each at their own temperature (as in a plateau's settling).

    With 20-min soaks and 120-s holds after 1 C/min ramps (a 10-min case lag) the unit ends its 34 minutes at a
    setpoint still 0.4 C away and moving at 0.04 C/min, twice the plateau threshold."""
    settling = rate_c_per_min < settings.settle_rate_c_per_min
    out = []
    for i0, i1 in _runs(settling):
        if i1 - i0 < 8 or any(a < i1 and b > i0 for a, b in found):
            continue
        # the approach ends where the temperature moves slowest (the next ramp begins)
        i1 = i0 + 1 + int(np.argmin(rate_c_per_min[i0:i1]))
        near = np.abs(temp_c[i0:i1] - temp_c[i1 - 1]) < settings.settle_band_c
        i0 += int(np.argmax(near))
        if i1 - i0 < 8 or clock_s[i1 - 1] - clock_s[i0] < settings.plateau_min_s:
            continue
        q = max((i1 - i0) // 4, 2)
        t, y = clock_s[i0:i1], temp_c[i0:i1]
        first = np.polyfit(t[:q], y[:q], 1)[0]
        last = np.polyfit(t[-q:], y[-q:], 1)[0]
        if first * last > 0 and abs(first) > _APPROACH_SLOWING * abs(last):
            out.append((i0, i1))
    return out


#: an approach to a soak slows down by more than this factor from its first quarter to its last. A 20-min soak
#: after 1 C/min ramps: 4.7 to 5.4; 10-min soaks after slower ramps: 9; no soak at all (the fast program turning
#: at +70 and -40 C, the unit 300 s behind, its temperature slowest where it turns): 3.1
_APPROACH_SLOWING = 4.0


#: a stable run ends a soak's approach when the slope one approach time before it was this many times the threshold
_APPROACH_FACTOR = 3.0


def _bridge_flicker(
    rate_c_per_min: np.ndarray, t_s: np.ndarray, window_s: float, settings: SegmentSettings
) -> np.ndarray:
    """Stable samples (|slope| under ``plateau_rate_c_per_min``), with the gaps of less than a slope window
    between stable runs filled where the runs end an approach: at the end of a short soak the slope hovers about
    the threshold and noise cuts the unit's last approach into runs of a minute or two, none long enough alone.
    An approach is told from a slow drift (which hovers about the threshold for hours) by the slope
    2 ``plateau_min_s`` before the first run: over ``_APPROACH_FACTOR`` times the threshold (an exponential
    approach with a time constant of 10 min is 2.7 times faster 10 min earlier; a drift is as slow), and by
    its runs all being short (a group holding a run of ``plateau_min_s`` is a plateau, or a drift's piece,
    already)."""
    stable = rate_c_per_min < settings.plateau_rate_c_per_min
    runs = _runs(stable)
    if len(runs) < 2:
        return stable
    out = stable.copy()
    gap_s = t_s[runs[1:, 0]] - t_s[runs[:-1, 1] - 1]
    long_run = t_s[runs[:, 1] - 1] - t_s[runs[:, 0]] >= settings.plateau_min_s
    # groups of runs less than a window apart
    cut = np.concatenate(([0], np.flatnonzero(gap_s >= window_s) + 1, [len(runs)]))
    for g0, g1 in zip(cut[:-1], cut[1:]):
        if g1 - g0 < 2 or long_run[g0:g1].any():
            continue
        before = int(np.searchsorted(t_s, t_s[runs[g0, 0]] - 2 * settings.plateau_min_s, side="left"))
        if rate_c_per_min[before] > _APPROACH_FACTOR * settings.plateau_rate_c_per_min:
            out[runs[g0, 0] : runs[g1 - 1, 1]] = True
    return out


def _join_interrupted(
    found: list[tuple[int, int]], t_s: np.ndarray, temp_c: np.ndarray, settings: SegmentSettings, window_s: float
) -> list[tuple[int, int]]:
    """Join consecutive stable runs [a, b) less than one slope window (``window_s``) apart when all the samples
    from the first's start to the second's end stay within ``plateau_band_c`` of their median: one soak whose
    slope rose over the plateau threshold for a moment (the unit's last approach to the chamber's temperature),
    not two plateaus. A drift (a chain of plateaus a band apart, or minutes apart) is not joined."""
    out: list[tuple[int, int]] = []
    for a, b in found:
        if out:
            a0, b0 = out[-1]
            span = temp_c[a0:b]
            if t_s[a] - t_s[b0 - 1] < window_s and np.max(np.abs(span - np.median(span))) <= settings.plateau_band_c:
                out[-1] = (a0, b)
                continue
        out.append((a, b))
    return out


def _extend_plateau(
    t_s: np.ndarray, temp_c: np.ndarray, a: int, b: int, lo: int, hi: int, window_s: float
) -> tuple[int, int]:
    """Move a plateau's ends [a, b) outwards (not past lo / hi) while the temperature stays within the noise of
    the plateau's value at that end.

    The centred slope window sees a ramp before it begins, so stable runs end up to half a window early (and start
    late); the true ends are where the temperature leaves the plateau's value by more than its noise (4 sigma of
    the sample-to-sample scatter, at least 1 mC).
    """
    noise = float(np.std(np.diff(temp_c[a:b]))) / np.sqrt(2.0) if b - a > 2 else 0.0
    tol = max(4.0 * noise, _PLATEAU_TOL_FLOOR_C)
    head = temp_c[a : np.searchsorted(t_s, t_s[a] + window_s / 2, side="right")].mean()
    tail = temp_c[np.searchsorted(t_s, t_s[b - 1] - window_s / 2, side="left") : b].mean()
    after = np.abs(temp_c[b:hi] - tail) > tol
    b = b + (int(np.argmax(after)) if after.any() else after.size)
    before = np.abs(temp_c[lo:a][::-1] - head) > tol
    a = a - (int(np.argmax(before)) if before.any() else before.size)
    return a, b


def _local_slope_c_per_s(t_s: np.ndarray, y: np.ndarray, window_s: float, whole: bool = False) -> np.ndarray:
    """Least-squares slope of y(t) (per s of ``t_s``) over the samples within ``window_s / 2`` (s) of each sample
    (one-sided at the record's ends). ``whole``: every slope over a whole window: within ``window_s / 2`` of the
    record's first (last) sample the window is the record's first (last) ``window_s`` (the whole record when it is
    shorter), not a half window, whose slope is 2.8 times noisier (the noise of a slope goes as the window's length
    to the power -3/2)."""
    centre = t_s
    if whole and t_s.size:
        first, last = float(t_s[0]), float(t_s[-1])
        edge = min(window_s / 2, (last - first) / 2)
        centre = np.clip(t_s, first + edge, last - edge)
    lo = np.searchsorted(t_s, centre - window_s / 2, side="left")
    hi = np.searchsorted(t_s, centre + window_s / 2, side="right")
    x = t_s - t_s[t_s.size // 2]
    yc = y - np.median(y)

    def wsum(v):
        c = np.concatenate(([0.0], np.cumsum(v)))
        return c[hi] - c[lo]

    n = (hi - lo).astype(np.float64)
    sx, sy, sxx, sxy = wsum(x), wsum(yc), wsum(x * x), wsum(x * yc)
    var = sxx - sx * sx / n
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = (sxy - sx * sy / n) / var
    return np.where(var > 0, slope, 0.0)


@dataclass(frozen=True)
class TemperatureProgram:
    """What the AU temperature did over a run: ``kind`` is ``plateaus`` (soaks separated by ramps), ``sweep`` (a
    continuous drift or ramp that never holds: docs/physics.md, "Real recordings") or ``constant`` (one temperature
    throughout). ``range_c`` (lo, hi) C; ``max_rate_c_per_h`` the largest rate of the temperature smoothed over
    ``rate_window_s``; ``plateaus`` the plateaus that are soaks (found plateaus chained into a drift are not);
    ``drift_s`` the time spent in such chains."""

    kind: str
    range_c: tuple[float, float]
    max_rate_c_per_h: float
    plateaus: tuple[Plateau, ...]
    drift_s: float
    rate_window_s: float


#: a temperature range below this (C) is one temperature, however long the record
_CONSTANT_RANGE_C = 1.0
#: a run that soaks for less than this fraction of its length is a sweep (the standard program: about half)
_SOAK_FRACTION = 0.2
#: the largest rate is of the temperature smoothed over this long (s)
_RATE_WINDOW_S = 600.0


def classify_temperature(
    t_ns: np.ndarray, temp_c: np.ndarray, plateaus: list[Plateau], settings: SegmentSettings = SegmentSettings()
) -> TemperatureProgram:
    """Plateau program, sweep or constant temperature, from the thermosensor (``t_ns``, ``temp_c`` in C) and the
    plateaus :func:`find_plateaus` found in it.

    A slow drift passes the plateau test piecewise: the temperature stays within ``plateau_band_c`` for
    ``plateau_min_s`` again and again, giving a chain of "plateaus" each starting where (or before) the last one
    ended and a band away from it. Plateaus chained like that (less than ``plateau_min_s`` apart and less than two
    bands apart in temperature) are a drift, not soaks. The run is a sweep when it soaks for less than a fifth of
    its length and its temperature spans more than 1 C.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    temp_c = np.asarray(temp_c, dtype=np.float64)
    ok = np.isfinite(temp_c)
    t_ns, temp_c = t_ns[ok], temp_c[ok]
    if temp_c.size == 0:
        return TemperatureProgram("constant", (float("nan"), float("nan")), 0.0, tuple(plateaus), 0.0, _RATE_WINDOW_S)
    t_s = (t_ns - t_ns[0]) / _NS
    rate = np.abs(_local_slope_c_per_s(t_s, temp_c, _RATE_WINDOW_S)) * 3600.0 if t_s.size > 2 else np.zeros(1)
    lo, hi = float(np.min(temp_c)), float(np.max(temp_c))
    # durations and distances over data (the thermosensor's gaps do not count: :func:`data_clock_s`)
    clock_s = data_clock_s(t_ns, gap_indices(t_ns, slope_window_s(t_ns, settings) / 2))

    def clock_at(ns: int) -> float:
        return float(clock_s[min(int(np.searchsorted(t_ns, ns)), clock_s.size - 1)])

    chained = np.zeros(len(plateaus), dtype=bool)
    for k in range(1, len(plateaus)):
        a, b = plateaus[k - 1], plateaus[k]
        if (
            clock_at(b.t_start_ns) - clock_at(a.t_end_ns) < settings.plateau_min_s
            and abs(b.temp_c - a.temp_c) < 2 * settings.plateau_band_c
        ):
            chained[k - 1] = chained[k] = True
    drift_s = sum(p.covered_s for p, c in zip(plateaus, chained) if c)
    soaks = tuple(dataclasses.replace(p, index=i) for i, p in enumerate(p for p, c in zip(plateaus, chained) if not c))
    soak_s = sum(p.covered_s for p in soaks)
    if hi - lo < _CONSTANT_RANGE_C:
        kind = "constant"
    elif soaks and soak_s >= _SOAK_FRACTION * float(clock_s[-1]):
        kind = "plateaus"
    else:
        kind = "sweep"
    kept = {"constant": tuple(plateaus), "plateaus": soaks, "sweep": ()}[kind]
    return TemperatureProgram(kind, (lo, hi), float(np.max(rate)), kept, float(drift_s), _RATE_WINDOW_S)


# ---------------------------------------------------------------------------------------------------------------
# static stretches


def _chunk_views(column) -> tuple[list[int], list[np.ndarray]] | None:
    """(first sample, numpy view) of each non-empty chunk of a Float64 polars column without nulls (numpy's view of
    the table's memory, no copy: polars' documented zero-copy case), for slabs without a polars call each; None for
    any other column (read with :func:`pipeline.run.slab_of`)."""
    if not isinstance(column, pl.Series) or column.dtype != pl.Float64 or column.null_count():
        return None
    starts, views, at = [], [], 0
    for length in column.chunk_lengths():
        if length:
            starts.append(at)
            views.append(column.slice(at, length).to_numpy())
        at += length
    return starts, views


def _slab_of_views(starts: list[int], views: list[np.ndarray], s0: int, s1: int) -> np.ndarray:
    """Samples ``s0 .. s1 - 1`` of a column held as chunk views (:func:`_chunk_views`): a view inside one chunk, a
    copy of the slab across chunks."""
    k = max(bisect.bisect_right(starts, s0) - 1, 0)
    if k < len(views) and s1 - starts[k] <= len(views[k]):
        return views[k][s0 - starts[k] : s1 - starts[k]]
    pieces = []
    while k < len(views) and starts[k] < s1:
        pieces.append(views[k][max(s0 - starts[k], 0) : s1 - starts[k]])
        k += 1
    return np.concatenate(pieces) if pieces else np.zeros(0)


class Channels:
    """The three voltmeter channels (V) of a record, read a slab of samples at a time.

    Built from an (n, 3) array, or from three 1-D columns (numpy arrays or polars Series: a run's table columns,
    which the readers build in chunks). A slab inside one chunk is a view, one across chunks a copy of the slab:
    the per-sample passes of this module never copy the whole record.
    """

    def __init__(self, u_v):
        if isinstance(u_v, np.ndarray):
            if u_v.ndim != 2 or u_v.shape[1] != 3:
                raise ValueError(f"voltages must be an (n, 3) array, got shape {u_v.shape}")
            cols = [u_v[:, c] for c in range(3)]
        else:
            cols = list(u_v)
            if len(cols) != 3:
                raise ValueError(f"expected 3 voltage channels, got {len(cols)}")
        self._cols = [c if isinstance(c, pl.Series) else np.asarray(c, dtype=np.float64) for c in cols]
        self.n = len(self._cols[0])
        self._views = [_chunk_views(c) for c in self._cols]

    @classmethod
    def of_run(cls, run: Run) -> Channels:
        return cls([run.voltmeter[c] for c in ("ux", "uy", "uz")])

    def slab(self, s0: int, s1: int) -> list[np.ndarray]:
        """Samples ``s0 .. s1 - 1`` of each channel, as three float64 arrays."""
        return [
            slab_of(c, s0, s1) if v is None else _slab_of_views(v[0], v[1], s0, s1)
            for c, v in zip(self._cols, self._views)
        ]

    def copy_into(self, channel: int, s0: int, s1: int, out: np.ndarray) -> np.ndarray:
        """Samples ``s0 .. s1 - 1`` of one channel copied into ``out`` (the caller's, reused: no fresh pages)."""
        views = self._views[channel]
        if views is None:
            out[: s1 - s0] = slab_of(self._cols[channel], s0, s1)
            return out[: s1 - s0]
        starts, arrays = views
        k = max(bisect.bisect_right(starts, s0) - 1, 0)
        at = s0
        while at < s1 and k < len(arrays):
            piece = arrays[k][at - starts[k] : s1 - starts[k]]
            out[at - s0 : at - s0 + piece.size] = piece
            at += piece.size
            k += 1
        return out[: s1 - s0]

    def chunk_starts(self) -> np.ndarray:
        """The sorted sample indices (> 0) where a column's next chunk begins: a slab across one is a copy."""
        ends = [np.cumsum(c.chunk_lengths())[:-1] for c in self._cols if isinstance(c, pl.Series)]
        return np.unique(np.concatenate(ends)) if ends else np.zeros(0, dtype=np.int64)

    def every(self, step: int) -> np.ndarray:
        """Every ``step``-th sample, as a small (k, 3) array (taken from views of the table's chunks)."""
        edges = np.concatenate(([0], self.chunk_starts(), [self.n]))
        cols = []
        for c in self._cols:
            pieces = []
            for a, b in zip(edges[:-1], edges[1:]):
                first = -(-int(a) // step) * step  # the first multiple of step at or after a
                if first < b:
                    pieces.append(slab_of(c, first, int(b))[::step])
            cols.append(np.concatenate(pieces) if pieces else np.zeros(0))
        return np.column_stack(cols)

    def finite(self) -> np.ndarray:
        """True (n,) where all three channels are finite (one byte per sample)."""
        out = np.empty(self.n, dtype=bool)
        for s0 in range(0, self.n, _SLAB_SAMPLES):
            s1 = min(s0 + _SLAB_SAMPLES, self.n)
            finite_columns(self.slab(s0, s1), out=out[s0:s1])
        return out


@dataclass(frozen=True)
class BlockStats:
    """Voltage statistics of a record on short time blocks, and over rolling windows of blocks.

    Blocks are ``block_ns`` long from the first sample; a run of empty blocks longer than a window (a pause in the
    recording) is shortened to one block more than a window, which changes no window's samples. ``starts`` (k,)
    is the first sample of each non-empty block and ``ids`` (k,) its index among the m blocks; ``std`` (m, 3)
    is the standard deviation (V) of each channel over the window centred on each block (NaN with fewer than 2
    finite samples) and ``count`` (m,) the finite samples in that window; ``n`` is the record's number of samples
    and ``bad`` the sorted indices of those whose three channels are not all finite.
    """

    starts: np.ndarray
    ids: np.ndarray
    std: np.ndarray
    count: np.ndarray
    n: int
    bad: np.ndarray

    def runs(self, block_mask: np.ndarray) -> np.ndarray:
        """Sample index ranges ((k, 2), [i0, i1)) of the finite samples of the blocks where the per-block
        ``block_mask`` (m,) is True: runs of such blocks, less their non-finite samples (no per-sample mask)."""
        blocks = _runs(block_mask[self.ids])
        if not blocks.size:
            return blocks
        ends = np.append(self.starts, self.n)
        runs = np.column_stack((self.starts[blocks[:, 0]], ends[blocks[:, 1]]))
        if not self.bad.size:
            return runs
        # a run [a, b) holding the bad samples j1 < .. < jm becomes [a, j1), [j1 + 1, j2), .., [jm + 1, b)
        k = np.searchsorted(runs[:, 0], self.bad, side="right") - 1
        inside = self.bad[(k >= 0) & (self.bad < runs[np.maximum(k, 0), 1])]
        a = np.sort(np.concatenate((runs[:, 0], inside + 1)))
        b = np.sort(np.concatenate((inside, runs[:, 1])))
        return np.column_stack((a, b))[b > a]


def _blocks(t_ns: np.ndarray, block_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of :class:`BlockStats` on the sorted times ``t_ns``: each non-empty block's first sample, its index
    among the blocks (a pause of more than a window's empty blocks shortened to one block more than a window), and
    its number of samples."""
    starts, numbers = _block_starts(t_ns, block_ns)
    step = np.diff(numbers)
    np.minimum(step, _BLOCKS_PER_WINDOW + 1, out=step)
    ids = np.concatenate(([0], np.cumsum(step)))
    return starts, ids, np.diff(np.append(starts, t_ns.size))


def _once(found: dict | None, key, make):
    """``make()``, or what it gave before for ``key`` in ``found`` (the memo of times several units share:
    :class:`UnitClock`); ``make()`` each time without one."""
    if found is None:
        return make()
    if key not in found:
        found[key] = make()  # (two threads may both make it: the same value)
    return found[key]


def _block_starts(t_ns: np.ndarray, block_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """First sample of each non-empty block of ``block_ns`` (from the first sample) and its block number. ``t_ns``
    is sorted. Where the record has at least as many samples as blocks, each block's first sample is found by
    searching the block edges in the times (no pass over every sample); otherwise (a sparse record with long
    pauses) from each sample's block number, a slab at a time."""
    t0 = t_ns[0]
    m = int((t_ns[-1] - t0) // block_ns) + 1
    if m <= t_ns.size:
        numbers = np.arange(m, dtype=np.int64)
        first = _first_at_or_after(t_ns, t0 + numbers * np.int64(block_ns))
        nonempty = first < np.append(first[1:], t_ns.size)
        return first[nonempty], numbers[nonempty]
    starts, numbers_ = [], []
    last = -1
    for s0 in range(0, t_ns.size, _SLAB_SAMPLES):
        b = t_ns[s0 : s0 + _SLAB_SAMPLES] - t0
        b //= block_ns
        new = np.flatnonzero(np.diff(b)) + 1
        if b[0] != last:
            new = np.concatenate(([0], new))
        starts.append(new + s0)
        numbers_.append(b[new])
        last = b[-1]
    return np.concatenate(starts), np.concatenate(numbers_)


def _first_at_or_after(t_ns: np.ndarray, keys_ns: np.ndarray) -> np.ndarray:
    """``np.searchsorted(t_ns, keys_ns, side="left")`` for sorted ``keys_ns`` within the sorted ``t_ns``: each index
    guessed from the median interval and kept where the samples either side confirm it (a steady rate: all of
    them), searched for where they do not."""
    n = t_ns.size
    step = int(median_interval_ns(t_ns, pairs=1000)) if n > 1 else 0  # (a guess: 1000 intervals are enough)
    if step <= 0:
        return np.searchsorted(t_ns, keys_ns, side="left")
    guess = np.clip((keys_ns - t_ns[0]) // step, 0, n)
    right = np.minimum(guess, n - 1)
    left = np.maximum(guess - 1, 0)
    ok = ((guess == n) | (t_ns[right] >= keys_ns)) & ((guess == 0) | (t_ns[left] < keys_ns))
    if not ok.all():
        wrong = np.flatnonzero(~ok)
        guess[wrong] = np.searchsorted(t_ns, keys_ns[wrong], side="left")
    return guess


#: the block statistics are taken this many samples at a time (their temporaries stay in the processor's cache: a
#: quarter less time than slabs of SLAB_SAMPLES on 6 M samples)
_BLOCK_SLAB = 1 << 16


def rolling_std_v(t_ns: np.ndarray, u_v, window_s: float, found: dict | None = None) -> BlockStats:
    """Standard deviation of each channel of ``u_v`` (an (n, 3) array or :class:`Channels`, V) over windows of
    ``window_s``, at the resolution of window_s / 10 (see :class:`BlockStats`). Non-finite samples are left out.

    Each block is reduced exactly (two-pass mean and squared deviations), a slab of whole blocks at a time, and the
    blocks are combined into windows with the parallel-variance formula. ``found``: what was found from these
    times for another unit on them (:class:`UnitClock`), reused (the blocks).
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    ch = u_v if isinstance(u_v, Channels) else Channels(u_v)
    block_ns = max(int(window_s * _NS / _BLOCKS_PER_WINDOW), 1)
    starts, ids, lengths = _once(found, ("blocks", block_ns), lambda: _blocks(t_ns, block_ns))
    m = int(ids[-1]) + 1
    # per block, side by side: the finite samples n, the sums n * mean and the sums of squares m2 + n * mean^2 of the
    # three channels: rows (7,) of the moments P, zero-padded by half a window before the first block and after the
    # last (P[i + K // 2] is block i's); each window's sums P[i] + .. + P[i + K - 1] are taken as soon as a slab has
    # made its last row, so only the rows of the current slab (and the K - 1 before it) are held (one reused buffer)
    k = _BLOCKS_PER_WINDOW
    std = np.empty((m, 3))
    count = np.empty(m)
    rows_p = np.zeros((7, _BLOCK_SLAB // 4))  # P's rows from ``done`` on (as columns), the first ``have`` made
    acc = np.empty_like(rows_p)
    done = have = 0  # the windows summed so far
    bad = []
    # whole blocks of about _BLOCK_SLAB samples at a time: the per-sample temporaries stay small; a block across
    # two chunks of the table is a slab of its own (the others are views of the table, not copies)
    chunked = np.searchsorted(starts, ch.chunk_starts(), side="right") - 1
    edges = np.unique(
        np.concatenate(
            (np.searchsorted(starts, np.arange(0, t_ns.size, _BLOCK_SLAB)), chunked, chunked + 1, [starts.size])
        )
    )
    bounds = np.append(starts, t_ns.size)[edges]
    scratch = np.empty(int(np.max(np.diff(bounds), initial=0)))  # the squared deviations, one buffer for all slabs
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for ka, kb in zip(edges[:-1], edges[1:]):
            s0, s1 = starts[ka], (starts[kb] if kb < starts.size else t_ns.size)
            st, ln, bid = starts[ka:kb] - s0, lengths[ka:kb], ids[ka:kb]
            cols = ch.slab(s0, s1)
            sums = [np.add.reduceat(x, st) for x in cols]
            # finite block sums: every sample is finite (a NaN or an infinity makes its block's sum one)
            all_finite = all(bool(np.isfinite(v).all()) for v in sums)
            if not all_finite:
                fin = finite_columns(cols)
                bad.append(s0 + np.flatnonzero(~fin))
            nb = ln.astype(np.float64) if all_finite else np.add.reduceat(fin, st).astype(np.float64)
            # P's rows up to this slab's last block (the empty blocks before its first: zeros)
            top = int(bid[-1]) + k // 2 + 1
            rows_p, acc = _room(rows_p, acc, have, top - done, spare=2)
            rows_p[:, have : top - done] = 0.0
            view = bid[-1] - bid[0] == kb - ka - 1  # its blocks consecutive (no pause inside it)
            row = rows_p[:, bid[0] + k // 2 - done : top - done] if view else np.empty((7, kb - ka))
            row[0] = nb
            rows = int(ln[0]) if bool(np.all(ln == ln[0])) else 0  # blocks of one length (a steady rate)
            dev = scratch[: s1 - s0]
            for c, x in enumerate(cols):
                if not all_finite:
                    x = np.where(fin, x, 0.0)
                    sums[c] = np.add.reduceat(x, st)
                mean = sums[c] / nb
                if not all_finite:  # (every block has samples: an empty one only lacks finite ones)
                    mean = np.where(nb > 0, mean, 0.0)
                if rows:  # the squared deviations, in place in the scratch buffer
                    np.subtract(x.reshape(-1, rows), mean[:, None], out=dev.reshape(-1, rows))
                else:
                    np.subtract(x, np.repeat(mean, ln), out=dev)
                if not all_finite:
                    dev[~fin] = 0.0
                np.multiply(dev, dev, out=dev)
                np.multiply(nb, mean, out=row[1 + c])
                np.multiply(mean, mean, out=mean)
                mean *= nb
                np.add(np.add.reduceat(dev, st), mean, out=row[4 + c])
            if not view:
                rows_p[:, bid + k // 2 - done] = row
            ready = max(top - k + 1 - done, 0)  # the windows whose last row is made
            _window_std(rows_p, ready, k, std[done : done + ready], count[done : done + ready], acc)
            have = top - done - ready
            rows_p[:, :have] = rows_p[:, ready : ready + have].copy()
            done += ready
        # the last windows, over the zero padding after the last block
        rows_p, acc = _room(rows_p, acc, have, m + k - 1 - done)
        rows_p[:, have : m + k - 1 - done] = 0.0
        _window_std(rows_p, m - done, k, std[done:], count[done:], acc)
    bad_i = np.concatenate(bad) if bad else np.zeros(0, dtype=np.intp)
    return BlockStats(starts=starts, ids=ids, std=std, count=count, n=int(t_ns.size), bad=bad_i)


def _room(rows: np.ndarray, acc: np.ndarray, have: int, need: int, spare: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rolling_std_v`'s buffer of rows (and its scratch ``acc``) with room for ``need`` columns, the first
    ``have`` kept: the same buffers when they have it already, else new ones of ``spare`` x ``need`` columns."""
    if need <= rows.shape[1]:
        return rows, acc
    rows = np.concatenate((rows[:, :have], np.empty((rows.shape[0], spare * need - have))), axis=1)
    return rows, np.empty_like(rows)


def _window_std(rows: np.ndarray, n_out: int, k: int, std: np.ndarray, count: np.ndarray, acc: np.ndarray) -> None:
    """Into ``std`` (n_out, 3) and ``count`` (n_out,): the standard deviations (V) and finite samples of the windows
    of ``k`` rows of block moments (``rows``: (7, r), a row a column) starting at each of the first ``n_out`` rows
    (see :func:`rolling_std_v`): the sums row by row in order (short sums, no cancellation), then
    (s2 - s1 s1 / n) / (n - 1). NaN with fewer than 2 samples. ``acc``: a scratch buffer like ``rows``."""
    if n_out <= 0:
        return
    acc = acc[:, :n_out]
    np.copyto(acc, rows[:, :n_out])
    for j in range(1, k):  # k shifted slices: the same short sums, 6x faster than a window view's sum
        acc += rows[:, j : j + n_out]
    n_w, s1, s2, var = acc[0], acc[1:4], acc[4:7], std.T
    with np.errstate(invalid="ignore", divide="ignore"):
        np.multiply(s1, s1, out=var)
        var /= n_w
        np.subtract(s2, var, out=var)
        var /= n_w - 1
    np.clip(var, 0.0, None, out=var)
    np.sqrt(var, out=var)
    std[n_w < 2] = np.nan
    count[:] = n_w


def static_threshold_v(std_v: np.ndarray, u_v=None) -> np.ndarray:
    """Per-channel static threshold (3,): a multiple of a low quantile of the rolling std, with a tiny floor
    relative to the signal's spread (so that a noise-free run still has a threshold above rounding). ``u_v``: the
    samples, an (n, 3) array or :class:`Channels` (about 100 000 of them are looked at)."""
    valid = finite_rows(std_v)
    if not valid.any():
        return np.full(3, np.inf)
    floor_q = _column_quantiles(std_v, _NOISE_QUANTILE, valid)
    scale = 1.0
    if u_v is not None:
        ch = u_v if isinstance(u_v, Channels) else Channels(u_v)
        sub = ch.every(max(1, ch.n // 100_000))
        sub = sub[finite_rows(sub)]
        if sub.size:
            q = _column_quantiles(sub, [0.01, 0.99])
            scale = max(float(np.max(q[1] - q[0])) / 2, 1e-300)
    return np.maximum(_NOISE_MULTIPLE * floor_q, _NOISE_FLOOR_REL * scale)


def _column_quantiles(x: np.ndarray, q, rows: np.ndarray | None = None) -> np.ndarray:
    """``np.quantile(x[rows], q, axis=0)`` of an (n, 3) array (``rows``: a boolean mask, default all), a contiguous
    copy of a column at a time, partitioned in place (the same order statistics, a third of the time of numpy's
    own pass along the rows, and one copy of a column instead of three)."""
    cols = (x[:, j].copy() if rows is None else x[:, j][rows] for j in range(x.shape[1]))
    return np.stack([np.quantile(c, q, overwrite_input=True) for c in cols], axis=-1)


def find_static(t_ns: np.ndarray, u_v, settings: SegmentSettings = SegmentSettings()) -> list[tuple[int, int]]:
    """Static stretches of the voltages ``u_v`` at times ``t_ns``: index ranges ``(i0, i1)``, i1 exclusive.

    ``u_v`` (V) is an (n, 3) array, three 1-D columns (numpy arrays or polars Series) or :class:`Channels`; it is
    read a slab at a time. A sample is static when the window of ``static_window_s`` around it has every channel's
    standard deviation below :func:`static_threshold_v` and the sample is finite. Stretches interrupted only by
    non-finite samples for less than a window are joined; no stretch spans a gap in time longer than half a window
    (:func:`gap_indices`: the windows either side of it do not see what happened in it); stretches shorter than
    ``static_min_s`` are dropped. Not trimmed, not cut at plateaus.
    """
    return _static_and_bad(
        np.asarray(t_ns, dtype=np.int64), u_v if isinstance(u_v, Channels) else Channels(u_v), settings
    )[0]


def _static_and_bad(
    t_ns: np.ndarray, ch: Channels, settings: SegmentSettings
) -> tuple[list[tuple[int, int]], np.ndarray]:
    """:func:`find_static`'s stretches, and the indices of the non-finite samples.

    The window adapts to the recording: ``static_window_s`` first; where the stretches it finds cover less than
    :data:`STATIC_COVER` of the record (poses shorter than a few windows, as on a hand-turned fixture), windows of
    1/2, 1/4 and 1/8 of it (never fewer than :data:`MIN_WINDOW_SAMPLES` samples: a step below that tries that
    shortest window instead, the last; ``static_min_s`` shortened to :data:`POSE_WINDOWS` windows) are tried, and the
    first that covers as much is kept (else the one covering most).
    """
    return _adaptive_static(t_ns, ch, settings)[:2]


#: stretches covering at least this fraction of the record: the static window suits the recording
STATIC_COVER = 0.5
#: with a shortened window, the shortest static stretch kept is this many windows
POSE_WINDOWS = 3.0


def _adaptive_static(
    t_ns: np.ndarray,
    ch: Channels,
    settings: SegmentSettings,
    readers: np.ndarray | None = None,
    interval_ns: float | None = None,
    found: dict | None = None,
) -> tuple[list[tuple[int, int]], np.ndarray, SegmentSettings]:
    """(stretches, non-finite sample indices, the settings whose window found them): see :func:`_static_and_bad`.
    ``readers``: the readers' gaps of ``t_ns`` (:func:`gap_indices`), ``interval_ns`` its
    :func:`median_interval_ns`, when already found; ``found``: the memo of :class:`UnitClock`."""
    if t_ns.size < 2:
        return [], np.flatnonzero(~ch.finite()), settings
    readers = reader_gap_indices(t_ns) if readers is None else readers
    dt_s = (median_interval_ns(t_ns) if interval_ns is None else interval_ns) / _NS

    runs, bad = _static_at(t_ns, ch, settings, readers, found)
    best = (_cover(t_ns, runs), runs, settings)
    for trial in _shorter_windows(settings, dt_s):
        if best[0] >= STATIC_COVER:
            break
        r, _ = _static_at(t_ns, ch, trial, readers, found)
        c = _cover(t_ns, r)
        if c > best[0] * 1.1:
            best = (c, r, trial)
    return best[1], bad, best[2]


def _cover(t_ns: np.ndarray, runs) -> float:
    """The fraction of the record (times ``t_ns``, sorted) that the stretches ``runs`` cover."""
    span_ns = float(t_ns[-1] - t_ns[0])
    return sum(float(t_ns[b - 1] - t_ns[a]) for a, b in runs) / span_ns if span_ns > 0 else 1.0


def _lenient_static(rated: SegmentSettings, used: SegmentSettings, covered: float, dt_s: float) -> SegmentSettings:
    """Of the static detections :func:`_adaptive_static` tried (``rated``, the settings for the rate, then
    :func:`_shorter_windows` while the stretches covered less than :data:`STATIC_COVER`; ``used``, the one it kept,
    whose stretches cover the fraction ``covered`` of the record), the one that finds the shortest holds: the
    least ``static_window_s + static_min_s``."""
    tried = [used] if covered >= STATIC_COVER else [rated, *_shorter_windows(rated, dt_s)]
    return min(tried, key=lambda s: s.static_window_s + s.static_min_s)


def _shorter_windows(settings: SegmentSettings, dt_s: float):
    """The settings :func:`_adaptive_static` tries in turn after ``settings`` on a record sampled every ``dt_s``
    seconds: the window halved (three times at most), never below :data:`MIN_WINDOW_SAMPLES` samples (the shortest
    window the rate allows is the last one tried), ``static_min_s`` shortened to :data:`POSE_WINDOWS` windows but
    never below :data:`MIN_SEGMENT_SAMPLES` samples."""
    window = settings.static_window_s
    shortest = MIN_WINDOW_SAMPLES * dt_s
    for _ in range(3):
        if not window > shortest:  # (NaN: no rate, no trial)
            return
        window = max(window / 2, shortest)
        yield dataclasses.replace(
            settings,
            static_window_s=window,
            static_min_s=max(MIN_SEGMENT_SAMPLES * dt_s, min(settings.static_min_s, POSE_WINDOWS * window)),
        )


def _static_at(
    t_ns: np.ndarray,
    ch: Channels,
    settings: SegmentSettings,
    readers: np.ndarray | None = None,
    found: dict | None = None,
) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Static stretches with the window of ``settings`` (no adaptation), and the non-finite sample indices
    (``readers``: as :func:`gap_indices`; ``found``: as :func:`rolling_std_v`)."""
    stats = rolling_std_v(t_ns, ch, settings.static_window_s, found)
    thr = static_threshold_v(stats.std, ch)
    quiet_block = np.all(stats.std < thr, axis=1)  # NaN compares False
    runs = stats.runs(quiet_block)
    bad = stats.bad
    if runs.size == 0:
        return [], bad
    # join stretches separated only by non-finite samples, for less than a window
    gap_ns = t_ns[runs[1:, 0]] - t_ns[runs[:-1, 1] - 1]
    gap_len = runs[1:, 0] - runs[:-1, 1]
    only_nan = (np.searchsorted(bad, runs[1:, 0]) - np.searchsorted(bad, runs[:-1, 1])) == gap_len
    join = only_nan & (gap_ns < settings.static_window_s * _NS)
    keep_start = np.concatenate(([True], ~join))
    keep_end = np.concatenate((~join, [True]))
    runs = np.column_stack((runs[keep_start, 0], runs[keep_end, 1]))
    # no stretch spans a gap longer than half a window: the windows either side of it do not see across it
    runs = split_runs(runs, gap_indices(t_ns, settings.static_window_s / 2, readers) + 1)
    dur_ns = t_ns[runs[:, 1] - 1] - t_ns[runs[:, 0]]
    runs = runs[dur_ns >= settings.static_min_s * _NS]
    return [(int(a), int(b)) for a, b in runs], bad


def split_runs(runs: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Index ranges ``runs`` ((k, 2), [i0, i1)) split where a piece must begin: at each of the sorted indices
    ``starts`` strictly inside a range (the first sample after a gap)."""
    runs = np.asarray(runs, dtype=np.int64).reshape(-1, 2)
    starts = np.asarray(starts, dtype=np.int64)
    if not runs.size or not starts.size:
        return runs
    lo = np.searchsorted(starts, runs[:, 0], side="right")
    hi = np.searchsorted(starts, runs[:, 1], side="left")
    if not np.any(hi > lo):
        return runs
    pieces = []
    for (a, b), j0, j1 in zip(runs, lo, hi):  # per range (a few hundred), not per sample
        bounds = np.concatenate(([a], starts[j0:j1], [b]))
        pieces.append(np.column_stack((bounds[:-1], bounds[1:])))
    return np.concatenate(pieces)


def remove_spans(t_ns: np.ndarray, runs, spans_ns: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges ``runs`` of the sorted times ``t_ns`` less their samples inside the open time spans
    ``spans_ns`` ((k, 2) ns, sorted): a range across a span becomes the pieces either side of it."""
    runs = np.asarray(runs, dtype=np.int64).reshape(-1, 2)
    if not runs.size or not len(spans_ns):
        return [(int(a), int(b)) for a, b in runs]
    # samples strictly inside a span are dropped: cut at its first and after its last
    first = np.searchsorted(t_ns, spans_ns[:, 0], side="right")
    last = np.searchsorted(t_ns, spans_ns[:, 1], side="left")
    pieces = split_runs(runs, np.unique(np.concatenate((first, last))))
    inside = np.zeros(len(pieces), dtype=bool)
    k = np.searchsorted(first, pieces[:, 0], side="right") - 1
    ok = k >= 0
    inside[ok] = pieces[ok, 0] < last[k[ok]]
    return [(int(a), int(b)) for a, b in pieces[~inside] if b > a]


def finite_rows(x: np.ndarray) -> np.ndarray:
    """True for the rows of an (n, 3) array whose three values are finite (fast for either memory order)."""
    return finite_columns((x[:, 0], x[:, 1], x[:, 2]))


def finite_columns(cols, out: np.ndarray | None = None) -> np.ndarray:
    """True where all three 1-D columns ``cols`` (of one length) are finite; written into ``out`` when given."""
    out = np.logical_and(np.isfinite(cols[0]), np.isfinite(cols[1]), out=out)
    out &= np.isfinite(cols[2])
    return out


def _runs(mask: np.ndarray) -> np.ndarray:
    """Runs of True in a boolean array as an (k, 2) array of [start, end) indices."""
    edge = np.flatnonzero(mask[1:] != mask[:-1]) + 1
    bounds = np.concatenate(([0], edge, [mask.size]))
    first_true = 0 if mask.size and mask[0] else 1
    b = bounds[first_true:]
    k = b.size // 2
    return np.column_stack((b[0 : 2 * k : 2], b[1 : 2 * k + 1 : 2])) if k else np.zeros((0, 2), dtype=np.int64)


# ---------------------------------------------------------------------------------------------------------------
# the whole run


#: fewest voltmeter samples in a static window, and in a kept static segment (for a stable noise floor)
MIN_WINDOW_SAMPLES = 12
MIN_SEGMENT_SAMPLES = 24
#: fewest voltmeter samples in a kept static segment on a temperature plateau (a hold there is known to be one: a
#: voltmeter at 0.5 Hz finds the 60-s holds of the short program); off every plateau :data:`MIN_SEGMENT_SAMPLES`
MIN_HOLD_SAMPLES = 12


def for_rate(settings: SegmentSettings, t_ns, interval_ns: float | None = None) -> SegmentSettings:
    """``settings`` with the static window and minimum segment length widened to at least
    :data:`MIN_WINDOW_SAMPLES` and :data:`MIN_SEGMENT_SAMPLES` voltmeter samples: the defaults suit 10 Hz and
    faster; at 1-2 Hz a 2 s window holds too few samples and a run falls apart into thousands of pieces.
    ``t_ns``: the sorted voltmeter times (ns), a numpy array or a polars Series (a run's column, not copied);
    ``interval_ns``: their :func:`median_interval_ns` when already found."""
    if len(t_ns) < 3:
        return settings
    dt_s = (median_interval_ns(t_ns) if interval_ns is None else interval_ns) / _NS
    if not dt_s > 0:
        return settings
    return dataclasses.replace(
        settings,
        static_window_s=max(settings.static_window_s, MIN_WINDOW_SAMPLES * dt_s),
        static_min_s=max(settings.static_min_s, MIN_SEGMENT_SAMPLES * dt_s),
    )


def median_interval_ns(t_ns, pairs: int = 100_000) -> float:
    """Median interval (ns) between consecutive samples of the sorted times ``t_ns`` (numpy array or polars
    Series), from up to ``pairs`` pairs spread evenly over the record: a long record's rate without a difference
    array of all its samples."""
    n = len(t_ns)
    if n < 2:
        return float("nan")
    i = np.linspace(0, n - 2, min(n - 1, pairs)).astype(np.int64)  # distinct: spacing >= 1
    if isinstance(t_ns, pl.Series):
        d = (t_ns.gather(i + 1) - t_ns.gather(i)).to_numpy()
    else:
        d = t_ns[i + 1] - t_ns[i]
    return float(np.median(d))


@dataclass(frozen=True)
class StaticStretches:
    """A run's static stretches as :func:`segment_run` finds them: voltmeter index ranges ``(i0, i1)`` in time order,
    the indices of the non-finite samples, and the settings (window adapted to the rate and the poses) they were
    found with."""

    stretches: list[tuple[int, int]]
    bad: np.ndarray
    settings: SegmentSettings
    #: the voltmeter's times (ns) they index, and the indices after which its gaps come
    #: (:func:`pipeline.io.checks.gap_indices`), when handed over (each is a pass over the run's samples)
    t_ns: np.ndarray | None = None
    gaps_after: np.ndarray | None = None
    #: ... and the median interval (ns) between them (:func:`median_interval_ns`)
    interval_ns: float | None = None
    #: ... and what was found from them for every unit on them (:attr:`UnitClock.found`)
    found: dict | None = None


def static_stretches(
    run: Run,
    settings: SegmentSettings = SegmentSettings(),
    clock: tuple | None = None,
) -> StaticStretches:
    """The static stretches of ``run``'s voltages (the step of :func:`segment_run` that reads every sample), for a
    caller that decides them across several units (:mod:`pipeline.segment_units`) and hands them back to
    :func:`segment_run` (with the times and gaps they were found on). The run's voltmeter must be in time order
    (the readers sort it). ``clock``: its :class:`UnitClock` (or the times (ns), the readers' gaps in them and their
    median interval) when the caller has it (units read by one logger share it)."""
    clock = unit_clock(run) if clock is None else clock
    t_ns, readers, interval_ns = clock[:3]
    memo = clock[3] if len(clock) > 3 else None
    ch = Channels([run.voltmeter[c] for c in ("ux", "uy", "uz")])
    found = _adaptive_static(t_ns, ch, for_rate(settings, t_ns, interval_ns), readers, interval_ns, memo)
    return StaticStretches(*found, t_ns, readers, interval_ns, memo)


def _goes_back(t_ns: np.ndarray) -> bool:
    """Whether the times ``t_ns`` ever decrease, a slab at a time (no mask the length of the record)."""
    n = t_ns.size - 1  # intervals
    return any(
        bool(np.any(t_ns[s0 + 1 : min(s0 + _SLAB_SAMPLES, n) + 1] < t_ns[s0 : min(s0 + _SLAB_SAMPLES, n)]))
        for s0 in range(0, max(n, 0), _SLAB_SAMPLES)
    )


class UnitClock(NamedTuple):
    """A voltmeter's times and what is found from them alone, once for every unit sampled on them."""

    #: the times (ns, a numpy copy of the table's column)
    t_ns: np.ndarray
    #: the indices after which its gaps come (:func:`pipeline.io.checks.gap_indices`)
    gaps_after: np.ndarray
    #: the :func:`median_interval_ns`
    interval_ns: float
    #: a memo of what the segmenter finds from the times alone (the blocks of :func:`rolling_std_v` by block
    #: length, whether they go back, as float64), made by the first unit that needs it
    found: dict


def unit_clock(run: Run) -> UnitClock:
    """``run``'s voltmeter :class:`UnitClock`."""
    t_ns = run.t_ns()
    return UnitClock(t_ns, reader_gap_indices(t_ns), median_interval_ns(t_ns), {})


def _left_out(t_ns: np.ndarray, left_out_ns: tuple[tuple[str, int, int], ...], column: str) -> np.ndarray:
    """Which of the times ``t_ns`` (ns) lie in a stretch of ``column`` that the readers set to NaN as stuck or
    clipped and named (:attr:`pipeline.run.Run.left_out_ns`): a non-finite line does not count them again."""
    spans = np.array(sorted((a, b) for c, a, b in left_out_ns if c == column), dtype=np.int64).reshape(-1, 2)
    if not spans.size:
        return np.zeros(t_ns.size, dtype=bool)
    k = np.searchsorted(spans[:, 0], t_ns, "right") - 1
    return (k >= 0) & (t_ns <= spans[np.maximum(k, 0), 1])


def _non_finite_line(
    volts: pl.DataFrame,
    t_ns: np.ndarray,
    bad: np.ndarray,
    interval_ns,
    unit: str | None,
    left_out_ns: tuple[tuple[str, int, int], ...] = (),
) -> str | None:
    """The warning about the voltmeter samples ``bad`` (sorted indices into ``t_ns``, the table ``volts``' times)
    that have a non-finite channel: the unit (``unit``, named in a run with several), how many samples, the
    channels with how many each, and the stretches in seconds (:func:`pipeline.io.checks.stretches_text`). A
    channel's samples in ``left_out_ns`` (:attr:`pipeline.run.Run.left_out_ns`: set to NaN by the readers as stuck
    or clipped, and named there) are not counted again; None when no other is left."""
    from pipeline.io.checks import index_stretches, stretches_text

    at = pl.Series(bad)
    t_bad = t_ns[bad]
    counts: dict[str, int] = {}
    other = np.zeros(bad.size, dtype=bool)
    for c in ("ux", "uy", "uz"):
        missing = ~np.isfinite(volts[c].gather(at).to_numpy()) & ~_left_out(t_bad, left_out_ns, c)
        counts[c] = int(np.count_nonzero(missing))
        other |= missing
    bad = bad[other]
    if not bad.size:
        return None
    channels = ", ".join(f"{c} {n}" for c, n in counts.items() if n)
    runs, _ = index_stretches(bad)
    step_ns = float("nan") if interval_ns is None else float(interval_ns)
    where = "voltmeter" if unit is None else f"voltmeter of unit {unit}"
    return (
        f"{where}: {bad.size} non-finite samples excluded (not static), {channels}, "
        f"{stretches_text(t_ns, runs, step_ns)}"
    )


def segment_run(
    run: Run,
    settings: SegmentSettings = SegmentSettings(),
    static: StaticStretches | None = None,
    unit: str | None = None,
) -> Segmentation:
    """Plateaus, static segments (cut at plateau boundaries, trimmed, averaged, named) and warnings of ``run``.

    The voltages are read from the run's table a slab at a time (:class:`Channels`): besides the table, the
    per-sample memory is the times (8 bytes per sample) and a few masks (1 byte per sample). ``static``: the static
    stretches decided elsewhere (:func:`static_stretches`, e.g. across the units of one fixture), used instead of
    finding them here. ``unit``: the unit's serial where the run holds several (its warnings about its own
    voltmeter name it).
    """
    warnings: list[str] = []
    t_ns = run.t_ns() if static is None or static.t_ns is None else static.t_ns
    memo = static.found if static is not None and static.t_ns is t_ns else None
    volts = run.voltmeter
    if _once(memo, "goes back", lambda: _goes_back(t_ns)):
        memo = None
        volts = volts.sort("t_ns", maintain_order=True)
        t_ns = volts["t_ns"].to_numpy()
        warnings.append("voltmeter: samples not in time order; sorted")
    ch = Channels([volts[c] for c in ("ux", "uy", "uz")])
    tt_ns = run.au_temperature["t_ns"].to_numpy()
    temp = run.au_temperature["temp_c"].to_numpy()
    if np.any(tt_ns[1:] < tt_ns[:-1]):
        order = np.argsort(tt_ns, kind="stable")
        tt_ns, temp = tt_ns[order], temp[order]
        warnings.append("au_temperature: samples not in time order; sorted")
    bad_t = ~np.isfinite(temp)
    if bad_t.any():
        other = bad_t & ~_left_out(tt_ns, run.left_out_ns, "temp_c")  # (stuck or clipped: named by the readers)
        if other.any():
            warnings.append(
                f"au_temperature: {int(other.sum())} non-finite samples ignored, first at t_ns={int(tt_ns[other][0])}"
            )
        tt_ns, temp = tt_ns[~bad_t], temp[~bad_t]

    known = static is not None and static.t_ns is t_ns and static.interval_ns is not None  # (not after sorting)
    interval_ns = static.interval_ns if known and static is not None else median_interval_ns(t_ns)
    asked_min_s = settings.static_min_s
    settings = for_rate(settings, t_ns, interval_ns)
    plateaus = find_plateaus(tt_ns, temp, settings)
    # (on the plateaus, a thermosensor read once a minute shows its noise, not the ramps' curvature)
    on_plateaus = [
        (int(np.searchsorted(tt_ns, p.t_start_ns, "left")), int(np.searchsorted(tt_ns, p.t_end_ns, "right")))
        for p in plateaus
    ]
    temp_noise_c = thermosensor_noise_c(temp, on_plateaus)
    if temp_noise_c == 0.0:
        temp_noise_c = thermosensor_noise_c(temp)
    if not plateaus:
        warnings.append(
            f"{NO_PLATEAU_WARNING} (the temperature never stays within "
            f"{settings.plateau_rate_c_per_min} C/min for {settings.plateau_min_s:.0f} s)"
        )

    readers = None if static is None else static.gaps_after
    readers = reader_gap_indices(t_ns) if readers is None else readers
    rated = settings
    if static is None:
        stretches, bad_u, settings = _adaptive_static(t_ns, ch, settings, readers, interval_ns)
    else:
        stretches, bad_u, settings = static.stretches, static.bad, static.settings
    covered = _cover(t_ns, stretches) if t_ns.size > 1 else 1.0
    dt_s = float("nan") if interval_ns is None else interval_ns / _NS
    lenient = _lenient_static(rated, settings, covered, dt_s)
    # on a temperature plateau a hold is known to be one: a stretch of MIN_HOLD_SAMPLES will do there
    hold_min_s = max(MIN_HOLD_SAMPLES * dt_s, min(asked_min_s, settings.static_min_s))
    if static is None and plateaus and hold_min_s < settings.static_min_s:
        shorter = dataclasses.replace(settings, static_min_s=hold_min_s)
        found, _ = _static_at(t_ns, ch, shorter, readers)
        starts = np.array([p.t_start_ns for p in plateaus], dtype=np.int64)
        ends = np.array([p.t_end_ns for p in plateaus], dtype=np.int64)
        on = np.searchsorted(starts, [t_ns[a] for a, _ in found], side="right") - 1  # the plateau begun by then
        extra = [
            (a, b)
            for (a, b), j in zip(found, on)
            if j >= 0 and t_ns[b - 1] <= ends[j] and t_ns[b - 1] - t_ns[a] < settings.static_min_s * _NS
        ]
        if extra:
            stretches = sorted(stretches + extra)
        lenient = dataclasses.replace(lenient, static_min_s=min(lenient.static_min_s, hold_min_s))
    else:
        hold_min_s = settings.static_min_s
    # a sample in a gap of the thermosensor, or away from its record, has no temperature: no stretch holds one
    holes = thermosensor_gaps(tt_ns, settings)
    unknown = thermosensor_gaps(tt_ns, settings, within=(t_ns[0], t_ns[-1])) if t_ns.size and tt_ns.size else holes
    if len(unknown):
        min_ns = hold_min_s * _NS  # (pieces off every plateau: static_min_s, :func:`_cut_at_plateaus`)
        stretches = [(a, b) for a, b in remove_spans(t_ns, stretches, unknown) if t_ns[b - 1] - t_ns[a] >= min_ns]
    outside_ns = sum(b - a for a, b in unknown) - sum(b - a for a, b in holes)
    if tt_ns.size > 1 and outside_ns > median_interval_ns(tt_ns):  # more than a reading's worth
        warnings.append(
            f"voltmeter: {outside_ns / _NS:.0f} s of samples before the first or after the last AU thermosensor "
            "reading have no temperature: not used"
        )
    said = _non_finite_line(volts, t_ns, bad_u, interval_ns, unit, run.left_out_ns) if bad_u.size else None
    if said:
        warnings.append(said)
    gaps = {"voltmeter": gap_spans(t_ns, settings.static_window_s / 2, readers), "au_temperature": holes}
    warnings += _gaps_on_plateaus(plateaus, gaps, settings.static_min_s, run.fixture)
    pieces = _cut_at_plateaus(t_ns, stretches, plateaus, settings, hold_min_s)
    all_gaps = np.concatenate([gaps["voltmeter"], holes.reshape(-1, 2)])
    all_gaps = all_gaps[np.argsort(all_gaps[:, 1], kind="stable")]
    fixture, stale = _fixture_labels(run, t_ns, pieces, all_gaps, run.unlogged_ns)

    rows: list[dict[str, Any]] = []
    tt_s = tt_ns.astype(np.float64)
    # the voltmeter's times as float64 (for the interpolation of the temperature), once for the units on them
    t_float = None if memo is None else _once(memo, "float64", lambda: t_ns.astype(np.float64))
    n_bad = np.searchsorted(bad_u, [a for a, *_ in pieces]), np.searchsorted(bad_u, [b for _, b, *_ in pieces])
    # a piece begins after a move where its static stretch is not its predecessor's (else a plateau cut it)
    stretch_of = np.searchsorted(np.array([a for a, _ in stretches], dtype=np.int64), [a for a, *_ in pieces], "right")
    after_move = np.concatenate(([False], stretch_of[1:] != stretch_of[:-1]))
    moments: list[HoldMoments] = []
    for (i0, i1, p, settling), fix, old, some_bad, moved in zip(
        pieces, fixture, stale, n_bad[1] > n_bad[0], after_move
    ):
        cols, tt = ch.slab(i0, i1), (t_ns if t_float is None else t_float)[i0:i1]
        if some_bad:  # (non-finite samples are found once: :attr:`StaticStretches.bad`)
            fin = finite_columns(cols)
            cols, tt = [c[fin] for c in cols], tt[fin]
        tc = np.interp(tt.astype(np.float64, copy=False), tt_s, temp) if temp.size else np.full(tt.size, np.nan)
        ddof = 1 if tt.size > 1 else 0
        stats = [_mean_std(c, ddof) for c in cols]
        temp_c = _mean_std(tc, 0)
        temp_sigma_c = temp_noise_c * np.sqrt(interpolated_mean_weight2(tt_s, tt)) if tt.size else 0.0
        t_s = (tt - tt[0]) / _NS if moved and tt.size else np.zeros(0)  # (no creep without a move: no moments)
        moments.append(hold_moments(t_s, cols, np.array([m for m, _ in stats]), tc))
        rows.append(
            dict(
                t_start_ns=int(t_ns[i0]),
                t_end_ns=int(t_ns[i1 - 1]),
                plateau=p,
                fixture_label=fix,
                mean_v=np.array([m for m, _ in stats]),
                std_v=np.array([sd for _, sd in stats]),
                count=int(tt.size),
                temp_c=float(temp_c[0]),
                temp_std_c=float(temp_c[1]),
                temp_sigma_c=float(temp_sigma_c),
                settling=settling,
                stale=old,
            )
        )
    creep = _take_out_settling(rows, moments, after_move, warnings)

    names = _name_segments(run, rows, settings, warnings)
    continues = _continued_holds(rows, [nm["position"] for nm in names], all_gaps, run.fixture, settings)
    segments = []
    for k, (r, nm) in enumerate(zip(rows, names)):
        segments.append(
            StaticSegment(
                index=k,
                t_start_ns=r["t_start_ns"],
                t_end_ns=r["t_end_ns"],
                position=nm["position"],
                label_source=nm["source"],
                fixture_label=nm.get("fixture_label", r["fixture_label"]),
                label_conflict=nm["conflict"],
                plateau=r["plateau"],
                mean_v=vector3(r["mean_v"]),
                std_v=vector3(r["std_v"]),
                count=r["count"],
                temp_c=r["temp_c"],
                temp_std_c=r["temp_std_c"],
                direction_g=vector3(nm["direction"]),
                settling=r["settling"],
                continues=continues[k],
                temp_sigma_c=r["temp_sigma_c"],
            )
        )
    first = np.empty(min(ch.n, _SLAB_SAMPLES))  # (one buffer for the three channels' resolutions)
    seg = Segmentation(
        plateaus=plateaus,
        segments=segments,
        warnings=warnings,
        stretches=stretches,
        static_window_s=settings.static_window_s,
        static_min_s=settings.static_min_s,
        lenient_static_s=(lenient.static_window_s, lenient.static_min_s),
        gaps_ns={k: [(int(a), int(b)) for a, b in v] for k, v in gaps.items()},
        resolution_v=vector3(
            [reading_resolution(ch.copy_into(c, 0, first.size, first), scratch=True) for c in range(3)]
        ),
        settling=creep,
    )
    if run.fixture is not None and run.fixture.height:  # (without a log, the holds are found when refused)
        note = short_holds(run, seg, t_ns, interval_ns)
        if note:
            warnings.append(f"{SHORT_HOLDS_WARNING}: {note}: not used")
    return seg


def thermosensor_noise_c(temp_c: np.ndarray, spans: list[tuple[int, int]] | None = None) -> float:
    """White noise (C, 1 sigma) of a thermosensor's finite readings ``temp_c`` in time order: robust (1.4826 MAD)
    from their second differences, which cancel ramps, within each of ``spans`` (index ranges [i0, i1) of the
    readings, e.g. the plateaus, where the temperature's own curvature is least; default: all of them); 0 with
    fewer than 10 second differences."""
    temp_c = np.asarray(temp_c, dtype=float)
    pieces = [np.diff(temp_c[a:b], 2) for a, b in ([(0, temp_c.size)] if spans is None else spans) if b - a > 2]
    d2 = np.concatenate(pieces) if pieces else np.zeros(0)
    if d2.size < 10:
        return 0.0
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def interpolated_mean_weight2(xp: np.ndarray, x: np.ndarray) -> float:
    """The sum of the squared weights of the readings at ``xp`` (sorted) in the mean of their linear interpolation
    (``np.interp``, the ends held) at the points ``x``: the variance of that mean in units of one reading's variance,
    for independent readings (1 where every point lies between the same two readings' ends, 1/n for n readings
    one per point).

    In closed form per interval between readings: a point x in [xp_j, xp_j+1) gives reading j the weight
    1 - lam and reading j+1 lam, lam = (x - xp_j) / (xp_j+1 - xp_j), so each interval needs only its count of
    points and the sum of their x - xp_j (one sum over the points, cut where each reading's time falls: no per-point
    weights); points before the first reading or from the last one on weigh on that reading alone. Exact for
    points and readings on whole nanoseconds (float64 of int64 ns, the segmentation's)."""
    m, n = xp.size, x.size
    if m < 2 or n == 0:
        return 1.0
    x = np.asarray(x, dtype=np.float64)
    if n > 1 and np.any(x[1:] < x[:-1]):
        x = np.sort(x)
    # the intervals j = lo..hi the points fall in (np.interp's: x in [xp_j, xp_j+1), the ends held)
    lo = min(max(int(np.searchsorted(xp, x[0], side="right")) - 1, 0), m - 2)
    hi = min(max(int(np.searchsorted(xp, x[-1], side="right")) - 1, 0), m - 2)
    r = np.asarray(xp[lo : hi + 2], dtype=np.float64)  # readings lo..hi+1
    cut = np.searchsorted(x, r, side="left")  # (hi - lo + 2,) the first point at or after each reading
    count = np.diff(cut)  # (hi - lo + 1,) points within each interval
    full = count > 0
    # each interval's sum of x - x_0 (reduceat at the starts of the non-empty ones: each runs to the next such
    # start), less its count times xp_j - x_0: its sum of x - xp_j, exact for whole ns below 2^53 ns an interval
    sums = np.zeros(count.size)
    if np.any(full):
        sums[full] = np.add.reduceat(x[: cut[-1]] - x[0], cut[:-1][full])
    dx = np.diff(r)
    lam_sum = np.divide(sums - count * (r[:-1] - x[0]), dx, out=np.zeros(count.size), where=full & (dx > 0))
    w = np.zeros(r.size)
    w[:-1] += count - lam_sum
    w[1:] += lam_sum
    w[0] += cut[0]  # points before the first reading: on it alone
    w[-1] += n - cut[-1]  # points at or after the last reading lo..hi+1 (the last of all): on it alone
    w /= n
    return float(w @ w)


def _take_out_settling(
    rows: list[dict[str, Any]], moments: list[HoldMoments], after_move: np.ndarray, warnings: list[str]
) -> Settling | None:
    """The creep after each move (:func:`pipeline.settling.settling_fit`) taken out of the means of ``rows`` (the
    segments in time order, with their :class:`pipeline.settling.HoldMoments` and whether each follows a move: its
    static stretch is not its predecessor's), said in ``warnings``, and returned; nothing changes (None) where the
    recording shows none."""
    if len(rows) < 2:
        return None
    found = settling_fit(
        moments,
        np.array([r["mean_v"] for r in rows]),
        np.array([r["std_v"] for r in rows]),
        np.array([r["t_start_ns"] for r in rows], dtype=np.int64) / _NS,
        np.array([r["t_end_ns"] for r in rows], dtype=np.int64) / _NS,
        np.asarray(after_move)[1:],
    )
    if not found.used:
        return None
    for r, c in zip(rows, found.correction_v):
        r["mean_v"] = r["mean_v"] - c
    warnings.append(found.line(int(np.count_nonzero(np.any(found.correction_v != 0, axis=1)))))
    return found


#: how the warning of holds too short for the static detection at the recording's rate begins
SHORT_HOLDS_WARNING = "voltmeter: holds too short for the rate"
#: a static window or stretch within this factor of its fewest samples is at that floor (the rate set it)
_AT_FLOOR = 1.001


def short_holds(run: Run, seg: Segmentation, t_ns=None, interval_ns: float | None = None) -> str | None:
    """What says that positions were held too briefly for the static detection at the voltmeter's rate, e.g.
    ``16 of the fixture log's 25 holds (TP2, ...) last ~60 s at 0.5 Hz; a position needs >= 72 s at this rate (a
    24-s static window, stretches of >= 48 s)``; None when no hold is that short. The holds are the fixture log's
    (from each position's event to the next event) or, without a log, the still poses the signal shows: the quiet
    stretches too short to keep (with the segmentation's window, plus that window). What a position needs is
    :attr:`Segmentation.lenient_static_s`, from the settings at this rate (:func:`for_rate`,
    :func:`_shorter_windows`); None too when neither is at its floor of :data:`MIN_WINDOW_SAMPLES` and
    :data:`MIN_SEGMENT_SAMPLES` samples (the cause is not the rate). ``t_ns``, ``interval_ns``: the voltmeter's
    sorted times and their :func:`median_interval_ns`, when already found."""
    if seg.lenient_static_s is None or seg.static_window_s is None:
        return None
    t_ns = run.t_ns() if t_ns is None else t_ns
    if t_ns.size < 3:
        return None
    dt_s = (median_interval_ns(t_ns) if interval_ns is None else interval_ns) / _NS
    window_s, min_s = seg.lenient_static_s
    if not (window_s <= MIN_WINDOW_SAMPLES * dt_s * _AT_FLOOR or min_s <= MIN_SEGMENT_SAMPLES * dt_s * _AT_FLOOR):
        return None  # the rate did not lengthen what a hold needs: a faster voltmeter would not find more
    needed_s = window_s + min_s
    fx = run.fixture
    if fx is not None and fx.height:
        ft = fx["t_ns"].to_numpy()
        order = np.argsort(ft, kind="stable")
        ft, fp = ft[order], np.asarray(fx["position"].to_list(), dtype=object)[order]
        new = np.concatenate(([True], fp[1:] != fp[:-1]))  # an event repeating the position goes on holding it
        ft, fp = ft[new], fp[new]
        ends = np.append(ft[1:], max(int(t_ns[-1]), int(ft[-1])))
        held = [(str(p), (b - a) / _NS) for p, a, b in zip(fp, ft, ends) if p in ALL_POSITIONS]
        short = [(p, d) for p, d in held if d < needed_s]
        names = ", ".join(dict.fromkeys(p for p, _ in short))
        what = f"{len(short)} of the fixture log's {len(held)} holds ({names}) last"
        durations = [d for _, d in short]
    else:
        quiet, _ = _static_at(
            t_ns,
            Channels.of_run(run),
            dataclasses.replace(SegmentSettings(), static_window_s=seg.static_window_s, static_min_s=0.0),
        )
        poses = np.array([(t_ns[b - 1] - t_ns[a]) / _NS + seg.static_window_s for a, b in quiet])
        durations = list(poses[poses < needed_s])
        if len(durations) < max(2, poses.size - len(durations)):  # short poses: most of the still ones
            return None
        what = f"{len(durations)} still poses (no fixture log) last"
    if not durations:
        return None
    return (
        f"{what} ~{float(np.median(durations)):.2g} s at {1 / dt_s:.3g} Hz; a position needs >= {needed_s:.3g} s at "
        f"this rate (a {window_s:.3g}-s static window, stretches of >= {min_s:.3g} s)"
    )


def _mean_std(x: np.ndarray, ddof: int) -> tuple[float, float]:
    """``(x.mean(), x.std(ddof=ddof))`` of a 1-D float64 array, to the last bit, with one pass fewer: the sum is
    taken once (numpy's std takes the mean as its mean does, then the sum of the squared deviations)."""
    n = x.size
    if n == 0 or n - ddof <= 0:
        return x.mean(), x.std(ddof=ddof)
    mean = np.add.reduce(x) / n
    dev = x - mean
    np.multiply(dev, dev, out=dev)
    return mean, np.sqrt(np.add.reduce(dev) / (n - ddof))


def _continued_holds(
    rows: list[dict[str, Any]],
    positions: list[str | None],
    gaps_ns: np.ndarray,
    fixture: pl.DataFrame | None,
    settings: SegmentSettings,
) -> list[int | None]:
    """Per segment (``rows`` in time order, named ``positions``), the index of the segment it continues across a
    gap, or None. Two neighbouring segments are pieces of one hold where they have the same position, plateau and
    settling, a gap (``gaps_ns``, (k, 2) ns) lies between them and, gaps aside, no more time separates them than the
    trimming and the static windows either side of a gap take (``settle_trim_s`` and two ``static_window_s`` on
    each side): nothing but missing data. Where a ``fixture`` log is given, it must hold that position from the
    end of the first piece to the start of the second (a logged move in the gap makes two holds); without one, the
    signal's position on both sides is all there is (a move and return inside the gap cannot be seen)."""
    out: list[int | None] = [None] * len(rows)
    if len(rows) < 2 or not len(gaps_ns):
        return out
    slack_ns = 2 * (settings.settle_trim_s + 2 * settings.static_window_s) * _NS
    if fixture is not None and fixture.height:
        fx = fixture.sort("t_ns")
        ft, fp = fx["t_ns"].to_numpy(), fx["position"].to_list()
    else:
        ft, fp = None, []
    for k in range(1, len(rows)):
        a, b, pos = rows[k - 1], rows[k], positions[k]
        if pos is None or positions[k - 1] != pos or a["plateau"] != b["plateau"] or a["settling"] != b["settling"]:
            continue
        lo, hi = a["t_end_ns"], b["t_start_ns"]
        inside = gaps_ns[(gaps_ns[:, 0] >= lo) & (gaps_ns[:, 1] <= hi)]
        if not len(inside) or (hi - lo) - int((inside[:, 1] - inside[:, 0]).sum()) > slack_ns:
            continue
        if ft is not None:
            i0 = int(np.searchsorted(ft, lo, side="right")) - 1
            i1 = int(np.searchsorted(ft, hi, side="right"))
            if any(p != pos for p in fp[max(i0, 0) : i1]) or i0 < 0:
                continue
        out[k] = k - 1
    return out


def reading_resolution(x: np.ndarray, scratch: bool = False) -> float:
    """The resolution of recorded values ``x`` (a channel's readings, V): a logger's quantisation step where the
    distinct finite values lie on one (every step between them a whole number of the smallest, within 1 %), else
    the float64 spacing of the largest value (a value stored as float64 says nothing finer). 0 without a finite
    value. The format declares no quantisation step (docs/log-format.md), so the values' own is the one there is.
    ``scratch``: ``x`` is the caller's own copy, which may be reordered (sorted in place where all is finite)."""
    # sorted: the steps between distinct values are the sorted values' steps > 0 (a finite sum: all finite)
    v = x if scratch and np.isfinite(np.add.reduce(x)) else x[np.isfinite(x)]
    if not v.size:
        return 0.0
    v.sort()
    floor = float(np.spacing(max(abs(v[0]), abs(v[-1]))))

    def steps():  # the steps > 0 between the sorted values, a slab at a time (temporaries in the cache)
        for a in range(0, v.size - 1, _BLOCK_SLAB):
            d = np.diff(v[a : a + _BLOCK_SLAB + 1])
            yield d[d > 0]

    q, count = np.inf, 0
    for d in steps():
        count += d.size
        q = min(q, float(d.min())) if d.size else q
    if count < 2 or not q > floor:
        return floor
    on_grid = all(bool(np.all(np.abs(d / q - np.round(d / q)) < 0.01)) for d in steps())
    return q if on_grid else floor


def _gaps_on_plateaus(
    plateaus: list[Plateau], gaps: dict[str, np.ndarray], min_off_s: float, fixture: pl.DataFrame | None = None
) -> list[str]:
    """One line per plateau (its settling included) with gaps of the voltmeter or the thermosensor: what is
    missing, where (no position is made of that time), by name where the ``fixture`` log held a position on the
    plateau for less than ``min_off_s`` outside the gaps; and one line for the gaps of at least ``min_off_s`` on
    no plateau (e.g. a soak whose every thermosensor reading is lost: no plateau is found there)."""
    from pipeline.utc import utc_span

    spans_ns = [np.asarray(v, dtype=np.int64).reshape(-1, 2) for v in gaps.values()]
    every_gap = np.concatenate(spans_ns) if spans_ns else np.zeros((0, 2), dtype=np.int64)
    out = []
    for p in plateaus:
        lo = p.t_start_ns if p.settle_start_ns is None else p.settle_start_ns
        streams: dict[tuple[int, int], list[str]] = {}
        for stream, spans in gaps.items():
            for a, b in spans:
                if a < p.t_end_ns and b > lo:
                    streams.setdefault((int(a), int(b)), []).append(stream)
        said = [
            f"no {' or '.join(names)} data {utc_span(a, b)} ({(b - a) / _NS:.0f} s)"
            for (a, b), names in sorted(streams.items())
        ]
        if said:
            lost = _held_only_in_gaps(fixture, lo, p.t_end_ns, every_gap, min_off_s)
            what = (
                f"{', '.join(lost)}, held only then (fixture log), {'is' if len(lost) == 1 else 'are'} missing"
                if lost
                else "a position held only then is missing"
            )
            out.append(f"plateau {p.index} at {p.temp_c:+.1f} C: {'; '.join(said)}: nothing held then is used ({what})")
    # gaps on no plateau found (a soak whose every thermosensor reading is lost is no plateau): one line for them
    fronts = [(p.t_start_ns if p.settle_start_ns is None else p.settle_start_ns, p.t_end_ns) for p in plateaus]
    off: dict[tuple[int, int], list[str]] = {}
    for stream, spans in gaps.items():
        for a, b in spans:
            if b - a >= min_off_s * _NS and not any(a < hi and b > lo for lo, hi in fronts):
                off.setdefault((int(a), int(b)), []).append(stream)
    if off:
        said = [
            f"no {' or '.join(names)} data {utc_span(a, b)} ({(b - a) / _NS:.0f} s)"
            for (a, b), names in sorted(off.items())
        ]
        more = f"; and {len(said) - _GAPS_LISTED} more" if len(said) > _GAPS_LISTED else ""
        spans = np.array(list(off), dtype=np.int64)
        times = _fixture_time_in_gaps(fixture, int(spans[:, 0].min()), int(spans[:, 1].max()), spans)
        logged = [k for k, (_, inside) in times.items() if inside >= min_off_s * _NS]
        what = f"the fixture log held {', '.join(logged)} then" if logged else "a position held only then is missing"
        out.append(f"off every plateau: {'; '.join(said[:_GAPS_LISTED])}{more}: nothing held then is used ({what})")
    return out


#: the gaps off every plateau listed by name in the warning (the rest counted)
_GAPS_LISTED = 5


def _cut_at_plateaus(
    t_ns: np.ndarray,
    stretches: list[tuple[int, int]],
    plateaus: list[Plateau],
    settings: SegmentSettings,
    hold_min_s: float | None = None,
) -> list[tuple[int, int, int | None, int | None]]:
    """Cut static stretches at plateau boundaries, drop pieces shorter than static_min_s (on a plateau's stable
    part: ``hold_min_s``, when given), trim each piece.

    A stretch is cut where each plateau begins and ends, except where it began in that plateau's settling: a hold
    the program started while the unit still settled is one segment, even where it goes on into the stable part.
    (A position carried through the ramp and the soak is cut where the plateau begins: its part on the plateau is
    a segment of its own.) Returns (i0, i1, plateau index or None, settling) per piece, in time order: a piece
    starting on a plateau is on it; one starting in the settling before it is off every plateau, ``settling`` the
    plateau's index (None otherwise).
    """
    starts = np.array([p.t_start_ns for p in plateaus], dtype=np.int64)
    fronts = np.array(
        [p.t_start_ns if p.settle_start_ns is None else p.settle_start_ns for p in plateaus], dtype=np.int64
    )
    ends = np.array([p.t_end_ns for p in plateaus], dtype=np.int64)
    # sample index boundaries: a plateau owns the samples with start <= t <= end, its settling front <= t < start
    start_idx = np.searchsorted(t_ns, starts, side="left")
    end_idx = np.searchsorted(t_ns, ends, side="right")
    min_ns = settings.static_min_s * _NS
    hold_min_ns = min_ns if hold_min_s is None else min(min_ns, hold_min_s * _NS)
    out = []
    for i0, i1 in stretches:
        cuts = np.concatenate((start_idx[fronts > t_ns[i0]], end_idx))
        inner = np.sort(cuts[(cuts > i0) & (cuts < i1)])
        bounds = np.concatenate(([i0], inner, [i1]))
        for a, b in zip(bounds[:-1], bounds[1:]):
            a, b = int(a), int(b)
            if b <= a or t_ns[b - 1] - t_ns[a] < hold_min_ns:
                continue
            dur_ns = t_ns[b - 1] - t_ns[a]
            first = t_ns[a]
            on = np.flatnonzero((fronts <= first) & (first <= ends))
            k = int(on[0]) if on.size else None
            if dur_ns < min_ns and not (k is not None and first >= starts[k]):
                continue  # (shorter than static_min_s: only on a plateau's stable part)
            trim0 = int(min(settings.settle_trim_s * _NS, _MAX_START_TRIM * dur_ns))
            trim1 = int(min(settings.settle_trim_s / 10 * _NS, _MAX_END_TRIM * dur_ns))
            # (search keys of the array's dtype: a float key would convert the whole array)
            a2 = a + int(np.searchsorted(t_ns[a:b], t_ns[a] + np.int64(trim0), side="left"))
            b2 = a + int(np.searchsorted(t_ns[a:b], t_ns[b - 1] - np.int64(trim1), side="right"))
            if b2 > a2:
                stable = k is not None and first >= starts[k]
                out.append((a2, b2, k if stable else None, None if stable else k))
    return out


def _fixture_time_in_gaps(
    fixture: pl.DataFrame | None, lo_ns: int, hi_ns: int, gaps_ns: np.ndarray
) -> dict[str, tuple[int, int]]:
    """Per position the ``fixture`` log holds within [lo_ns, hi_ns): (ns held there, ns of it inside ``gaps_ns``
    ((k, 2) ns, may overlap)), in the log's order. {} without a log or a gap."""
    if fixture is None or fixture.height == 0 or not len(gaps_ns):
        return {}
    ft = fixture["t_ns"].to_numpy()
    order = np.argsort(ft, kind="stable")
    ft, fp = ft[order], np.asarray(fixture["position"].to_list(), dtype=object)[order]
    a = np.clip(ft, lo_ns, hi_ns)
    b = np.clip(np.append(ft[1:], np.iinfo(np.int64).max), lo_ns, hi_ns)  # each event holds until the next
    g = gaps_ns[np.argsort(gaps_ns[:, 0], kind="stable")]
    merged: list[list[int]] = []
    for x, y in g:  # the union of the gaps (a few spans)
        if merged and x <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], int(y))
        else:
            merged.append([int(x), int(y)])
    m = np.array(merged, dtype=np.int64)
    inside = np.clip(np.minimum(b[:, None], m[None, :, 1]) - np.maximum(a[:, None], m[None, :, 0]), 0, None).sum(axis=1)
    held = b - a
    out = {}
    for name in dict.fromkeys(x for x in fp if x in ALL_POSITIONS):
        mine = fp == name
        if held[mine].sum() > 0:
            out[str(name)] = (int(held[mine].sum()), int(inside[mine].sum()))
    return out


def _held_only_in_gaps(
    fixture: pl.DataFrame | None, lo_ns: int, hi_ns: int, gaps_ns: np.ndarray, min_s: float
) -> list[str]:
    """The positions the ``fixture`` log holds within [lo_ns, hi_ns) that lie in ``gaps_ns`` and are held there for
    less than ``min_s`` outside them: data of them is missing, none can be made. [] without a log."""
    times = _fixture_time_in_gaps(fixture, lo_ns, hi_ns, gaps_ns)
    return [k for k, (held, inside) in times.items() if inside > 0 and held - inside < min_s * _NS]


def _fixture_labels(
    run: Run, t_ns: np.ndarray, pieces, gaps_ns: np.ndarray, unlogged_ns=()
) -> tuple[list[str | None], list[bool]]:
    """The fixture position logged for the middle of each piece (None: no log, MOVING or unknown), and whether
    that event was logged before a gap of the recording (``gaps_ns``, (k, 2) ns) that lies before the piece: the
    fixture log may have lost the events of a move in the gap, so such a label is only believed where the signal
    agrees with it. So is one logged before the start of a stretch the log does not cover (``unlogged_ns``: a file
    of the recording without a fixture log, :attr:`pipeline.run.Run.unlogged_ns`) that begins by the piece's start:
    the piece lies in it or after it."""
    fx = run.fixture
    if fx is None or fx.height == 0 or not pieces:
        return [None] * len(pieces), [False] * len(pieces)
    ft = fx["t_ns"].to_numpy()
    order = np.argsort(ft, kind="stable")
    ft = ft[order]
    fp = np.asarray(fx["position"].to_list(), dtype=object)[order]
    first = np.array([t_ns[a] for a, *_ in pieces], dtype=np.int64)
    mids = np.array([(t_ns[a] + t_ns[b - 1]) // 2 for a, b, *_ in pieces], dtype=np.int64)
    k = np.searchsorted(ft, mids, side="right") - 1
    event = np.where(k >= 0, ft[np.maximum(k, 0)], np.iinfo(np.int64).min)
    # a gap ending after the event and by the piece's first sample: the last gap ending by then starts after it
    stale = np.zeros(len(pieces), dtype=bool)
    if len(gaps_ns):
        g = np.searchsorted(gaps_ns[:, 1], first, side="right") - 1
        ok = g >= 0
        stale[ok] = gaps_ns[g[ok], 0] >= event[ok]
    if len(unlogged_ns):
        starts = np.array(sorted(a for a, _ in unlogged_ns), dtype=np.int64)
        u = np.searchsorted(starts, first, side="right") - 1  # the last such stretch begun by the piece's start
        ok = u >= 0
        stale[ok] |= starts[u[ok]] >= event[ok]
    out = []
    for j in k:
        name = fp[j] if j >= 0 else None
        out.append(name if name in ALL_POSITIONS else None)
    return out, [bool(x) for x in stale]


# ---------------------------------------------------------------------------------------------------------------
# naming


def _name_segments(run: Run, rows: list[dict], settings: SegmentSettings, warnings: list[str]) -> list[dict]:
    """Name each averaged segment (dicts with mean_v, fixture_label, t_start_ns) from the fixture log and gravity.

    Returns per segment a dict: position, source, conflict, direction (unit vector or NaN).
    """
    if not rows:
        return []
    mean_v = np.array([r["mean_v"] for r in rows])
    fix = [r["fixture_label"] for r in rows]
    gain_v_per_g = run.meta.nominal_gain_v_per_g
    gain: np.ndarray | None
    if gain_v_per_g is not None and gain_v_per_g != 0 and np.isfinite(gain_v_per_g):
        gain, offset = _polarity_from_fixture(mean_v, fix, float(gain_v_per_g), warnings), np.zeros(3)
    else:
        gain, offset = _scale_from_fixture(mean_v, fix)
        if gain is None:
            warnings.append(
                "positions unnamed: no nominal_gain_v_per_g in the metadata and no fixture log "
                "labelling positions on every axis"
            )
            nan3 = np.full(3, np.nan)
            return [dict(position=None, source="none", conflict=False, direction=nan3) for _ in rows]

    names = _nearest(mean_v, gain, offset, settings.max_label_angle_deg)
    # refine offsets and gains with the opposite test-position pairs found, then name again
    gain, offset = _refine_scale(mean_v, [n for n, _ in names], fix, gain, offset)
    names = _nearest(mean_v, gain, offset, settings.max_label_angle_deg)

    out = []
    for r, (gname, direction) in zip(rows, names):
        fl = r["fixture_label"]
        agrees = fl is not None and _angle_deg(direction, gravity_vector_g(fl)) <= settings.max_label_angle_deg
        if agrees:
            out.append(dict(position=fl, source="fixture", conflict=False, direction=direction))
            continue
        if fl is not None and r.get("stale"):  # logged before a gap, not what the unit did after it: no label
            out.append(
                dict(
                    position=gname,
                    source="gravity" if gname else "none",
                    conflict=False,
                    direction=direction,
                    fixture_label=None,
                )
            )
            continue
        conflict = fl is not None
        if conflict:
            warnings.append(
                f"fixture label conflict at t_ns={r['t_start_ns']}..{r['t_end_ns']}: fixture log says "
                f"{fl}, the signal says {gname or 'no known position'}; named from gravity"
            )
        out.append(dict(position=gname, source="gravity" if gname else "none", conflict=conflict, direction=direction))
    return out


def _nearest(
    mean_v: np.ndarray, gain: np.ndarray, offset: np.ndarray, max_angle_deg: float
) -> list[tuple[str | None, np.ndarray]]:
    """(nearest position within max_angle_deg or None, unit gravity direction) per row of mean_v."""
    a = (mean_v - offset) / gain
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = a / norm
    out: list[tuple[str | None, np.ndarray]] = []
    for v in d:
        if not np.all(np.isfinite(v)):
            out.append((None, v))
            continue
        name, ang = nearest_position(v)
        out.append((name if ang <= max_angle_deg else None, v))
    return out


def _angle_deg(d: np.ndarray, v: np.ndarray) -> float:
    if not np.all(np.isfinite(d)):
        return np.inf
    c = float(np.dot(d, v) / (np.linalg.norm(d) * np.linalg.norm(v)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _scale_from_fixture(mean_v: np.ndarray, fix: list[str | None]) -> tuple[np.ndarray | None, np.ndarray]:
    """Per-axis gain (V/g, signed) and offset (V) fitted as U_i = g_i a_i + c_i over the fixture-labelled segments.

    Returns (None, zeros) when some axis has no spread of labelled gravity (cannot be estimated).
    """
    rows = [k for k, f in enumerate(fix) if f is not None]
    if len(rows) < 2:
        return None, np.zeros(3)
    a = np.array([gravity_vector_g(f) for f in fix if f is not None])
    u = mean_v[rows]
    gain, offset = np.zeros(3), np.zeros(3)
    for i in range(3):
        if np.ptp(a[:, i]) < 0.5:
            return None, np.zeros(3)
        g, c = np.polyfit(a[:, i], u[:, i], 1)
        gain[i], offset[i] = g, c
    if np.any(gain == 0) or not np.all(np.isfinite(gain)):
        return None, np.zeros(3)
    return gain, offset


def _polarity_from_fixture(
    mean_v: np.ndarray, fix: list[str | None], nominal_v_per_g: float, warnings: list[str]
) -> np.ndarray:
    """The per-axis gains (V/g) to name positions with: ``nominal_v_per_g`` on each axis, or its opposite on every
    axis where the fixture log shows all three outputs with the other sign (a unit wired with the other polarity, or
    a run whose shared ``nominal_gain_v_per_g`` is not this unit's), with a warning. No mounting turns all three axes
    over (that is a mirror image, which gravity naming with the nominal sign would take for the opposite positions:
    TP1 for TP3, every hold in conflict); one axis reversed is found from the label conflicts
    (:func:`pipeline.plausibility.mirrored_axis`), two are what a unit turned 180 degrees reads. The log decides only
    where each axis's fit to its labels has the nominal gain's size (within a factor 1.5)."""
    nominal = np.full(3, nominal_v_per_g)
    shown, _ = _scale_from_fixture(mean_v, fix)
    if shown is None:
        return nominal
    ratio = shown / nominal
    if not np.all((ratio < -0.5) & (ratio > -1.5)):
        return nominal
    warnings.append(
        f"voltmeter: the fixture log's positions show every axis with the opposite sign of nominal_gain_v_per_g "
        f"({nominal_v_per_g:+g} V/g; the labelled holds fit {', '.join(f'{g:+.3g}' for g in shown)} V/g on x, y, "
        "z): the unit is named as the log says (wired with the other polarity, or the metadata's gain not this "
        "unit's?)"
    )
    return -nominal


def _refine_scale(
    mean_v: np.ndarray, gravity_names: list[str | None], fix: list[str | None], gain: np.ndarray, offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Offsets from the midpoints of opposite test-position pairs, each axis's gain from its own vertical pair.

    Names are the gravity names (the fixture label where it agrees with them). Medians over repeated segments.
    """
    names = [f if (f is not None and f == g) else g for f, g in zip(fix, gravity_names)]

    def med(p):
        sel = [k for k, n in enumerate(names) if n == p]
        return np.median(mean_v[sel], axis=0) if sel else None

    per = {p: med(p) for p in TEST_POSITIONS}
    mids = [
        0.5 * (per[hi] + per[lo]) for hi, lo in _OPPOSITE_TP.values() if per[hi] is not None and per[lo] is not None
    ]
    if not mids:
        return gain, offset
    new_offset = np.mean(mids, axis=0)
    new_gain = gain.copy()
    for i, (hi, lo) in _OPPOSITE_TP.items():
        if per[hi] is not None and per[lo] is not None:
            g = 0.5 * (per[hi][i] - per[lo][i])
            if g != 0 and np.sign(g) == np.sign(gain[i]):
                new_gain[i] = g
    return new_gain, new_offset


__all__ = [
    "NO_PLATEAU_WARNING",
    "SegmentSettings",
    "Plateau",
    "TemperatureProgram",
    "classify_temperature",
    "StaticSegment",
    "Segmentation",
    "Channels",
    "BlockStats",
    "find_plateaus",
    "find_static",
    "rolling_std_v",
    "static_threshold_v",
    "finite_rows",
    "finite_columns",
    "segment_run",
]
