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
from dataclasses import dataclass

import numpy as np

from pipeline.errors import CalibrationError
from pipeline.run import NS_PER_S as _NS
from pipeline.run import Run


def first_order_lag(t_s: np.ndarray, x: np.ndarray, tau_s: float, y0: float | None = None) -> np.ndarray:
    """Response y of ``tau dy/dt = x - y`` to ``x`` sampled at ``t_s`` (s), starting from ``y0`` (default x[0]).

    Exact for x linear between samples (first-order-hold discretisation, one ``lfilter`` pass). A non-uniform grid
    is resampled to its median step and back.
    """
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(x, dtype=float)
    y_start = float(x[0]) if (y0 is None and x.size) else y0
    if tau_s <= 0 or x.size < 2:
        return x.copy() if tau_s <= 0 else np.full_like(x, y_start)
    dt = np.diff(t)
    h = float(np.median(dt))
    if not np.allclose(dt, h, rtol=1e-6, atol=1e-9):
        grid = t[0] + h * np.arange(int(np.ceil((t[-1] - t[0]) / h)) + 1)
        return np.interp(t, grid, first_order_lag(grid, np.interp(grid, t, x), tau_s, y_start))
    a = np.exp(-h / tau_s)
    c = tau_s / h * (1.0 - a)
    b = [1.0 - c, c - a]
    den = [1.0, -a]
    from scipy.signal import lfilter, lfiltic  # ~1 s to import: only where a lag is filtered

    rest, _ = lfilter(b, den, x[1:], zi=lfiltic(b, den, [y_start], [x[0]]))
    return np.concatenate([[y_start], rest])


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
    resampled to its median step first (the filter needs a uniform grid)."""
    t_s = np.asarray(t_s, dtype=float)
    temp_c = np.asarray(temp_c, dtype=float)
    ok = np.isfinite(t_s) & np.isfinite(temp_c)
    if ok.sum() < 5:
        raise CalibrationError("too few thermosensor samples to smooth", stream="au_temperature")
    ts, y0 = t_s[ok], temp_c[ok]
    h = float(np.median(np.diff(ts)))
    grid = ts[0] + h * np.arange(int(np.floor((ts[-1] - ts[0]) / h)) + 1)
    y = np.interp(grid, ts, y0)
    win = min(max(int(round(window_s / h)) | 1, 5), grid.size if grid.size % 2 else grid.size - 1)
    from scipy.signal import savgol_filter  # ~1 s to import: only where a thermosensor is smoothed

    smooth = savgol_filter(y, win, 2, mode="interp")
    rate = savgol_filter(y, win, 2, deriv=1, delta=h, mode="interp") * 60.0
    return np.interp(t_s, grid, smooth), np.interp(t_s, grid, rate)


@dataclass
class Thermosensor:
    """The smoothed thermosensor of a run: times ``t_s`` (s since ``t_ref_ns``), temperature (C), rate (C/min)."""

    t_s: np.ndarray
    temp_c: np.ndarray
    rate_c_per_min: np.ndarray
    t_ref_ns: int = 0

    @classmethod
    def from_run(cls, run, window_s: float, t_ref_ns: int | None = None) -> Thermosensor:
        tt_ns = run.au_temperature["t_ns"].to_numpy()
        t_ref = int(run.t_ns()[0]) if t_ref_ns is None else int(t_ref_ns)
        t_s = (tt_ns - t_ref) / _NS
        temp, rate = smooth_temperature(t_s, run.au_temperature["temp_c"].to_numpy(), window_s)
        return cls(t_s, temp, rate, t_ref)

    def at(self, t_s: np.ndarray, lag_tau_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Temperature (the element temperature through a first-order lag ``lag_tau_s`` if > 0) and rate at
        ``t_s``, interpolated."""
        temp = first_order_lag(self.t_s, self.temp_c, lag_tau_s) if lag_tau_s > 0 else self.temp_c
        return np.interp(t_s, self.t_s, temp), np.interp(t_s, self.t_s, self.rate_c_per_min)


__all__ = [
    "first_order_lag",
    "ramp_sign_from_temperature",
    "thermosensor_since",
    "ramp_steps",
    "ramp_direction",
    "step_at",
    "smooth_temperature",
    "Thermosensor",
]
