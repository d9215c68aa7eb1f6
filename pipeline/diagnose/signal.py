"""What ``diagnose`` compares: a recording reduced to its static stretches, as 1 s means and as blocks.

A static stretch is a run of voltmeter samples in one orientation, moves excluded: the untrimmed extents found by
:func:`pipeline.segment.find_static` (carried by the segmentation), so soaks and ramps in one position are one
stretch. Each stretch is named by the segmenter's named static segments lying in it; unnamed stretches are left out
(their specific force is unknown).

- :func:`static_record` reduces a run to *micro-samples*: means over ``micro_s`` (1 s) of the static samples of each
  stretch, with their sample count, the thermosensor temperature interpolated to the samples, the nominal specific
  force and position, the direction the temperature last came from (from the chamber setpoint when recorded, else
  the thermosensor), and the moves (start, arrival) between stretches in different positions. Everything downstream
  works on these, so the voltmeter rate changes only the noise of the means (and the cost of this one reduction).
- :func:`make_blocks` groups micro-samples into blocks: ``block_s`` (30 s) inside each stretch, finer (4, 4, 8, 16,
  32 s) at the start of a stretch where the settling after a move lives.
- :func:`sample_noise_v` is the per-sample white noise of each channel from first differences of static samples.

Every pass over the samples reads the voltmeter a slab (:data:`SLAB_SAMPLES`, about 1 M samples) at a time
(:meth:`pipeline.run.Run.voltmeter_slab`): per micro-sample sums, the differences for the noise, the move gaps. No
per-sample array of the whole record is made, so a 1 kHz run (59 M samples) costs its table and a few slabs; the
noise's median and MAD are exact order statistics found in passes over the slabs (:func:`exact_medians`), and the
sample step is the median of the whole record's steps, found the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl

from pipeline.dynamics import first_order_lag, ramp_steps, step_at, thermosensor_since
from pipeline.effects.base import SignalContext
from pipeline.positions import ALL_POSITIONS, MOVING, POSITION_NAMES
from pipeline.run import NS_PER_S as _NS
from pipeline.run import SLAB_SAMPLES, Run
from pipeline.segment import Segmentation, SegmentSettings, finite_columns, for_rate, thermosensor_noise_c

#: the smallest per-sample noise assumed (a noise-free or coarsely quantised record still has a finite weight)
_NOISE_FLOOR_V = 1e-9
#: edges of the fine blocks at the start of every stretch, s after its first static sample
FINE_EDGES_S = (0.0, 4.0, 8.0, 16.0, 32.0, 64.0)


@dataclass(frozen=True)
class Stretch:
    """One named static stretch: first and last kept sample (s since the run start), its position, and the first
    sample the static detection found (before the edge margin was cut)."""

    index: int
    position: str
    t_start_s: float
    t_end_s: float
    detected_start_s: float


@dataclass
class StaticRecord:
    """A recording's static samples as micro-sample means (m of them), and what the effects need to know.

    ``t_s`` mean time (s since ``start_ns``, the first voltmeter sample: the unit is powered on when the recording
    starts), ``u_v`` (m, 3) mean outputs (V), ``count`` samples averaged, ``temp_c`` mean thermosensor temperature
    (C), ``stretch`` index into ``stretches``, ``position_idx`` into ``positions.POSITION_NAMES``, ``a_g`` (m, 3)
    the position's nominal specific force (g), ``ramp_sign`` +1 / -1 / 0 after heating / cooling / before the
    first ramp. ``move_start_s`` and ``arrive_s`` are the moves between stretches. ``sigma_sample_v`` (3,) is the
    per-sample noise, ``rate_hz`` the voltmeter rate. ``ramp_source`` says where ``ramp_sign`` came from;
    ``ramp_uncertain`` marks micro-samples near a change of direction found from the thermosensor, whose onset is
    only known to a few minutes. ``thermo_t_s`` / ``thermo_c`` are the whole thermosensor series (finite samples),
    for history-dependent effects that must not see the gaps of the moves. ``model_temp_c`` (m,) C is the
    temperature the passport's own model is evaluated at where it differs from ``temp_c``: the element's, through
    the element lag a passport holds (``rate_terms.lag_tau_s``, the ramp and differential methods); None: ``temp_c``.
    """

    start_ns: int
    normal_temp_c: float
    t_s: np.ndarray
    u_v: np.ndarray
    count: np.ndarray
    temp_c: np.ndarray
    stretch: np.ndarray
    position_idx: np.ndarray
    a_g: np.ndarray
    ramp_sign: np.ndarray
    stretches: list[Stretch]
    move_start_s: np.ndarray
    arrive_s: np.ndarray
    sigma_sample_v: np.ndarray
    rate_hz: float
    ramp_source: str
    ramp_uncertain: np.ndarray
    thermo_t_s: np.ndarray
    thermo_c: np.ndarray
    warnings: list[str] = field(default_factory=list)
    model_temp_c: np.ndarray | None = None

    @property
    def size(self) -> int:
        return int(self.t_s.size)

    def context(self, constants, temp_c: np.ndarray | None = None) -> SignalContext:
        """A :class:`SignalContext` over the micro-samples with the given constants model (and temperature)."""
        return SignalContext(
            t_s=self.t_s,
            temp_c=self.temp_c if temp_c is None else temp_c,
            a_g=self.a_g,
            position_idx=self.position_idx,
            move_start_s=self.move_start_s,
            arrive_s=self.arrive_s,
            constants=constants,
            normal_temp_c=self.normal_temp_c,
            ramp_sign=self.ramp_sign,
            start_ns=self.start_ns,
        )

    def element_temperature_c(self, tau_s: float | None) -> np.ndarray:
        """Temperature (m,) C of a sensing element lagging the thermosensor by ``tau_s``, computed on the whole
        thermosensor series (the simulator's first-order lag) and read at the micro-samples. None: the temperature
        the passport's model is evaluated at (``model_temp_c``: with the passport's own lag, if it holds one)."""
        if tau_s is None:
            return self.temp_c if self.model_temp_c is None else self.model_temp_c
        return np.interp(self.t_s, self.thermo_t_s, first_order_lag(self.thermo_t_s, self.thermo_c, tau_s))


@dataclass
class Blocks:
    """Micro-samples grouped into blocks (B of them), each inside one stretch.

    ``starts`` (B,) index of each block's first micro-sample (blocks are contiguous and in time order), ``n`` (B,)
    voltmeter samples per block, ``t_s`` / ``t_end_s`` (B,) mean time and last micro-sample time, ``since_start_s``
    (B,) time of the block's start after its stretch's start, ``temp_c`` (B,) mean temperature, ``stretch`` and
    ``position_idx`` (B,), ``a_g`` (B, 3).
    """

    starts: np.ndarray
    weight: np.ndarray
    n: np.ndarray
    t_s: np.ndarray
    t_start_s: np.ndarray
    t_end_s: np.ndarray
    since_start_s: np.ndarray
    temp_c: np.ndarray
    stretch: np.ndarray
    position_idx: np.ndarray
    a_g: np.ndarray

    @property
    def size(self) -> int:
        return int(self.starts.size)

    def mean(self, q: np.ndarray) -> np.ndarray:
        """Count-weighted block means of a per-micro-sample quantity ``q`` (m, ...) -> (B, ...)."""
        q = np.asarray(q, dtype=float)
        w = self.weight.reshape((-1,) + (1,) * (q.ndim - 1))
        return np.add.reduceat(q * w, self.starts, axis=0) / self.n.reshape((-1,) + (1,) * (q.ndim - 1))


# ---------------------------------------------------------------------------------------------------------------


def segment_settings_for(run: Run, base: SegmentSettings = SegmentSettings()) -> SegmentSettings:
    """Segmentation settings for the run's voltmeter rate (:func:`pipeline.segment.for_rate`, which
    :func:`pipeline.segment.segment_run` applies too)."""
    return for_rate(base, run.voltmeter["t_ns"])


def static_record(
    run: Run,
    segmentation: Segmentation,
    *,
    micro_s: float = 1.0,
    edge_margin_s: float = 0.5,
    settings: SegmentSettings = SegmentSettings(),
    slab_samples: int | None = None,
) -> StaticRecord:
    """Reduce ``run`` to micro-sample means of its named static stretches (see the module doc).

    The voltmeter is read ``slab_samples`` samples at a time (default :data:`SLAB_SAMPLES`); the result does not
    depend on it beyond float rounding (a micro-sample cut by a slab boundary is summed in two parts)."""
    slab = _slab(slab_samples)
    warnings: list[str] = []
    start_ns = int(run.voltmeter["t_ns"][0])
    rate_hz = 1.0 / _median_step(run, slab) if run.voltmeter.height > 1 else 1.0

    stretches, kept = _named_stretches(run, segmentation, edge_margin_s, warnings)
    thermo_ns, thermo_c = _finite_thermosensor(run)
    if thermo_c.size == 0:  # no temperature to put on any sample: nothing to compare
        kept_ok: list[tuple[int, int]] = []
    else:
        kept_ok = kept
    t0_s = np.array([s.t_start_s for s in stretches]) if stretches else np.zeros(0)
    bin_s = max(micro_s, 1.0 / rate_hz)
    micro_sid, count, micro_t, micro_u, micro_temp = _micro_means(
        run, kept_ok, t0_s, start_ns, bin_s, thermo_ns, thermo_c, slab, 1.0 / rate_hz
    )
    sigma = sample_noise_v(run, kept_ok, slab_samples=slab)

    pos_idx = np.array([POSITION_NAMES.index(s.position) for s in stretches], dtype=int)
    table = np.array([ALL_POSITIONS[p] for p in POSITION_NAMES])
    micro_pos = pos_idx[micro_sid] if micro_sid.size else np.zeros(0, int)
    move_start_s, arrive_s = _moves(run, kept, stretches, start_ns, settings.static_window_s, slab)
    ramp, source, uncertain = _ramp_sign(run, micro_t, start_ns)
    thermo_t_s, thermo_temp_c = thermosensor_since(run, start_ns)
    return StaticRecord(
        start_ns=start_ns,
        normal_temp_c=float(run.meta.normal_temp_c),
        t_s=micro_t,
        u_v=micro_u,
        count=count,
        temp_c=micro_temp,
        stretch=micro_sid,
        position_idx=micro_pos,
        a_g=table[micro_pos] if micro_pos.size else np.zeros((0, 3)),
        ramp_sign=ramp,
        stretches=stretches,
        move_start_s=move_start_s,
        arrive_s=arrive_s,
        sigma_sample_v=sigma,
        rate_hz=rate_hz,
        ramp_source=source,
        ramp_uncertain=uncertain,
        thermo_t_s=thermo_t_s,
        thermo_c=thermo_temp_c,
        warnings=warnings,
    )


def _slab(slab_samples: int | None) -> int:
    slab = SLAB_SAMPLES if slab_samples is None else int(slab_samples)
    if slab < 2:
        raise ValueError(f"slab_samples must be >= 2, got {slab_samples}")
    return slab


def _spans(i0: int, i1: int, slab: int):
    """[s0, s1) slabs of at most ``slab`` samples covering [i0, i1)."""
    return ((s, min(s + slab, i1)) for s in range(int(i0), int(i1), slab))


def _rows_v(run: Run, s0: int, s1: int) -> np.ndarray:
    """Voltmeter samples s0 .. s1 - 1 as an (m, 3) array (V); for short ranges."""
    return np.column_stack(run.voltmeter_slab(s0, s1))


def _t_ns_at(run: Run, idx) -> np.ndarray:
    """Voltmeter times (ns) of the samples ``idx`` (int64)."""
    return run.voltmeter["t_ns"].gather(np.asarray(idx, dtype=np.int64)).to_numpy()


def _median_step(run: Run, slab: int) -> float:
    """Median of the voltmeter's sample steps (s), as ``np.median(np.diff(t_s))`` of the whole record gives it,
    t_s the times in s since the first sample (the rounding of float seconds included)."""
    n = run.voltmeter.height
    start_ns = int(run.voltmeter["t_ns"][0])

    def steps():
        for s0, s1 in _spans(0, n - 1, slab):
            t_ns = run.voltmeter_slab(s0, s1 + 1, ("t_ns",))[0]
            yield [np.diff((t_ns - start_ns) / _NS)]

    count, sample = _count_and_sample(steps, n - 1, 1)
    return float(exact_medians(steps, count, sample)[0])


def _finite_thermosensor(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """The AU thermosensor's finite samples: times (ns, as float64, for interpolation) and temperatures (C)."""
    tt, temp = run.thermosensor()
    return tt.astype(np.float64), temp


def _micro_means(
    run: Run,
    kept: list[tuple[int, int]],
    t0_s: np.ndarray,
    start_ns: int,
    bin_s: float,
    thermo_ns: np.ndarray,
    thermo_c: np.ndarray,
    slab: int,
    step_s: float = 0.0,
):
    """Micro-samples of the finite voltmeter samples in the ``kept`` index ranges (stretch k starting at
    ``t0_s[k]``): bins of ``bin_s`` from the stretch start. Returns per micro-sample the stretch, sample count, mean
    time (s since ``start_ns``), mean outputs (m, 3) V and mean thermosensor temperature (C): each voltmeter sample
    stands for the ``step_s`` (the voltmeter's interval) centred on it, and takes the thermosensor's mean over that
    time (:func:`mean_over`; the interpolation at the sample for a voltmeter as fast as the thermosensor or
    faster): a voltmeter slower than the thermosensor uses every reading once, as the block noise
    of :func:`pipeline.diagnose.diagnosis._block_sigma` counts them, not one in two (whose noise a lag filter over
    all of them would then take for a signal).

    Each slab is summed per bin (``np.add.reduceat``); a bin cut by a slab boundary is the sum of its two parts."""
    sid, bins, cnt, s_t, s_u, s_temp = [], [], [], [], [], []
    for k, (a, b) in enumerate(kept):
        for s0, s1 in _spans(a, b, slab):
            t_ns, *u = run.voltmeter_slab(s0, s1, ("t_ns", "ux", "uy", "uz"))
            fin = finite_columns(u)
            if not fin.all():
                t_ns, u = t_ns[fin], [x[fin] for x in u]
            if t_ns.size == 0:
                continue
            t_s = (t_ns - start_ns) / _NS
            temp = mean_over(t_ns.astype(np.float64), step_s * _NS, thermo_ns, thermo_c)
            b_idx = np.floor((t_s - t0_s[k]) / bin_s).astype(np.int64)
            st = np.flatnonzero(np.concatenate(([True], b_idx[1:] != b_idx[:-1])))
            sid.append(np.full(st.size, k, dtype=np.int64))
            bins.append(b_idx[st])
            cnt.append(np.diff(np.append(st, b_idx.size)))
            s_t.append(np.add.reduceat(t_s, st))
            s_u.append(np.column_stack([np.add.reduceat(x, st) for x in u]))
            s_temp.append(np.add.reduceat(temp, st))
    if not sid:
        return np.zeros(0, int), np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros(0)
    sid_a, bins_a = np.concatenate(sid), np.concatenate(bins)
    key = (sid_a << 32) + bins_a
    first = np.flatnonzero(np.concatenate(([True], key[1:] != key[:-1])))
    count = np.add.reduceat(np.concatenate(cnt), first).astype(float)
    return (
        sid_a[first].astype(int),
        count,
        np.add.reduceat(np.concatenate(s_t), first) / count,
        np.add.reduceat(np.concatenate(s_u), first, axis=0) / count[:, None],
        np.add.reduceat(np.concatenate(s_temp), first) / count,
    )


def mean_over(t: np.ndarray, width: float, knots_t: np.ndarray, knots_y: np.ndarray) -> np.ndarray:
    """The mean of the piecewise-linear interpolation of (``knots_t``, ``knots_y``) over [t - width/2, t + width/2]
    at each ``t`` (any unit of time, float); the interpolation at ``t`` itself for a width no longer than the
    knots' median interval (a sample then stands for no more than one knot: the mean is the interpolation but for
    the curvature between knots) or with fewer than two knots. Outside the knots the end values hold (as
    ``np.interp``)."""
    t = np.asarray(t, dtype=np.float64)
    if knots_t.size < 2 or not width > float(np.median(np.diff(knots_t))):
        return np.interp(t, knots_t, knots_y)
    seg = np.diff(knots_t)
    area = np.concatenate(([0.0], np.cumsum(0.5 * (knots_y[1:] + knots_y[:-1]) * seg)))

    def integral(x):  # of the interpolation from knots_t[0] to x (constant beyond the ends)
        k = np.clip(np.searchsorted(knots_t, x, side="right") - 1, 0, knots_t.size - 2)
        d = np.clip(x, knots_t[0], knots_t[-1]) - knots_t[k]
        slope = (knots_y[k + 1] - knots_y[k]) / seg[k]
        inside = area[k] + knots_y[k] * d + 0.5 * slope * d * d
        return inside + knots_y[0] * np.minimum(x - knots_t[0], 0.0) + knots_y[-1] * np.maximum(x - knots_t[-1], 0.0)

    return (integral(t + width / 2) - integral(t - width / 2)) / width


def _named_stretches(
    run: Run, segmentation: Segmentation, margin_s: float, warnings: list[str]
) -> tuple[list[Stretch], list[tuple[int, int]]]:
    """Untrimmed static stretches, each named by the segments inside it, less ``margin_s`` at both ends."""
    raw = segmentation.stretches
    if not raw:
        return [], []
    t_col = run.voltmeter["t_ns"]
    n = t_col.len()
    start_ns = int(t_col[0])
    margin_ns = int(round(margin_s * _NS))
    i0 = np.array([r[0] for r in raw], dtype=np.int64)
    i1 = np.array([r[1] for r in raw], dtype=np.int64)
    first_ns, last_ns = _t_ns_at(run, i0), _t_ns_at(run, i1 - 1)
    a_all = t_col.search_sorted(pl.Series(first_ns + margin_ns), side="left").to_numpy().astype(np.int64)
    b_all = t_col.search_sorted(pl.Series(last_ns - margin_ns), side="right").to_numpy().astype(np.int64)
    a_ns, b_ns = _t_ns_at(run, np.clip(a_all, 0, n - 1)), _t_ns_at(run, np.clip(b_all - 1, 0, n - 1))
    seg_mid = np.array([(s.t_start_ns + s.t_end_ns) // 2 for s in segmentation.segments], dtype=np.int64)
    seg_name = [s.position for s in segmentation.segments]
    stretches: list[Stretch] = []
    kept: list[tuple[int, int]] = []
    unnamed = 0
    for k in range(len(raw)):
        inside = np.flatnonzero((seg_mid >= first_ns[k]) & (seg_mid <= last_ns[k]))
        names = [nm for j in inside if (nm := seg_name[j]) is not None]
        if not names:
            unnamed += 1
            continue
        name = max(set(names), key=names.count)
        a, b = int(a_all[k]), int(b_all[k])
        if b - a < 2:
            continue
        stretches.append(
            Stretch(
                len(stretches),
                name,
                (a_ns[k] - start_ns) / _NS,
                (b_ns[k] - start_ns) / _NS,
                (first_ns[k] - start_ns) / _NS,
            )
        )
        kept.append((a, b))
    if unnamed:
        warnings.append(f"{unnamed} static stretch(es) without a position name left out")
    return stretches, kept


def _moves(
    run: Run, kept, stretches: list[Stretch], start_ns: int, window_s: float, slab: int
) -> tuple[np.ndarray, np.ndarray]:
    """(start, arrival) in s of every change of position between consecutive stretches.

    The move starts at the first sample after the earlier stretch. It arrives at the fixture log's arrival event
    in the gap when there is one; else when the unit has turned through 99.9 % of the angle between the two
    positions (read from the outputs, interpolated between samples: the end of the motion, whatever its profile);
    else, for a step too small to see, half a static window before the later stretch's first static sample.
    """
    fix_t, fix_p = np.zeros(0), np.zeros(0, dtype=object)
    if run.fixture is not None and run.fixture.height:
        fix_t = (run.fixture["t_ns"].to_numpy() - start_ns) / _NS
        fix_p = np.asarray(run.fixture["position"].to_list(), dtype=object)
    n = run.voltmeter.height
    starts, arrivals = [], []
    for k in range(1, len(stretches)):
        prev, cur = stretches[k - 1], stretches[k]
        if prev.position == cur.position:
            continue
        move_start = float((_t_ns_at(run, [min(kept[k - 1][1], n - 1)]) - start_ns)[0] / _NS)
        sel = np.flatnonzero((fix_t >= move_start) & (fix_t <= cur.t_start_s + 1.0) & (fix_p != MOVING))
        if sel.size:
            arrive = float(fix_t[sel[-1]])
        else:
            a0, a1 = (np.asarray(ALL_POSITIONS[p], dtype=float) for p in (prev.position, cur.position))
            angle = float(np.arccos(np.clip(a0 @ a1 / (np.linalg.norm(a0) * np.linalg.norm(a1)), -1.0, 1.0)))
            found = _arrival_from_signal(run, start_ns, kept[k - 1], kept[k], angle, slab)
            arrive = found if found is not None else cur.detected_start_s - window_s / 2
        starts.append(move_start)
        arrivals.append(max(arrive, move_start))
    return np.asarray(starts, dtype=float), np.asarray(arrivals, dtype=float)


def _arrival_from_signal(
    run: Run,
    start_ns: int,
    before: tuple[int, int],
    after: tuple[int, int],
    angle_rad: float,
    slab: int,
    done: float = 0.999,
    edge_s: float = 1.0,
) -> float | None:
    """When the outputs between two static stretches (index ranges) have turned through ``done`` of the angle
    between the two positions, s since ``start_ns`` (interpolated between samples). The outputs before and after
    are the means over the last and first ``edge_s`` of the two stretches (at least one sample each).

    The remaining angle is read from the distance to the final outputs: for a rotation through the total angle A,
    |U - U_new| / |U_new - U_old| = sin(r/2) / sin(A/2) with r the angle still to go. The gap is read a slab at a
    time from its end: the crossing wanted is the last one.
    """
    t_col = run.voltmeter["t_ns"]
    edge_ns = int(edge_s * _NS)
    b0 = int(t_col.search_sorted(int(t_col[before[1] - 1]) - edge_ns, side="right"))
    a1 = int(t_col.search_sorted(int(t_col[after[0]]) + edge_ns, side="left"))
    u_old = np.nanmean(_rows_v(run, min(max(before[0], b0), before[1] - 1), before[1]), axis=0)
    u_new = np.nanmean(_rows_v(run, after[0], max(min(after[1], a1), after[0] + 1)), axis=0)
    step = float(np.linalg.norm(u_new - u_old))
    if not np.isfinite(step) or step < 1e-3 or angle_rad <= 0:
        return None
    lo, hi = before[1] - 1, after[0] + 1
    later = None  # (t_s, progress) of the first finite sample after the slab in hand
    for s1 in range(hi, lo, -slab):
        s0 = max(lo, s1 - slab)
        t_ns, *u = run.voltmeter_slab(s0, s1, ("t_ns", "ux", "uy", "uz"))
        ratio = np.clip(np.linalg.norm(np.column_stack(u) - u_new, axis=1) / step * np.sin(angle_rad / 2), 0.0, 1.0)
        prog = 1.0 - 2 * np.arcsin(ratio) / angle_rad
        ok = np.isfinite(prog)
        t_s, prog = (t_ns[ok] - start_ns) / _NS, prog[ok]
        below = np.flatnonzero(prog < done)
        if below.size:
            j = below[-1]
            if j + 1 < prog.size:
                t_next, p_next = t_s[j + 1], prog[j + 1]
            elif later is not None:
                t_next, p_next = later
            else:
                return None
            frac = (done - prog[j]) / (p_next - prog[j])
            return float(t_s[j] + frac * (t_next - t_s[j]))
        if prog.size:
            later = (t_s[0], prog[0])
    return None


def _ramp_sign(
    run: Run, t_s: np.ndarray, start_ns: int, before_s: float = 360.0, after_s: float = 60.0
) -> tuple[np.ndarray, str, np.ndarray]:
    """The direction the temperature last came from at ``t_s``, where it came from, and where it is uncertain.

    From the chamber setpoint when it is recorded (exact ramp starts); else from the AU thermosensor, whose ramps
    are found minutes after the setpoint started them: from ``before_s`` before to ``after_s`` after each change of
    direction found there, the direction is marked uncertain.
    """
    none = np.zeros(t_s.size, dtype=bool)
    t_src, sign, source = ramp_steps(run, start_ns)
    if source == "none":
        return np.zeros(t_s.size), source, none
    if source == "chamber setpoint":
        return step_at(t_src, sign, t_s), source, none
    switch = t_src[1:][np.diff(sign) != 0]
    if switch.size == 0:
        return step_at(t_src, sign, t_s), source, none
    k = np.searchsorted(switch, t_s)
    near_next = (k < switch.size) & (switch[np.minimum(k, switch.size - 1)] - t_s <= before_s)
    near_prev = (k > 0) & (t_s - switch[np.maximum(k - 1, 0)] <= after_s)
    return step_at(t_src, sign, t_s), source, near_next | near_prev


def sample_noise_v(run: Run, ranges: list[tuple[int, int]], *, slab_samples: int | None = None) -> np.ndarray:
    """Per-sample white noise (3,) V: robust standard deviation (1.4826 MAD) of the first differences of consecutive
    finite voltmeter samples inside each index range [i0, i1), divided by sqrt(2); NaN with fewer than 10 of them.

    The differences are never held whole: their median and MAD are exact order statistics found slab by slab
    (:func:`exact_medians`)."""
    slab = _slab(slab_samples)

    def differences():
        for a, b in ranges:
            for s0, s1 in _spans(a, b - 1, slab):  # pairs (i, i + 1), a <= i < b - 1
                u = run.voltmeter_slab(s0, s1 + 1)
                fin = finite_columns(u)
                both = fin[1:] & fin[:-1]
                yield [np.diff(x) for x in u] if both.all() else [np.diff(x)[both] for x in u]

    n, sample = _count_and_sample(differences, sum(max(b - a - 1, 0) for a, b in ranges), 3)
    if n < 10:
        return np.full(3, np.nan)
    med = exact_medians(differences, n, sample)
    mad = exact_medians(
        lambda: ([np.abs(x - m) for x, m in zip(d, med)] for d in differences()),
        n,
        [np.abs(x - m) for x, m in zip(sample, med)],
    )
    return np.maximum(1.4826 * mad / np.sqrt(2.0), _NOISE_FLOOR_V)


# ---------------------------------------------------------------------------------------------------------------
# exact medians of long series, a slab at a time

#: values in the sample that brackets the middle ranks (a bracket holds about 2 * _BRACKET_Z / sqrt(that) of all)
_SAMPLE_SIZE = 1 << 17
_BRACKET_Z = 4.0


def _count_and_sample(slabs, n_max: int, c: int) -> tuple[int, list[np.ndarray]]:
    """Number of values per series in the slabs (each slab: ``c`` 1-D arrays of one length, one per series) and
    every k-th value of each slab (about ``_SAMPLE_SIZE`` in all when there are ``n_max``)."""
    every = max(1, n_max // _SAMPLE_SIZE)
    n = 0
    parts: list[list[np.ndarray]] = [[] for _ in range(c)]
    for cols in slabs():
        n += cols[0].size
        for part, x in zip(parts, cols):
            part.append(x[::every].copy())
    return n, [np.concatenate(p) if p else np.zeros(0) for p in parts]


def exact_medians(slabs, n: int, sample: list[np.ndarray]) -> np.ndarray:
    """Medians (c,) of c long series of n values each, delivered in slabs, equal to ``np.median`` of each series.

    ``slabs()`` returns an iterable of slabs, each c 1-D float arrays of one length (the same slabs at every call; no
    NaN); ``sample`` is some of the values of each series (c arrays). The sample's quantiles bracket the middle
    ranks; one pass counts the values below and at each bracket end and keeps those strictly inside, from which the
    middle ranks are selected (``np.partition``); where a bracket missed them it is widened (4x) and the pass
    repeated, up to the whole range. Memory: the values inside the brackets, about 2 % of the series.
    """
    c = len(sample)
    out = np.full(c, np.nan)
    if n == 0:
        return out
    ranks = ((n - 1) // 2, n // 2)
    todo = list(range(c))
    half = _BRACKET_Z / np.sqrt(max(min(s.size for s in sample), 1))
    while todo:
        lo = {j: np.quantile(sample[j], 0.5 - half) if half < 0.5 else -np.inf for j in todo}
        hi = {j: np.quantile(sample[j], 0.5 + half) if half < 0.5 else np.inf for j in todo}
        below, at_lo, at_hi = dict.fromkeys(todo, 0), dict.fromkeys(todo, 0), dict.fromkeys(todo, 0)
        inside: dict[int, list[np.ndarray]] = {j: [] for j in todo}
        for cols in slabs():
            for j in todo:
                x = cols[j]
                below[j] += int(np.count_nonzero(x < lo[j]))
                at_lo[j] += int(np.count_nonzero(x == lo[j]))
                if hi[j] > lo[j]:
                    at_hi[j] += int(np.count_nonzero(x == hi[j]))
                    inside[j].append(x[(x > lo[j]) & (x < hi[j])])
        missed = []
        for j in todo:
            vals = np.concatenate(inside[j]) if inside[j] else np.zeros(0)
            # sorted, the values are: below | == lo | inside (vals) | == hi | above
            e_lo = below[j] + at_lo[j]
            e_in = e_lo + vals.size
            if ranks[0] < below[j] or ranks[1] >= e_in + at_hi[j]:
                missed.append(j)
                continue
            kth = sorted({r - e_lo for r in ranks if e_lo <= r < e_in})
            part = np.partition(vals, kth) if kth else vals
            pick = [lo[j] if r < e_lo else part[r - e_lo] if r < e_in else hi[j] for r in ranks]
            out[j] = (pick[0] + pick[1]) / 2
        todo = missed
        half *= 4.0
    return out


def temperature_noise_c(run: Run) -> tuple[float, float]:
    """White noise of the AU thermosensor (C, robust, from second differences, which cancel ramps) and its rate
    (Hz)."""
    tt, temp = run.thermosensor()
    if temp.size < 10:
        return 0.0, 1.0
    rate_hz = _NS / float(np.median(np.diff(tt)))
    return thermosensor_noise_c(temp), rate_hz


def make_blocks(rec: StaticRecord, block_s: float = 30.0, fine_edges_s=FINE_EDGES_S) -> Blocks:
    """Group the micro-samples of ``rec`` into blocks (see the module doc); a last block shorter than half
    ``block_s`` joins the one before it."""
    t0 = np.array([s.t_start_s for s in rec.stretches])
    t1 = np.array([s.t_end_s for s in rec.stretches])
    since = rec.t_s - t0[rec.stretch]
    fine = np.asarray(fine_edges_s, dtype=float)
    last_fine = fine[-1]
    # block number inside the stretch: fine blocks first, then regular ones from the last fine edge
    regular = np.floor((since - last_fine) / block_s)
    n_regular = np.floor((t1[rec.stretch] - t0[rec.stretch] - last_fine) / block_s)
    tail_short = (t1[rec.stretch] - t0[rec.stretch] - last_fine - n_regular * block_s) < block_s / 2
    regular = np.where(tail_short & (regular >= n_regular) & (n_regular >= 1), n_regular - 1, regular)
    local = np.where(since < last_fine, np.searchsorted(fine, since, side="right") - 1, len(fine) - 1 + regular)
    key = rec.stretch.astype(np.int64) * (1 << 32) + local.astype(np.int64)
    starts = np.flatnonzero(np.concatenate(([True], np.diff(key) != 0))) if key.size else np.zeros(0, int)
    w = rec.count
    n = np.add.reduceat(w, starts)
    ends = np.concatenate((starts[1:], [rec.size])) - 1

    def mean(q):
        return np.add.reduceat(q * (w if q.ndim == 1 else w[:, None]), starts, axis=0) / (
            n if q.ndim == 1 else n[:, None]
        )

    return Blocks(
        starts=starts,
        weight=w,
        n=n,
        t_s=mean(rec.t_s),
        t_start_s=rec.t_s[starts],
        t_end_s=rec.t_s[ends],
        since_start_s=since[starts],
        temp_c=mean(rec.temp_c),
        stretch=rec.stretch[starts],
        position_idx=rec.position_idx[starts],
        a_g=rec.a_g[starts],
    )


__all__ = [
    "Stretch",
    "StaticRecord",
    "Blocks",
    "static_record",
    "segment_settings_for",
    "make_blocks",
    "sample_noise_v",
    "temperature_noise_c",
    "exact_medians",
    "FINE_EDGES_S",
    "SLAB_SAMPLES",
]
