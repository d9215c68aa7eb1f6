"""Temperature dynamics shared by the simulator, the effects and the methods: a first-order lag and the direction
the temperature last came from.

- :func:`first_order_lag`: the response y of ``tau dy/dt = x - y`` (the chamber air following its setpoint, the AU
  case following the air, a sensing element lagging its thermosensor), exact for inputs linear between samples.
- :func:`ramp_sign_from_temperature`: +1 after heating, -1 after cooling, 0 before the first ramp, per sample, from a
  recorded temperature series.
"""

from __future__ import annotations

import numpy as np


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


__all__ = ["first_order_lag", "ramp_sign_from_temperature"]
