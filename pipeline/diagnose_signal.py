"""What ``diagnose`` compares: a recording reduced to its static stretches, as 1 s means and as blocks.

A static stretch is a run of voltmeter samples in one orientation, moves excluded: the untrimmed extents found by
:func:`pipeline.segment.find_static`, so soaks and ramps in one position are one stretch. Each stretch is named by
the segmenter's named static segments lying in it; unnamed stretches are left out (their specific force is unknown).

- :func:`static_record` reduces a run to *micro-samples*: means over ``micro_s`` (1 s) of the static samples of each
  stretch, with their sample count, the thermosensor temperature interpolated to the samples, the nominal specific
  force and position, the direction the temperature last came from (from the chamber setpoint when recorded, else
  the thermosensor), and the moves (start, arrival) between stretches in different positions. Everything downstream
  works on these, so the voltmeter rate changes only the noise of the means (and the cost of this one reduction).
- :func:`make_blocks` groups micro-samples into blocks: ``block_s`` (30 s) inside each stretch, finer (4, 4, 8, 16,
  32 s) at the start of a stretch where the settling after a move lives.
- :func:`sample_noise_v` is the per-sample white noise of each channel from first differences of static samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .effects import SignalContext, first_order_lag, ramp_sign_from_temperature
from .positions import ALL_POSITIONS, MOVING, POSITION_NAMES
from .run import Run
from .segment import Segmentation, SegmentSettings, find_static, for_rate

_NS = 1_000_000_000
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
    for history-dependent effects that must not see the gaps of the moves.
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

    @property
    def size(self) -> int:
        return int(self.t_s.size)

    def context(self, constants, temp_c: np.ndarray | None = None) -> SignalContext:
        """A :class:`SignalContext` over the micro-samples with the given constants model (and temperature)."""
        return SignalContext(t_s=self.t_s, temp_c=self.temp_c if temp_c is None else temp_c, a_g=self.a_g,
                             position_idx=self.position_idx, move_start_s=self.move_start_s, arrive_s=self.arrive_s,
                             constants=constants, normal_temp_c=self.normal_temp_c, ramp_sign=self.ramp_sign,
                             start_ns=self.start_ns)

    def element_temperature_c(self, tau_s: float | None) -> np.ndarray:
        """Temperature (m,) C of a sensing element lagging the thermosensor by ``tau_s`` (None: no lag), computed
        on the whole thermosensor series (the simulator's first-order lag) and read at the micro-samples."""
        if tau_s is None:
            return self.temp_c
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
    """Segmentation settings for the run's voltmeter rate (:func:`pipeline.segment.for_rate`)."""
    return for_rate(base, run.t_ns())


def static_record(run: Run, segmentation: Segmentation, *, micro_s: float = 1.0, edge_margin_s: float = 0.5,
                  settings: SegmentSettings = SegmentSettings()) -> StaticRecord:
    """Reduce ``run`` to micro-sample means of its named static stretches (see the module doc)."""
    warnings: list[str] = []
    t_ns = run.t_ns()
    u_v = run.u_v()
    start_ns = int(t_ns[0])
    t_s = (t_ns - start_ns) / _NS
    rate_hz = 1.0 / float(np.median(np.diff(t_s))) if t_s.size > 1 else 1.0

    stretches, kept = _named_stretches(t_ns, u_v, segmentation, settings, edge_margin_s, warnings)
    finite = np.all(np.isfinite(u_v), axis=1)
    idx_list, sid_list = [], []
    for k, (i0, i1) in enumerate(kept):
        ii = np.arange(i0, i1)
        ii = ii[finite[ii]]
        idx_list.append(ii)
        sid_list.append(np.full(ii.size, k))
    idx = np.concatenate(idx_list) if idx_list else np.zeros(0, int)
    sid = np.concatenate(sid_list) if sid_list else np.zeros(0, int)

    temp_s = _temperature_at(run, t_ns[idx])
    ok = np.isfinite(temp_s)
    idx, sid, temp_s = idx[ok], sid[ok], temp_s[ok]
    sigma = sample_noise_v(u_v[idx], idx, sid)

    # micro-sample bins within each stretch
    t0 = np.array([s.t_start_s for s in stretches]) if stretches else np.zeros(0)
    bin_s = max(micro_s, 1.0 / rate_hz)
    key = sid.astype(np.int64) * (1 << 32) + np.floor((t_s[idx] - t0[sid]) / bin_s).astype(np.int64)
    starts = np.flatnonzero(np.concatenate(([True], np.diff(key) != 0))) if key.size else np.zeros(0, int)
    count = np.diff(np.concatenate((starts, [key.size]))).astype(float)

    def mean(q):
        return np.add.reduceat(q, starts, axis=0) / (count if q.ndim == 1 else count[:, None])

    micro_t = mean(t_s[idx]) if starts.size else np.zeros(0)
    micro_u = mean(u_v[idx]) if starts.size else np.zeros((0, 3))
    micro_temp = mean(temp_s) if starts.size else np.zeros(0)
    micro_sid = sid[starts] if starts.size else np.zeros(0, int)
    pos_idx = np.array([POSITION_NAMES.index(s.position) for s in stretches], dtype=int)
    table = np.array([ALL_POSITIONS[p] for p in POSITION_NAMES])
    micro_pos = pos_idx[micro_sid] if micro_sid.size else np.zeros(0, int)
    move_start_s, arrive_s = _moves(run, t_s, u_v, kept, stretches, start_ns, settings.static_window_s)
    ramp, source, uncertain = _ramp_sign(run, micro_t, start_ns)
    thermo_t_s, thermo_c = _thermosensor(run, start_ns)
    return StaticRecord(
        start_ns=start_ns, normal_temp_c=float(run.meta.normal_temp_c), t_s=micro_t, u_v=micro_u, count=count,
        temp_c=micro_temp, stretch=micro_sid, position_idx=micro_pos, a_g=table[micro_pos] if micro_pos.size
        else np.zeros((0, 3)), ramp_sign=ramp, stretches=stretches, move_start_s=move_start_s, arrive_s=arrive_s,
        sigma_sample_v=sigma, rate_hz=rate_hz, ramp_source=source, ramp_uncertain=uncertain,
        thermo_t_s=thermo_t_s, thermo_c=thermo_c, warnings=warnings)


def _temperature_at(run: Run, t_ns: np.ndarray) -> np.ndarray:
    tt = run.au_temperature["t_ns"].to_numpy()
    temp = run.au_temperature["temp_c"].to_numpy()
    ok = np.isfinite(temp)
    if not ok.any():
        return np.full(t_ns.size, np.nan)
    return np.interp(t_ns.astype(np.float64), tt[ok].astype(np.float64), temp[ok])


def _named_stretches(t_ns, u_v, segmentation: Segmentation, settings: SegmentSettings, margin_s: float,
                     warnings: list[str]) -> tuple[list[Stretch], list[tuple[int, int]]]:
    """Untrimmed static stretches, each named by the segments inside it, less ``margin_s`` at both ends."""
    start_ns = int(t_ns[0])
    raw = find_static(t_ns, u_v, settings)
    seg_mid = np.array([(s.t_start_ns + s.t_end_ns) // 2 for s in segmentation.segments], dtype=np.int64)
    seg_name = [s.position for s in segmentation.segments]
    stretches, kept, unnamed = [], [], 0
    for i0, i1 in raw:
        inside = np.flatnonzero((seg_mid >= t_ns[i0]) & (seg_mid <= t_ns[i1 - 1]))
        names = [seg_name[k] for k in inside if seg_name[k] is not None]
        if not names:
            unnamed += 1
            continue
        name = max(set(names), key=names.count)
        a = int(np.searchsorted(t_ns, t_ns[i0] + margin_s * _NS, side="left"))
        b = int(np.searchsorted(t_ns, t_ns[i1 - 1] - margin_s * _NS, side="right"))
        if b - a < 2:
            continue
        stretches.append(Stretch(len(stretches), name, (t_ns[a] - start_ns) / _NS, (t_ns[b - 1] - start_ns) / _NS,
                                 (t_ns[i0] - start_ns) / _NS))
        kept.append((a, b))
    if unnamed:
        warnings.append(f"{unnamed} static stretch(es) without a position name left out")
    return stretches, kept


def _moves(run: Run, t_s: np.ndarray, u_v: np.ndarray, kept, stretches: list[Stretch], start_ns: int,
           window_s: float) -> tuple[np.ndarray, np.ndarray]:
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
    starts, arrivals = [], []
    for k in range(1, len(stretches)):
        prev, cur = stretches[k - 1], stretches[k]
        if prev.position == cur.position:
            continue
        i_end = kept[k - 1][1]
        move_start = float(t_s[min(i_end, t_s.size - 1)])
        sel = np.flatnonzero((fix_t >= move_start) & (fix_t <= cur.t_start_s + 1.0) & (fix_p != MOVING))
        if sel.size:
            arrive = float(fix_t[sel[-1]])
        else:
            a0, a1 = (np.asarray(ALL_POSITIONS[p], dtype=float) for p in (prev.position, cur.position))
            angle = float(np.arccos(np.clip(a0 @ a1 / (np.linalg.norm(a0) * np.linalg.norm(a1)), -1.0, 1.0)))
            arrive = _arrival_from_signal(t_s, u_v, kept[k - 1], kept[k], angle)
            if arrive is None:
                arrive = cur.detected_start_s - window_s / 2
        starts.append(move_start)
        arrivals.append(max(arrive, move_start))
    return np.asarray(starts, dtype=float), np.asarray(arrivals, dtype=float)


def _arrival_from_signal(t_s: np.ndarray, u_v: np.ndarray, before: tuple[int, int], after: tuple[int, int],
                         angle_rad: float, done: float = 0.999, edge: int = 10) -> float | None:
    """When the outputs between two static stretches (index ranges) have turned through ``done`` of the angle
    between the two positions, s (interpolated between samples).

    The remaining angle is read from the distance to the final outputs: for a rotation through the total angle A,
    |U - U_new| / |U_new - U_old| = sin(r/2) / sin(A/2) with r the angle still to go.
    """
    u_old = np.nanmean(u_v[max(before[0], before[1] - edge):before[1]], axis=0)
    u_new = np.nanmean(u_v[after[0]:min(after[1], after[0] + edge)], axis=0)
    step = float(np.linalg.norm(u_new - u_old))
    if not np.isfinite(step) or step < 1e-3 or angle_rad <= 0:
        return None
    i = np.arange(before[1] - 1, after[0] + 1)
    ratio = np.clip(np.linalg.norm(u_v[i] - u_new, axis=1) / step * np.sin(angle_rad / 2), 0.0, 1.0)
    prog = 1.0 - 2 * np.arcsin(ratio) / angle_rad
    ok = np.isfinite(prog)
    i, prog = i[ok], prog[ok]
    below = np.flatnonzero(prog < done)
    if below.size == 0 or below[-1] + 1 >= prog.size:
        return None
    j = below[-1]
    frac = (done - prog[j]) / (prog[j + 1] - prog[j])
    return float(t_s[i[j]] + frac * (t_s[i[j + 1]] - t_s[i[j]]))


def _thermosensor(run: Run, start_ns: int) -> tuple[np.ndarray, np.ndarray]:
    tt = (run.au_temperature["t_ns"].to_numpy() - start_ns) / _NS
    temp = run.au_temperature["temp_c"].to_numpy()
    ok = np.isfinite(temp)
    return tt[ok], temp[ok]


def _ramp_sign(run: Run, t_s: np.ndarray, start_ns: int, before_s: float = 360.0, after_s: float = 60.0
               ) -> tuple[np.ndarray, str, np.ndarray]:
    """The direction the temperature last came from at ``t_s``, where it came from, and where it is uncertain.

    From the chamber setpoint when it is recorded (exact ramp starts); else from the AU thermosensor, whose ramps
    are found minutes after the setpoint started them: from ``before_s`` before to ``after_s`` after each change of
    direction found there, the direction is marked uncertain.
    """
    none = np.zeros(t_s.size, dtype=bool)
    ch = run.chamber
    if ch is not None and ch.height > 2:
        ts = (ch["t_ns"].to_numpy() - start_ns) / _NS
        sp = ch["setpoint_c"].to_numpy()
        ok = np.isfinite(sp)
        if ok.sum() > 2:
            step = float(np.median(np.diff(ts[ok])))
            sign = ramp_sign_from_temperature(ts[ok], sp[ok], window_s=4.0 * step)
            return _step_at(ts[ok], sign, t_s), "chamber setpoint", none
    tt, temp = _thermosensor(run, start_ns)
    if tt.size < 3:
        return np.zeros(t_s.size), "none", none
    sign = ramp_sign_from_temperature(tt, temp)
    switch = tt[1:][np.diff(sign) != 0]
    if switch.size == 0:
        return _step_at(tt, sign, t_s), "AU thermosensor", none
    k = np.searchsorted(switch, t_s)
    near_next = (k < switch.size) & (switch[np.minimum(k, switch.size - 1)] - t_s <= before_s)
    near_prev = (k > 0) & (t_s - switch[np.maximum(k - 1, 0)] <= after_s)
    return _step_at(tt, sign, t_s), "AU thermosensor", near_next | near_prev


def _step_at(t_src: np.ndarray, values: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """The value of a step function given at ``t_src`` (each value holds until the next) at ``t_s``."""
    i = np.clip(np.searchsorted(t_src, t_s, side="right") - 1, 0, t_src.size - 1)
    return np.asarray(values, dtype=float)[i]


def sample_noise_v(u_v: np.ndarray, sample_idx: np.ndarray, stretch: np.ndarray) -> np.ndarray:
    """Per-sample white noise (3,) V: robust standard deviation of first differences of consecutive static samples
    of one stretch, divided by sqrt(2)."""
    same = (np.diff(sample_idx) == 1) & (np.diff(stretch) == 0)
    if same.sum() < 10:
        return np.full(3, np.nan)
    d = np.diff(u_v, axis=0)[same]
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return np.maximum(1.4826 * mad / np.sqrt(2.0), _NOISE_FLOOR_V)


def temperature_noise_c(run: Run) -> tuple[float, float]:
    """White noise of the AU thermosensor (C, robust, from second differences, which cancel ramps) and its rate
    (Hz)."""
    tt = run.au_temperature["t_ns"].to_numpy()
    temp = run.au_temperature["temp_c"].to_numpy()
    ok = np.isfinite(temp)
    tt, temp = tt[ok], temp[ok]
    if temp.size < 10:
        return 0.0, 1.0
    rate_hz = _NS / float(np.median(np.diff(tt)))
    d2 = temp[2:] - 2 * temp[1:-1] + temp[:-2]
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0)), rate_hz


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
    local = np.where(since < last_fine, np.searchsorted(fine, since, side="right") - 1,
                     len(fine) - 1 + regular)
    key = rec.stretch.astype(np.int64) * (1 << 32) + local.astype(np.int64)
    starts = np.flatnonzero(np.concatenate(([True], np.diff(key) != 0))) if key.size else np.zeros(0, int)
    w = rec.count
    n = np.add.reduceat(w, starts)
    ends = np.concatenate((starts[1:], [rec.size])) - 1

    def mean(q):
        return np.add.reduceat(q * (w if q.ndim == 1 else w[:, None]), starts, axis=0) / (n if q.ndim == 1
                                                                                           else n[:, None])

    return Blocks(starts=starts, weight=w, n=n, t_s=mean(rec.t_s), t_start_s=rec.t_s[starts], t_end_s=rec.t_s[ends],
                  since_start_s=since[starts], temp_c=mean(rec.temp_c), stretch=rec.stretch[starts],
                  position_idx=rec.position_idx[starts], a_g=rec.a_g[starts])


__all__ = ["Stretch", "StaticRecord", "Blocks", "static_record", "segment_settings_for", "make_blocks",
           "sample_noise_v", "temperature_noise_c", "FINE_EDGES_S"]
