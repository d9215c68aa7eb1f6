"""Temperature dynamics shared by the simulator, the effects, the methods, ``apply`` and ``diagnose``: a first-order
lag, the direction the temperature last came from, and the smoothed thermosensor.

- :func:`first_order_lag`: the response y of ``tau dy/dt = x - y`` (the chamber air following its setpoint, the AU
  case following the air, a sensing element lagging its thermosensor), exact for inputs linear between samples.
- :func:`ramp_sign_from_temperature`: +1 after heating, -1 after cooling, 0 before the first ramp, per sample, from a
  recorded temperature series; :func:`ramp_steps` / :func:`ramp_direction`: the same of a whole recording (from the
  chamber setpoint when recorded, else the AU thermosensor), as a step function of time.
- :func:`smooth_temperature`, :class:`Thermosensor`: the thermosensor smoothed (Savitzky-Golay), with its rate and,
  through a lag, the sensing element's temperature.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import CalibrationError
from pipeline.run import NS_PER_S as _NS
from pipeline.run import Run


def first_order_lag(t_s: np.ndarray, x: np.ndarray, tau_s: float, y0: float | None = None) -> np.ndarray:
    """Response y of ``tau dy/dt = x - y`` to ``x`` sampled at ``t_s`` (s), starting from ``y0`` (default x[0]).

    Exact for x linear between samples (first-order-hold discretisation): one ``lfilter`` pass on a uniform grid;
    on a non-uniform one (a logger's irregular readings) the same recursion with each step's own coefficients
    (:func:`_lag_steps`), not a resampling (which would average neighbouring readings: a filter that removes
    noise, which a lag fitted to the data would then take for a signal).
    """
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(x, dtype=float)
    y_start = float(x[0]) if y0 is None and x.size else float(y0 if y0 is not None else np.nan)
    if tau_s <= 0 or x.size < 2:
        return x.copy() if tau_s <= 0 else np.full_like(x, y_start)
    dt = np.diff(t)
    h = float(np.median(dt))
    if not np.allclose(dt, h, rtol=1e-6, atol=1e-9):
        return _lag_steps(t, x, tau_s, y_start)
    a = np.exp(-h / tau_s)
    c = tau_s / h * (1.0 - a)
    b = [1.0 - c, c - a]
    den = [1.0, -a]
    from scipy.signal import lfilter, lfiltic  # ~1 s to import: only where a lag is filtered

    rest, _ = lfilter(b, den, x[1:], zi=lfiltic(b, den, [y_start], [x[0]]))
    return np.concatenate([[y_start], rest])


#: the recursion of a non-uniform lag is summed in closed form over stretches of this many time constants
_LAG_CHUNK_TAU = 500.0


def _lag_steps(t: np.ndarray, x: np.ndarray, tau_s: float, y0: float) -> np.ndarray:
    """:func:`first_order_lag` on a non-uniform grid: y_k = a_k y_(k-1) + u_k with a_k = exp(-dt_k / tau) and u_k
    the first-order hold's input terms for the step dt_k, in closed form y_k = A_k (y_s + sum u_j / A_j) (A the
    decay since the stretch's start s) over stretches of :data:`_LAG_CHUNK_TAU` time constants (1 / A stays below
    e^500), each carrying its last value into the next."""
    dt = np.diff(t)
    a = np.exp(-dt / tau_s)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(dt > 0, tau_s / dt * (1.0 - a), 1.0)  # a step of 0 s: y unchanged (c = a = 1)
    u = (1.0 - c) * x[1:] + (c - a) * x[:-1]
    decay = (t - t[0]) / tau_s  # -log of the decay since the first sample
    y = np.empty(x.size)
    y[0] = y0
    s = 0
    while s < x.size - 1:
        e = max(int(np.searchsorted(decay, decay[s] + _LAG_CHUNK_TAU, side="right")), s + 2)
        e = min(e, x.size)
        d = decay[s + 1 : e] - decay[s]
        if d[-1] > 700.0:  # one step longer than the stretch: nothing is remembered across it
            y[s + 1] = u[s] + (a[s] * y[s] if a[s] > 0 else 0.0)
            s += 1
            continue
        y[s + 1 : e] = np.exp(-d) * (y[s] + np.cumsum(u[s : e - 1] * np.exp(d)))
        s = e - 1
    return y


def ramp_sign_from_temperature(
    t_s: np.ndarray, temp_c: np.ndarray, threshold_c_per_min: float = 0.2, window_s: float = 120.0
) -> np.ndarray:
    """The direction the temperature last came from, per sample: +1 after heating, -1 after cooling, 0 before the
    first ramp (for a signal context's ``ramp_sign`` built from a recording).

    The rate is the difference over ``window_s`` (s); a ramp is where its magnitude exceeds ``threshold_c_per_min``.
    """
    t = np.asarray(t_s, dtype=float)
    temp = np.asarray(temp_c, dtype=float)
    rate_c_per_min = (np.interp(t + window_s / 2, t, temp) - np.interp(t - window_s / 2, t, temp)) / window_s * 60
    ramping = np.abs(rate_c_per_min) > threshold_c_per_min
    last = np.maximum.accumulate(np.where(ramping, np.arange(t.size), -1))
    return np.where(last >= 0, np.sign(rate_c_per_min[np.maximum(last, 0)]), 0.0)


def thermosensor_since(run: Run, start_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """The run's finite thermosensor record in time order: times (s since ``start_ns``) and temperature (C)."""
    tt, temp = run.thermosensor()
    return (tt - start_ns) / _NS, temp


def ramp_steps(run: Run, start_ns: int) -> tuple[np.ndarray, np.ndarray, str]:
    """The direction the temperature last came from as a step function of the whole record: its times (s since
    ``start_ns``), its values (+1 / -1 / 0, each holding until the next) and where it came from. From the chamber
    setpoint when it is recorded, else from the AU thermosensor; no steps ("none") with neither."""
    ch = run.chamber
    if ch is not None and ch.height > 2:
        ts = (ch["t_ns"].to_numpy() - start_ns) / _NS
        sp = ch["setpoint_c"].to_numpy()
        ok = np.isfinite(sp)
        if ok.sum() > 2:
            step = float(np.median(np.diff(ts[ok])))
            return ts[ok], ramp_sign_from_temperature(ts[ok], sp[ok], window_s=4.0 * step), "chamber setpoint"
    tt, temp = thermosensor_since(run, start_ns)
    if tt.size < 3:
        return np.zeros(0), np.zeros(0), "none"
    return tt, ramp_sign_from_temperature(tt, temp), "AU thermosensor"


def ramp_direction(run: Run, start_ns: int) -> Callable[[np.ndarray], np.ndarray]:
    """The direction the temperature last came from (+1 / -1 / 0) as a function of ``t_s`` (s since ``start_ns``),
    by the same rule as a diagnosis (the chamber setpoint when recorded, else the AU thermosensor), found once from
    the whole record: for applying an extended model to a recording a slab of samples at a time."""
    t_src, sign, _ = ramp_steps(run, start_ns)
    if t_src.size == 0:
        return lambda t_s: np.zeros(np.asarray(t_s).size)
    return lambda t_s: step_at(t_src, sign, np.asarray(t_s, dtype=float))


def step_at(t_src: np.ndarray, values: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """The value of a step function given at ``t_src`` (each value holds until the next) at ``t_s``."""
    i = np.clip(np.searchsorted(t_src, t_s, side="right") - 1, 0, t_src.size - 1)
    return np.asarray(values, dtype=float)[i]


def smooth_temperature(t_s: np.ndarray, temp_c: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Savitzky-Golay (quadratic) smoothing of a thermosensor series over ``window_s``: the smoothed temperature
    (C) and its rate (C/min) at ``t_s``. Non-finite samples are dropped (their outputs interpolated); the series is
    resampled to its median step first (the filter needs a uniform grid). Each stretch between two gaps of the
    thermosensor (:func:`pipeline.segment.thermosensor_gaps`) is smoothed by itself: no filter window reaches
    across a gap."""
    t_s = np.asarray(t_s, dtype=float)
    temp_c = np.asarray(temp_c, dtype=float)
    ok = np.isfinite(t_s) & np.isfinite(temp_c)
    if ok.sum() < 5:
        raise CalibrationError("too few thermosensor samples to smooth", stream="au_temperature")
    ts, y0 = t_s[ok], temp_c[ok]
    cuts = stretch_cuts(ts)
    smooth, rate = np.empty(ts.size), np.empty(ts.size)
    for a, b in zip(np.concatenate(([0], cuts + 1)), np.concatenate((cuts + 1, [ts.size]))):
        smooth[a:b], rate[a:b] = _savgol_piece(ts[a:b], y0[a:b], window_s)
    return hermite(t_s, ts, smooth, rate / 60.0, cuts), np.interp(t_s, ts, rate)


def smoothed_noise_span_s(step_s: float, smooth_s: float) -> float:
    """How far (s) the noise of a thermosensor read every ``step_s`` and smoothed over ``smooth_s``
    (:func:`smooth_temperature`, a window of at least five readings) stays correlated: twice the window."""
    return 2.0 * max(float(smooth_s), 5.0 * float(step_s))


def stretch_cuts(t_s: np.ndarray) -> np.ndarray:
    """Indices ``i`` of a thermosensor's sorted reading times ``t_s`` (s) after which comes one of its gaps
    (:func:`pipeline.segment.thermosensor_gaps`' rule): :func:`smooth_temperature` smooths each stretch between two
    by itself, and :func:`hermite` interpolates across them linearly."""
    from pipeline.segment import gap_indices, slope_window_s

    t_s = np.asarray(t_s, dtype=float)
    if t_s.size < 2:
        return np.empty(0, dtype=np.intp)
    t_ns = np.round((t_s - t_s[0]) * _NS).astype(np.int64)
    return gap_indices(t_ns, slope_window_s(t_ns) / 2)


def hermite(
    t_s: np.ndarray, knots_s: np.ndarray, y: np.ndarray, dy_per_s: np.ndarray, cuts: np.ndarray | None = None
) -> np.ndarray:
    """``y`` (given at the sorted ``knots_s``, s, with its derivative ``dy_per_s``) at ``t_s``: a cubic Hermite
    between neighbouring knots, so a curved temperature read once a minute is not cut into straight chords (at the
    end of a 1 C/min ramp a chord between readings a minute apart is off by up to 0.04 C; the cubic by
    thousandths); linear across the intervals after ``cuts`` (the sensor's gaps, where no slope is known: a cubic
    over an hour's gap would swing by tens of C) and held at the ends outside the knots, as ``np.interp``."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(knots_s, dtype=float)
    y = np.asarray(y, dtype=float)
    out = np.interp(t, x, y)
    if x.size < 2:
        return out
    i = np.clip(np.searchsorted(x, t, side="right") - 1, 0, x.size - 2)
    h = x[i + 1] - x[i]
    inside = (t > x[0]) & (t < x[-1]) & (h > 0)
    if cuts is not None and len(cuts):
        gap = np.zeros(x.size - 1, dtype=bool)
        gap[np.asarray(cuts, dtype=np.intp)] = True
        inside &= ~gap[i]
    i, h, tt = i[inside], h[inside], t[inside]
    s = (tt - x[i]) / h
    s2, s3 = s * s, s * s * s
    dy = np.asarray(dy_per_s, dtype=float)
    out[inside] = (
        (2 * s3 - 3 * s2 + 1) * y[i]
        + (s3 - 2 * s2 + s) * h * dy[i]
        + (3 * s2 - 2 * s3) * y[i + 1]
        + (s3 - s2) * h * dy[i + 1]
    )
    return out


def _savgol_piece(ts: np.ndarray, y0: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`smooth_temperature` of one gap-free stretch, at its own samples ``ts``; a stretch too short for the
    filter (under 3 steps of its grid) is its samples as they are, with their mean slope."""
    h = float(np.median(np.diff(ts))) if ts.size > 1 else 0.0
    grid = ts[0] + h * np.arange(int(np.floor((ts[-1] - ts[0]) / h)) + 1) if h > 0 else ts[:1]
    win = min(max(int(round(window_s / h)) | 1, 5), grid.size if grid.size % 2 else grid.size - 1) if h > 0 else 1
    if win < 3:
        slope = (y0[-1] - y0[0]) / (ts[-1] - ts[0]) * 60.0 if ts[-1] > ts[0] else 0.0
        return y0.copy(), np.full(ts.size, slope)
    from scipy.signal import savgol_filter  # ~1 s to import: only where a thermosensor is smoothed

    y = np.interp(grid, ts, y0)
    order = min(2, win - 1)
    smooth = savgol_filter(y, win, order, mode="interp")
    slope = savgol_filter(y, win, order, deriv=1, delta=h, mode="interp")
    return hermite(ts, grid, smooth, slope), np.interp(ts, grid, slope) * 60.0


@dataclass
class Thermosensor:
    """The smoothed thermosensor of a run: times ``t_s`` (s since ``t_ref_ns``), temperature (C), rate (C/min),
    and its gaps ``gaps_s`` ((k, 2) s, :func:`pipeline.segment.thermosensor_gaps`, the voltmeter's time before and
    after the readings included), where neither is known."""

    t_s: np.ndarray
    temp_c: np.ndarray
    rate_c_per_min: np.ndarray
    t_ref_ns: int = 0
    gaps_s: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @classmethod
    def from_run(cls, run, window_s: float, t_ref_ns: int | None = None) -> Thermosensor:
        from pipeline.segment import thermosensor_gaps

        tt_ns = run.au_temperature["t_ns"].to_numpy()
        t_ref = int(run.t_ns()[0]) if t_ref_ns is None else int(t_ref_ns)
        t_s = (tt_ns - t_ref) / _NS
        temp_c = run.au_temperature["temp_c"].to_numpy()
        temp, rate = smooth_temperature(t_s, temp_c, window_s)
        t_v = run.voltmeter["t_ns"]
        within = (int(t_v.min()), int(t_v.max())) if t_v.len() else None
        gaps = (thermosensor_gaps(tt_ns[np.isfinite(temp_c)], within=within) - t_ref) / _NS
        return cls(t_s, temp, rate, t_ref, gaps.reshape(-1, 2))

    def in_gap(self, t_s: np.ndarray) -> np.ndarray:
        """True where ``t_s`` falls inside a gap of the thermosensor (strictly between its two samples)."""
        t_s = np.asarray(t_s, dtype=float)
        out = np.zeros(t_s.shape, dtype=bool)
        if not len(self.gaps_s):
            return out
        k = np.searchsorted(self.gaps_s[:, 0], t_s, side="right") - 1
        ok = k >= 0
        out[ok] = (t_s[ok] > self.gaps_s[k[ok], 0]) & (t_s[ok] < self.gaps_s[k[ok], 1])
        return out

    def at(self, t_s: np.ndarray, lag_tau_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Temperature (the element temperature through a first-order lag ``lag_tau_s`` if > 0) and rate at
        ``t_s``: the temperature interpolated with its slope between readings (:func:`hermite`; the element's
        slope is (T - T_e) / tau), the rate linearly."""
        if lag_tau_s > 0:
            temp = first_order_lag(self.t_s, self.temp_c, lag_tau_s)
            slope = (self.temp_c - temp) / lag_tau_s
        else:
            temp, slope = self.temp_c, self.rate_c_per_min / 60.0
        return (
            hermite(t_s, self.t_s, temp, slope, stretch_cuts(self.t_s)),
            np.interp(t_s, self.t_s, self.rate_c_per_min),
        )


__all__ = [
    "first_order_lag",
    "ramp_sign_from_temperature",
    "thermosensor_since",
    "ramp_steps",
    "ramp_direction",
    "step_at",
    "smooth_temperature",
    "smoothed_noise_span_s",
    "stretch_cuts",
    "hermite",
    "Thermosensor",
]
