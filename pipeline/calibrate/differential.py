"""Differential specific-force thermal calibration (seed 003, Zhuo and Du).

After a normal-temperature calibration (K0, U0 at T0, e.g. a six-position passport), the unit sits in a chamber at a
few roughly known orientations -- no precise positioning, fixture face errors of a degree or more -- while the
temperature cycles. At one orientation the specific force a does not change, so the difference of a channel's
output between two times at that orientation holds only the temperature-induced change of its constants:

    (U_c(t2) - U_c(t1)) / K0_cc = a_c [s(t2) - s(t1)] + sum_{j != c} (K0_cj / K0_cc) a_j [g_cj(t2) - g_cj(t1)]
                                  + [b(t2) - b(t1)] / K0_cc

with the relative scale-factor change s, the bias change b (V) and the relative cross-axis changes g_cj, each a
polynomial in dT = T - T0 (order up to 3) plus terms in the temperature rate r = dT/dt (order up to 2):

    s  = sum_m beta_m dT^m   + sum_n sum_k beta~_nk  r^n dT^k
    b  = sum_m alpha_m dT^m  + sum_n sum_k alpha~_nk r^n dT^k          (k = 0 only in the paper)
    g_cj = sum_m gamma_cjm dT^m

The specific force a is not known precisely, but it multiplies only small changes, so the orientation's mean output
with the normal-temperature constants, a0 = K0^-1 (U - U0) (the paper's F^p), stands in for it. a0 carries the mean
temperature error of the window (mg uncompensated), which multiplies the scale change; ``refine_passes`` refits with
the windows' compensated mean instead (a micro-g effect). The paper fits s and b per axis (its quartz-flexure units have
negligible cross-axis temperature terms). This project adds, as options:

- the cross-axis terms g_cj for the axes j the orientations excite (``cross_axis``, on by default: seed 000's unit
  has gamma up to 6e-3 /C on cross-axis terms of 0.03 of the gain, about 1 mg of cross-axis change over 50 C);
- rate terms times dT^k (``rate_dt_order``): a lag of the sensing element behind the thermosensor makes
  b(T_e) = b(T - tau r) ~ b(T) - tau r b'(T), whose factor b'(T) changes with T when b is curved;
- the lag itself (``lag_fit``): the polynomials evaluated at the element temperature T_e, the thermosensor through a
  first-order lag tau (tau dT_e/dt = T - T_e), with tau fitted (a one-dimensional search around the linear fit).
  The paper's rate terms are the first-order expansion of this; the lag model also holds at the ends of ramps,
  where dT/dt changes within tau.

Processing as in the paper: the outputs are averaged over ``block_s`` (10 s) blocks and the thermosensor smoothed
(Savitzky-Golay over ``temp_smooth_s``, which also gives the rate); each orientation window (a static stretch of the
run) is split into halves and block i of the first half is differenced with block i of the second (equal spacing,
the longest baseline); least squares over all orientations, per channel.

The result maps onto the passport: alpha (bias, V/C^m), beta (scale, 1/C^m) and gamma (cross-axis, 1/C^m) of the
polynomial thermal model, and the rate terms and lag in an extra field ``rate_terms`` that
:func:`compensate_differential` applies (``pipeline.compensate`` works on the same passport without them).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import lstsq as scipy_lstsq
from scipy.optimize import minimize_scalar
from scipy.signal import savgol_filter

from pipeline.calibrate.method import Fitted, Method, Support
from pipeline.calibrate.observations import ObservedRun, observe_run, unit_of
from pipeline.calibrate.recording import Recording, axis_roles
from pipeline.calibrate.result import UnitFit, base_reference
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.dynamics import first_order_lag
from pipeline.errors import CalibrationError
from pipeline.model import specific_force_g
from pipeline.passport.document import load_passport
from pipeline.positions import AXES, is_verification_position
from pipeline.run import NS_PER_S as _NS
from pipeline.thermal import DifferentialModel, PolynomialModel, RateTerms, rate_basis
from pipeline.uncertainty import ThermalSigma, as_json_list, regression_cov

#: residuals of differenced pairs whose first blocks lie in one stretch of this length (s) of a window count as
#: correlated when the coefficients' uncertainties are estimated (a misfit that follows the temperature cycle)
CLUSTER_S = 1800.0


@dataclass(frozen=True)
class DifferentialSettings:
    """Model orders and the smoothing of seed 003's method (the paper: polynomial order 3, rate order 2)."""

    poly_order: int = 3  # scale factor, bias (and cross-axis) polynomial in dT, 1..3
    rate_order: int = 2  # terms in r^n, n = 1..rate_order (0: none)
    rate_dt_order: int = 0  # rate terms also times dT^k, k = 1..rate_dt_order (0: the paper's model)
    cross_axis: bool = True  # fit the cross-axis temperature terms the orientations excite
    lag_fit: bool = False  # evaluate the polynomials at the lagged element temperature, tau fitted
    lag_max_s: float = 1800.0  # search range of tau (s)
    block_s: float = 10.0  # outputs averaged over blocks of this length (s)
    temp_smooth_s: float = 301.0  # Savitzky-Golay window of the thermosensor, for T and r (s)
    min_window_s: float = 3600.0  # shortest orientation window used (s)
    trim_s: float = 60.0  # dropped at both ends of each orientation window (s)
    max_turn_deg: float = 2.0  # static stretches closer than this in gravity direction are one orientation
    min_excitation: float = 0.2  # smallest singular value per sqrt(windows) of [1, a_c, a_j] to fit a term
    refine_passes: int = 1  # refits with each window's specific force from the previous fit's compensation
    cross_axis_abs: bool = False  # cross-axis terms also where K0_cj is 0 (unknown), as absolute dK_cj (V/g/C^m)
    select_model: bool = False  # choose poly_order (1..poly_order) and cross-axis terms by two-fold validation

    def __post_init__(self):
        if not 1 <= self.poly_order <= 3:
            raise ValueError(f"poly_order must be 1..3, got {self.poly_order}")
        if not 0 <= self.rate_order <= 2:
            raise ValueError(f"rate_order must be 0..2, got {self.rate_order}")
        if not 0 <= self.rate_dt_order <= 2:
            raise ValueError(f"rate_dt_order must be 0..2, got {self.rate_dt_order}")
        if not self.block_s > 0 or not self.temp_smooth_s > 0 or not self.lag_max_s > 0:
            raise ValueError("block_s, temp_smooth_s and lag_max_s must be positive")


# ---------------------------------------------------------------------------------------------------------------
# The thermosensor, smoothed


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


# ---------------------------------------------------------------------------------------------------------------
# Orientation windows and block averages


@dataclass(frozen=True)
class OrientationWindow:
    """One orientation held through (part of) a temperature cycle: sample range [i0, i1) of the voltmeter, times,
    the mean specific force with the normal-temperature constants (g) and the temperature range covered (C)."""

    index: int
    i0: int
    i1: int
    t_start_ns: int
    t_end_ns: int
    a0_g: tuple[float, float, float]
    temp_min_c: float
    temp_max_c: float

    def to_dict(self) -> dict:
        return {
            "t_start_ns": self.t_start_ns,
            "t_end_ns": self.t_end_ns,
            "a0_g": list(self.a0_g),
            "temp_min_c": round(self.temp_min_c, 3),
            "temp_max_c": round(self.temp_max_c, 3),
            "duration_s": round((self.t_end_ns - self.t_start_ns) / _NS, 1),
        }


def orientation_windows(
    t_ns: np.ndarray,
    u_v: np.ndarray,
    temp_c: np.ndarray,
    K0: np.ndarray,
    U0: np.ndarray,
    settings: DifferentialSettings = DifferentialSettings(),
) -> list[OrientationWindow]:
    """The orientation windows of a run: static stretches (``pipeline.segment.find_static``, windows for the rate)
    joined while the
    gravity direction stays within ``max_turn_deg``, trimmed by ``trim_s`` at both ends, at least
    ``min_window_s`` long. ``temp_c`` (n,) is the temperature at the voltmeter samples."""
    from pipeline.segment import SegmentSettings, find_static, for_rate

    groups: list[list[int]] = []
    last_dir = None
    for i0, i1 in find_static(t_ns, u_v, for_rate(SegmentSettings(), t_ns)):
        a = specific_force_g(K0, U0, np.nanmean(u_v[i0:i1], axis=0))
        d = a / np.linalg.norm(a)
        if last_dir is not None and np.degrees(np.arccos(np.clip(d @ last_dir, -1, 1))) <= settings.max_turn_deg:
            groups[-1][1] = i1
        else:
            groups.append([i0, i1])
        last_dir = d
    out = []
    for i0, i1 in groups:
        j0 = int(np.searchsorted(t_ns, t_ns[i0] + settings.trim_s * _NS))
        j1 = int(np.searchsorted(t_ns, t_ns[i1 - 1] - settings.trim_s * _NS, side="right"))
        if j1 <= j0 or (t_ns[j1 - 1] - t_ns[j0]) < settings.min_window_s * _NS:
            continue
        a0 = specific_force_g(K0, U0, np.nanmean(u_v[j0:j1], axis=0))
        out.append(
            OrientationWindow(
                len(out),
                j0,
                j1,
                int(t_ns[j0]),
                int(t_ns[j1 - 1]),
                tuple(float(x) for x in a0),
                float(np.nanmin(temp_c[j0:j1])),
                float(np.nanmax(temp_c[j0:j1])),
            )
        )
    return out


@dataclass
class BlockData:
    """Block averages of a run in its orientation windows: block centre times ``t_s`` (m,) in s since the
    thermosensor's ``t_ref_ns``, outputs ``u_v`` (m, 3) V, the window of each block (m,), the windows, and the
    smoothed thermosensor."""

    t_s: np.ndarray
    u_v: np.ndarray
    window: np.ndarray
    windows: list[OrientationWindow]
    sensor: Thermosensor
    run_id: str = ""
    #: the constants (K0 (3, 3) V/g, U0 (3,) V) the windows' specific force was computed with
    constants: tuple[np.ndarray, np.ndarray] | None = None
    #: (m, 3) V^2, the variance of each block mean from the voltmeter noise measured in the block: the residual
    #: sum of squares about the block's straight line in time over (n - 2), divided by n
    u_var_v2: np.ndarray | None = None

    def a0_g(self) -> np.ndarray:
        """(n_windows, 3) mean specific force of each window with the normal-temperature constants."""
        return np.array([w.a0_g for w in self.windows])

    def temperature(self, lag_tau_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Temperature (element temperature with a lag) and rate at the block centres."""
        return self.sensor.at(self.t_s, lag_tau_s)


def block_data(
    run, K0: np.ndarray, U0: np.ndarray, settings: DifferentialSettings = DifferentialSettings()
) -> BlockData:
    """Orientation windows of ``run`` and the ``block_s`` averages of its outputs in them. Blocks with fewer than
    80 % of their samples are dropped. Raises CalibrationError when the run has no orientation window."""
    t_ns = run.t_ns()
    u_v = run.u_v()
    sensor = Thermosensor.from_run(run, settings.temp_smooth_s)
    t_s = (t_ns - sensor.t_ref_ns) / _NS
    windows = orientation_windows(t_ns, u_v, sensor.at(t_s)[0], K0, U0, settings)
    if not windows:
        raise CalibrationError(
            f"no orientation held for {settings.min_window_s:.0f} s or more (the differential "
            "method needs the unit static at a few orientations through a temperature cycle)",
            path=run.source or None,
            stream="voltmeter",
        )
    idx = np.concatenate([np.arange(w.i0, w.i1) for w in windows])
    win = np.concatenate([np.full(w.i1 - w.i0, w.index) for w in windows])
    start_s = np.array([(w.t_start_ns - sensor.t_ref_ns) / _NS for w in windows])
    block = np.floor((t_s[idx] - start_s[win]) / settings.block_s).astype(np.int64)
    key = win.astype(np.int64) * (1 << 40) + block
    ok = np.isfinite(u_v[idx]).all(axis=1)
    idx, win, key = idx[ok], win[ok], key[ok]
    bounds = np.concatenate(([0], np.flatnonzero(np.diff(key)) + 1))
    counts = np.diff(np.append(bounds, key.size))
    step_s = float(np.median(np.diff(t_s))) if t_s.size > 1 else settings.block_s
    full = counts >= 0.8 * settings.block_s / step_s
    u_b = np.add.reduceat(u_v[idx], bounds, axis=0) / counts[:, None]
    t_b = np.add.reduceat(t_s[idx], bounds) / counts
    # the noise in each block: the scatter about a straight line in time (a ramp moves the output within a block)
    dev = u_v[idx] - np.repeat(u_b, counts, axis=0)
    tc = t_s[idx] - np.repeat(t_b, counts)
    stt = np.add.reduceat(tc**2, bounds)
    slope = np.add.reduceat(tc[:, None] * dev, bounds, axis=0) / np.where(stt > 0, stt, 1.0)[:, None]
    dev = dev - np.repeat(slope, counts, axis=0) * tc[:, None]
    var_b = np.add.reduceat(dev**2, bounds, axis=0) / np.maximum(counts - 2, 1)[:, None] / counts[:, None]
    return BlockData(
        t_s=t_b[full],
        u_v=u_b[full],
        window=win[bounds][full],
        windows=windows,
        sensor=sensor,
        run_id=run.meta.run_id,
        constants=(np.asarray(K0, float), np.asarray(U0, float)),
        u_var_v2=var_b[full],
    )


# ---------------------------------------------------------------------------------------------------------------
# The fit


@dataclass
class DifferentialFit:
    """Result of :func:`fit_differential`: the model, which terms each channel has, and the fit's residuals.

    ``terms[c]`` lists the fitted terms of channel c (``bias``, ``scale``, ``cross_x``..., ``bias_rate``,
    ``scale_rate``); ``residual_rms_g`` (3,) the rms of the differenced equations after the fit (g);
    ``notes`` what could not be determined.
    """

    model: DifferentialModel
    terms: list[list[str]]
    residual_rms_g: np.ndarray
    n_pairs: int
    windows: list[dict]
    settings: DifferentialSettings
    notes: list[str] = field(default_factory=list)
    #: the standard uncertainty of every coefficient of ``model`` in the same layout (NaN: not fitted; its K0, U00
    #: are NaN too: they are the base's), conditional on the lag when it was fitted
    sigma: DifferentialModel | None = None
    #: per channel c, the covariance of its least-squares vector (terms ``terms[c]``, relative to K0_cc)
    covariance: list[np.ndarray] | None = None

    def summary(self) -> dict:
        st = self.settings
        return {
            "terms": {AXES[c]: t for c, t in enumerate(self.terms)},
            "residual_rms_g": self.residual_rms_g.tolist(),
            "n_pairs": int(self.n_pairs),
            "windows": self.windows,
            "poly_order": st.poly_order,
            "rate_order": st.rate_order,
            "rate_dt_order": st.rate_dt_order,
            "cross_axis": st.cross_axis,
            "lag_fit": st.lag_fit,
            "lag_tau_s": self.model.lag_tau_s,
            "block_s": st.block_s,
            "temp_smooth_s": st.temp_smooth_s,
        }


def _half_pairs(window: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i, j) pairing block k of each window's first half with block k of its second half."""
    first, second = [], []
    for w in np.unique(window):
        idx = np.flatnonzero(window == w)
        n = idx.size // 2
        first.append(idx[:n])
        second.append(idx[n : 2 * n])
    return np.concatenate(first), np.concatenate(second)


def _excited(a_windows: np.ndarray, cols: list[int], min_sv: float) -> bool:
    """Whether the windows' [1, a0[:, cols]] (n_windows, 1 + len(cols)) separates the terms: its smallest singular
    value per sqrt(n_windows) is at least ``min_sv`` (about 0.58 for an axis up in one of six windows and down in
    another, 0.02 for an axis that stayed horizontal within a degree)."""
    V = np.column_stack([np.ones(len(a_windows))] + [a_windows[:, c] for c in cols])
    if V.shape[0] < V.shape[1]:
        return False
    return bool(np.linalg.svd(V, compute_uv=False)[-1] / np.sqrt(len(V)) >= min_sv)


def _channel_terms(
    c: int, K0: np.ndarray, a_windows: np.ndarray, settings: DifferentialSettings
) -> tuple[list[str], list[str]]:
    """The terms channel c can have given the orientations, and a note per term that it cannot."""
    names, axes, notes = ["bias"], [], []
    if _excited(a_windows, [c], settings.min_excitation):
        names.append("scale")
        axes.append(c)
    else:
        notes.append(
            f"channel {AXES[c]}: no orientation had gravity along it; its scale-factor temperature "
            "terms are not determined (left at 0)"
        )
    for j in range(3):
        if (
            settings.cross_axis
            and j != c
            and (K0[c, j] != 0 or settings.cross_axis_abs)
            and _excited(a_windows, axes + [j], settings.min_excitation)
        ):
            names.append(f"cross_{AXES[j]}")
            axes.append(j)
    if settings.rate_order:
        names += ["bias_rate"] + (["scale_rate"] if "scale" in names else [])
    return names, notes


@dataclass
class _Equations:
    """The differenced equations of all runs: per pair, the static and rate basis differences, the window's
    specific force, the output differences; rebuilt for each trial lag."""

    df: np.ndarray  # (p, P)
    dg: np.ndarray  # (p, R*(Kx+1))
    a0: np.ndarray  # (p, 3)
    du: np.ndarray  # (p, 3)
    var: np.ndarray  # (p, 3) V^2: variance of du from the noise measured in the two blocks
    cluster: np.ndarray  # (p,) int: the stretch of time (run, window, CLUSTER_S) the pair's first block is in


def _bases(
    dt: np.ndarray, rate: np.ndarray, poly_order: int, rate_order: int, rate_dt_order: int
) -> tuple[np.ndarray, np.ndarray]:
    """The temperature basis dT^n, n = 1..poly_order (m, P), and the rate basis (m, R * (rate_dt_order + 1),
    :func:`pipeline.thermal.rate_basis`) at temperature offsets ``dt`` (C from the normal temperature) and rates
    ``rate`` (C/min)."""
    f = dt[:, None] ** np.arange(1, poly_order + 1)[None, :]
    return f, rate_basis(dt, rate, rate_order, rate_dt_order).reshape(len(dt), -1)


def _equations(
    data: list[BlockData], a_g: list[np.ndarray], normal_temp_c: float, settings: DifferentialSettings, lag_tau_s: float
) -> _Equations:
    """The differenced equations; ``a_g`` holds each run's specific force per window (n_windows, 3)."""
    P, R, Kx = settings.poly_order, settings.rate_order, settings.rate_dt_order
    parts = []
    for d, a in zip(data, a_g):
        i, j = _half_pairs(d.window)
        temp, rate = d.temperature(lag_tau_s)
        f, g = _bases(temp - normal_temp_c, rate, P, R, Kx)
        var = d.u_var_v2[i] + d.u_var_v2[j] if d.u_var_v2 is not None else np.zeros((len(i), 3))
        start = np.array([(w.t_start_ns - d.sensor.t_ref_ns) / _NS for w in d.windows])
        chunk = np.floor((d.t_s[i] - start[d.window[i]]) / CLUSTER_S).astype(np.int64)
        cluster = len(parts) * 1_000_000 + d.window[i].astype(np.int64) * 10_000 + chunk
        parts.append((f[j] - f[i], g[j] - g[i], a[d.window[i]], d.u_v[j] - d.u_v[i], var, cluster))
    return _Equations(*(np.concatenate([p[k] for p in parts]) for k in range(6)))


def _cross_factor(K0: np.ndarray, c: int, j: int) -> float:
    """The cross-axis column's factor: K0_cj / K0_cc (relative gamma) where K0_cj is known, 1 (absolute dK_cj in
    units of K0_cc) where it is 0 (not determined: sweeps without a base passport)."""
    return K0[c, j] / K0[c, c] if K0[c, j] != 0 else 1.0


def _columns(f: np.ndarray, g: np.ndarray, a: np.ndarray, c: int, names: list[str], K0: np.ndarray) -> np.ndarray:
    """Channel c's regressors over the named terms (rows, terms), in units of K0_cc: the temperature basis ``f``
    (rows, P), the rate basis ``g`` (rows, R*(Kx+1)) and the specific force ``a`` (rows, 3) g. Differenced bases
    give the fit's equations; plain ones give the model's change of the output from T0 (times K0_cc)."""
    cols = {"bias": f, "scale": a[:, [c]] * f, "bias_rate": g, "scale_rate": a[:, [c]] * g}
    return np.concatenate(
        [
            cols[n] if n in cols else _cross_factor(K0, c, AXES.index(n[-1])) * a[:, [AXES.index(n[-1])]] * f
            for n in names
        ],
        axis=1,
    )


def _solve(eq: _Equations, c: int, names: list[str], K0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of channel c's differenced equation over the named terms: coefficients, residuals (g) and the
    design (pairs, terms)."""
    X = _columns(eq.df, eq.dg, eq.a0, c, names, K0)
    y = eq.du[:, c] / K0[c, c]
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    coef = scipy_lstsq(X / scale, y, lapack_driver="gelsy", check_finite=False)[0] / scale
    return coef, y - X @ coef, X


def _best_lag(data, a_g, K0, normal_temp_c, settings, names) -> float:
    """The element lag tau (s) minimising the summed squared residuals of the three channels: a grid over
    [0, lag_max_s], then a bounded search around the best grid point."""

    def cost(tau):
        eq = _equations(data, a_g, normal_temp_c, settings, float(tau))
        return sum(float(np.sum(_solve(eq, c, names[c], K0)[1] ** 2)) for c in range(3))

    grid = np.linspace(0.0, settings.lag_max_s, 13)
    costs = [cost(t) for t in grid]
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    res = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 0.5})
    return float(res.x) if res.fun <= costs[k] else float(grid[k])


def fit_differential(
    data: list[BlockData],
    K0: np.ndarray,
    U0: np.ndarray,
    normal_temp_c: float,
    settings: DifferentialSettings = DifferentialSettings(),
) -> DifferentialFit:
    """Least-squares temperature coefficients from the half-window differences of one or more runs' block data,
    starting from the normal-temperature constants ``K0`` (3, 3) V/g and ``U0`` (3,) V at ``normal_temp_c``."""
    K0 = np.asarray(K0, dtype=float)
    U0 = np.asarray(U0, dtype=float)
    windows = [dict(w.to_dict(), run_id=d.run_id) for d in data for w in d.windows]
    a_windows = np.array([w["a0_g"] for w in windows])
    names, notes = [], []
    for c in range(3):
        n, msg = _channel_terms(c, K0, a_windows, settings)
        names.append(n)
        notes += msg
    a_g = [d.a0_g() for d in data]
    tau = _best_lag(data, a_g, K0, normal_temp_c, settings, names) if settings.lag_fit else 0.0
    for _ in range(1 + settings.refine_passes):
        model, sigma, resid, n_pairs, covs = _fit_once(data, a_g, K0, U0, normal_temp_c, settings, names, tau)
        # the windows' specific force, now compensated (the first pass used the normal-temperature estimate a0)
        a_g = [
            np.array([a[d.window == w.index].mean(axis=0) for w in d.windows])
            for d, a in ((d, compensate_blocks(model, d)) for d in data)
        ]
    return DifferentialFit(
        model=model,
        terms=names,
        residual_rms_g=resid,
        n_pairs=n_pairs,
        windows=windows,
        settings=settings,
        notes=notes,
        sigma=sigma,
        covariance=covs,
    )


def _fit_once(
    data, a_g, K0, U0, normal_temp_c, settings, names, tau
) -> tuple[DifferentialModel, DifferentialModel, np.ndarray, int, list[np.ndarray]]:
    """One linear fit with the windows' specific force ``a_g`` and the element lag ``tau`` (s): the model, the
    standard uncertainty of each of its coefficients in the same layout (NaN where a term was not fitted), the
    residual rms per channel (g), the number of pairs, and per channel the covariance of its least-squares vector
    (:func:`pipeline.uncertainty.regression_cov`, in the units of :func:`_solve`)."""
    P, R, Kx = settings.poly_order, settings.rate_order, settings.rate_dt_order
    eq = _equations(data, a_g, normal_temp_c, settings, tau)
    if len(eq.du) < 10 * max(len(n) for n in names) * max(P, R * (Kx + 1)):
        raise CalibrationError(f"too few differenced blocks ({len(eq.du)}) for the differential model")
    value, sigma = _Coefficients(P, R, Kx), _Coefficients(P, R, Kx, sigma=True)
    resid = np.zeros(3)
    covs = []
    for c in range(3):
        coef, r, X = _solve(eq, c, names[c], K0)
        resid[c] = np.sqrt(np.mean(r**2))
        value.place(c, names[c], coef, K0)
        cov = regression_cov(X, r, eq.var[:, c] / K0[c, c] ** 2, eq.cluster)
        covs.append(cov)
        sigma.place(c, names[c], np.sqrt(np.diag(cov)), K0)
    fitted_abs = np.any(value.cross_abs != 0)
    return (
        value.model(K0, U0, normal_temp_c, settings.temp_smooth_s, tau, fitted_abs),
        sigma.model(
            np.full((3, 3), np.nan), np.full(3, np.nan), normal_temp_c, settings.temp_smooth_s, tau, fitted_abs
        ),
        resid,
        len(eq.du),
        covs,
    )


class _Coefficients:
    """The coefficient arrays of a differential model (or their standard uncertainties), filled channel by
    channel from the least-squares vector of :func:`_solve`. ``sigma``: standard uncertainties (NaN where a term is
    not fitted, scaled by |K0_cc|) instead of values (0 where not fitted, scaled by K0_cc)."""

    def __init__(self, P: int, R: int, Kx: int, sigma: bool = False):
        self.P, self.R, self.Kx, self.sigma = P, R, Kx, sigma
        fill = np.nan if sigma else 0.0
        self.alpha, self.rel = np.full((P, 3), fill), np.full((P, 3, 3), fill)
        self.alpha_rate, self.beta_rate = np.full((R, Kx + 1, 3), fill), np.full((R, Kx + 1, 3), fill)
        self.cross_abs = np.full((P, 3, 3), fill)

    def place(self, c: int, names: list[str], vec: np.ndarray, K0: np.ndarray) -> None:
        """Channel c's fitted vector (terms ``names``, relative to K0_cc) into the model's units."""
        P, R, Kx = self.P, self.R, self.Kx
        gain = abs(K0[c, c]) if self.sigma else K0[c, c]
        k = 0
        for name in names:
            width = R * (Kx + 1) if name.endswith("_rate") else P
            part = vec[k : k + width]
            k += width
            if name == "bias":
                self.alpha[:, c] = part * gain
            elif name == "scale":
                self.rel[:, c, c] = part
            elif name.startswith("cross_"):
                j = AXES.index(name[-1])
                if K0[c, j] != 0:
                    self.rel[:, c, j] = part
                else:
                    self.cross_abs[:, c, j] = part * gain
            elif name == "bias_rate":
                self.alpha_rate[:, :, c] = part.reshape(R, Kx + 1) * gain
            else:
                self.beta_rate[:, :, c] = part.reshape(R, Kx + 1)

    def model(self, K0, U0, normal_temp_c, temp_smooth_s, tau, with_cross_abs: bool) -> DifferentialModel:
        static = PolynomialModel(
            np.asarray(K0, float), np.asarray(U0, float), float(normal_temp_c), self.P, self.alpha, self.rel
        )
        return DifferentialModel(
            static,
            RateTerms(self.alpha_rate, self.beta_rate, temp_smooth_s, tau, self.cross_abs if with_cross_abs else None),
        )


# ---------------------------------------------------------------------------------------------------------------
# Compensation


def compensate_differential(
    model: DifferentialModel, u_v: np.ndarray, temp_c: np.ndarray, rate_c_per_min: np.ndarray | None = None
) -> np.ndarray:
    """Specific force (m, 3) in g: a = K(T, r)^-1 (U - U0(T, r)) (method 1 with the rate terms; without them when
    ``rate_c_per_min`` is None). ``temp_c`` is the element temperature when the model has a lag."""
    K, U0 = model.constants_at(np.atleast_1d(temp_c), rate_c_per_min)
    return specific_force_g(K, U0, np.atleast_2d(u_v))


def compensate_blocks(model: DifferentialModel, data: BlockData, *, with_rate: bool = True) -> np.ndarray:
    """Compensated specific force (m, 3) in g of block data, with the model's lag and (unless ``with_rate`` is
    False) its rate terms."""
    temp, rate = data.temperature(model.lag_tau_s)
    return compensate_differential(model, data.u_v, temp, rate if with_rate else None)


def window_std_g(data: BlockData, a_g: np.ndarray) -> np.ndarray:
    """Per orientation window and axis, the standard deviation over the window of the block-mean specific force
    ``a_g`` (m, 3): the paper's "10 s standard deviation over the full temperature range" with 10 s blocks.
    Shape (n_windows, 3), g."""
    return np.array([a_g[data.window == w.index].std(axis=0) for w in data.windows])


def compensate_run(passport: dict, run) -> tuple[np.ndarray, np.ndarray]:
    """Every voltmeter sample of ``run`` compensated with a passport's model, lag and rate terms: times (n,) ns and
    specific force (n, 3) g. The thermosensor is smoothed as when the passport was made. The passport's base thermal
    model must be polynomial."""
    p = load_passport(passport)
    if not isinstance(p.thermal_model, PolynomialModel):
        raise CalibrationError("the differential compensation needs a polynomial thermal model")
    model = DifferentialModel(p.thermal_model, p.rate_terms)
    window = model.rate.temp_smooth_s if model.rate else DifferentialSettings().temp_smooth_s
    sensor = Thermosensor.from_run(run, window)
    t_ns = run.t_ns()
    temp, rate = sensor.at((t_ns - sensor.t_ref_ns) / _NS, model.lag_tau_s)
    return t_ns, compensate_differential(model, run.u_v(), temp, rate)


# ---------------------------------------------------------------------------------------------------------------
# Without a base passport: the constants at T0 from the orientations themselves (physics.md, "Real recordings")

#: an axis within this angle (deg) of gravity is vertical in an orientation; within it of horizontal, horizontal
AXIS_ROLE_DEG = 15.0
#: the model fitted to sweeps without a base passport: polynomials in T of order 1..3, with or without the
#: cross-axis terms the orientations excite and a first-order rate term, chosen by two-fold validation on the data
#: (:func:`select_model`). On the real CATS recording the validation rejects the rate terms (validation score 20.5
#: against 7.8 mm/s^2: fitted where the orientations saw fast changes, they extrapolate badly to an orientation
#: that did not; held out 6.5 against 5.6), and the lag search finds 0 s (benchmarks/cats_tag.py)
SWEEP_SETTINGS = DifferentialSettings(rate_order=1, cross_axis_abs=True, select_model=True)
#: validation folds: alternate chunks of this length (s) of each window's blocks; scored on means over MEAN_S
FOLD_S = 3600.0
SCORE_MEAN_S = 600.0


def _fold(data: BlockData, keep: np.ndarray) -> BlockData:
    return dataclasses.replace(
        data,
        t_s=data.t_s[keep],
        u_v=data.u_v[keep],
        window=data.window[keep],
        u_var_v2=None if data.u_var_v2 is None else data.u_var_v2[keep],
    )


def _spread_g(model: DifferentialModel, data: BlockData) -> float:
    """Mean over windows and axes of the std of the compensated specific force's SCORE_MEAN_S means (g)."""
    a = compensate_blocks(model, data)
    out = []
    for w in data.windows:
        sel = np.flatnonzero(data.window == w.index)
        if sel.size < 4:
            continue
        b = np.floor(data.t_s[sel] / SCORE_MEAN_S).astype(np.int64)
        ids, start, counts = np.unique(b, return_index=True, return_counts=True)
        means = np.add.reduceat(a[sel], start, axis=0) / counts[:, None]
        if len(means) > 2:
            out.append(means.std(axis=0, ddof=1))
    return float(np.mean(out)) if out else float("inf")


def select_model(
    data: list[BlockData], K0: np.ndarray, U0: np.ndarray, normal_temp_c: float, settings: DifferentialSettings
) -> tuple[DifferentialSettings, list[dict]]:
    """The polynomial order (1..``settings.poly_order``), the rate order (0..``settings.rate_order``) and whether to
    fit cross-axis terms, chosen where the data supports them: each candidate is fitted on alternate
    :data:`FOLD_S` chunks of the windows and scored on the others (the spread of the compensated
    :data:`SCORE_MEAN_S` means, both ways round); the lowest score wins.
    Returns the chosen settings (``select_model`` off) and every candidate's score (g)."""
    folds = []
    for d in data:
        odd = (np.floor(d.t_s / FOLD_S).astype(np.int64) % 2).astype(bool)
        folds.append((_fold(d, ~odd), _fold(d, odd)))
    scores = []
    grid = [
        (o, r, c)
        for r in range(settings.rate_order + 1)
        for o in range(1, settings.poly_order + 1)
        for c in ((False, True) if settings.cross_axis else (False,))
    ]
    for order, rate, cross in grid:
        cand = dataclasses.replace(settings, poly_order=order, rate_order=rate, cross_axis=cross, select_model=False)
        try:
            total = 0.0
            for k in (0, 1):
                fit = fit_differential([f[k] for f in folds], K0, U0, normal_temp_c, cand)
                total += np.mean([_spread_g(fit.model, f[1 - k]) for f in folds])
        except CalibrationError:
            continue
        scores.append({"poly_order": order, "rate_order": rate, "cross_axis": cross, "score_g": float(total / 2)})
    if not scores:
        return dataclasses.replace(settings, select_model=False), []
    best = min(scores, key=lambda x: x["score_g"])
    return (
        dataclasses.replace(
            settings,
            poly_order=best["poly_order"],
            rate_order=best["rate_order"],
            cross_axis=best["cross_axis"],
            select_model=False,
        ),
        scores,
    )


@dataclass
class OrientationBase:
    """Constants at T0 found from the orientation windows of temperature sweeps, without a base passport.

    ``K`` (3, 3) V/g (diagonal: the cross-axis sensitivities are not determined), ``U0`` (3,) V, ``std_K`` and
    ``std_U0`` (3,) their standard uncertainty from the spread between orientations (NaN where a single
    orientation gives the value, None-like where undetermined: see ``undetermined``), ``undetermined`` the
    constants the orientations cannot separate (each kept at its nominal value: gain from the metadata, offset 0,
    cross-axis 0) and ``roles`` per axis the windows in which it was vertical / horizontal.
    """

    K: np.ndarray
    U0: np.ndarray
    std_K: np.ndarray
    std_U0: np.ndarray
    undetermined: list[str]
    roles: dict[str, dict[str, list[int]]]
    nominal_gain_v_per_g: np.ndarray

    def to_dict(self) -> dict:
        def f(x):
            return [None if not np.isfinite(v) else float(v) for v in x]

        return {
            "K_diag_v_per_g": f(np.diag(self.K)),
            "U0_v": f(self.U0),
            "std_K_diag_v_per_g": f(self.std_K),
            "std_U0_v": f(self.std_U0),
            "undetermined": list(self.undetermined),
            "roles": self.roles,
            "nominal_gain_v_per_g": self.nominal_gain_v_per_g.tolist(),
        }


def nominal_gain_v_per_g(runs) -> np.ndarray:
    """(3,) nominal gain (V/g) from the runs' metadata (``nominal_gain_v_per_g``); without it, the median modulus
    of the outputs (the outputs are then taken to read +1 g on an axis pointing up)."""
    for r in runs:
        g = r.meta.nominal_gain_v_per_g
        if g is not None and np.isfinite(g) and g != 0:
            return np.full(3, float(g))
    u = np.concatenate([r.u_v()[:: max(1, r.voltmeter.height // 100_000)] for r in runs])
    u = u[np.isfinite(u).all(axis=1)]
    if u.size == 0:
        raise CalibrationError("no finite voltmeter sample to estimate the gain from", stream="voltmeter")
    return np.full(3, float(np.median(np.linalg.norm(u, axis=1))))


def constants_from_orientations(
    data: list[BlockData], model: DifferentialModel, gain_v_per_g: np.ndarray, fit: DifferentialFit | None = None
) -> OrientationBase:
    """K (diagonal) and U0 at T0 from orientation windows whose temperature terms ``model`` already describes.

    Each window's outputs are brought to T0 with the model (U - dU0(T, r) - dK(T, r) a) and averaged. Axis c's
    offset is the mean over the windows where c is horizontal (within :data:`AXIS_ROLE_DEG`), or the midpoint of
    opposite vertical windows; its gain the vertical window's output less the offset, over the specific force
    along c (|a| = 1 g, the other components from the other channels). An axis never horizontal (and not both up
    and down) has an undetermined offset, one never vertical an undetermined gain: they stay at their nominal
    values and are listed, not guessed.

    Standard uncertainties (``std_K``, ``std_U0``): the spread between the orientations that give a constant
    (std / sqrt(n), when there are two or more), plus, with ``fit`` (the fit that made ``model``, with its
    coefficients' covariance), the error of bringing each window to T0 with the model (propagated with that
    covariance) and the noise of the window means, added in quadrature. Not in them: the cross-axis constants
    the orientations cannot separate from the offsets (basis ``identification`` of the passport). A gain that one
    vertical window alone gives has none (NaN): on simulated sweeps such a gain is off by about 1 ppm against a
    propagated 0.15 ppm, an error no second orientation shows, so a number would claim what the data do not.
    """
    K_nom, U_nom = model.K0, model.U00
    means, dirs, grads, noise = [], [], [], []
    for d in data:
        temp, rate = d.temperature(model.lag_tau_s)
        K, U0 = model.constants_at(temp, rate)
        a0 = d.a0_g()
        a_unit = a0 / np.linalg.norm(a0, axis=1, keepdims=True)
        corrected = d.u_v - (U0 - U_nom) - np.einsum("mij,mj->mi", K - K_nom, a_unit[d.window])
        if fit is not None:
            st = fit.settings
            f, g = _bases(temp - model.normal_temp_c, rate, st.poly_order, st.rate_order, st.rate_dt_order)
            rows = [_columns(f, g, a_unit[d.window], c, fit.terms[c], K_nom) * -K_nom[c, c] for c in range(3)]
        for w in d.windows:
            sel = d.window == w.index
            if sel.any():
                means.append(corrected[sel].mean(axis=0))
                dirs.append(a_unit[w.index])
                # d(window mean of channel c) / d(channel c's coefficients), V; the noise of the mean, V^2
                grads.append([r[sel].mean(axis=0) for r in rows] if fit is not None else None)
                noise.append(d.u_var_v2[sel].mean(axis=0) / sel.sum() if d.u_var_v2 is not None else np.zeros(3))
    m, dirs, noise = np.array(means), np.array(dirs), np.array(noise)

    def model_var(c: int, weights: np.ndarray) -> float:
        """Variance (V^2) of sum_w weights[w] * (window w's mean of channel c) from the model's coefficients."""
        if fit is None or fit.covariance is None:
            return 0.0
        gvec = sum(wt * grads[w][c] for w, wt in enumerate(weights) if wt)
        cov = np.nan_to_num(fit.covariance[c])
        return float(gvec @ cov @ gvec) if np.ndim(gvec) else 0.0

    vert = np.abs(dirs) >= np.cos(np.radians(AXIS_ROLE_DEG))
    horiz = np.abs(dirs) <= np.sin(np.radians(AXIS_ROLE_DEG))
    U0 = np.zeros(3)
    std_U0 = np.full(3, np.nan)
    gain = np.array(gain_v_per_g, dtype=float)
    std_K = np.full(3, np.nan)
    undetermined = [f"K_{a}{b}" for a in AXES for b in AXES if a != b]
    known_u0 = np.zeros(3, dtype=bool)
    u0_weights = np.zeros((3, len(m)))
    for c in range(3):
        h = np.flatnonzero(horiz[:, c])
        up = np.flatnonzero(vert[:, c] & (dirs[:, c] > 0))
        down = np.flatnonzero(vert[:, c] & (dirs[:, c] < 0))
        if h.size:
            u0_weights[c, h] = 1.0 / h.size
            U0[c] = m[h, c].mean()
            spread = m[h, c].var(ddof=1) / h.size if h.size > 1 else 0.0
            known_u0[c] = True
        elif up.size and down.size:
            u0_weights[c, up] = 0.5 / up.size
            u0_weights[c, down] = 0.5 / down.size
            U0[c] = u0_weights[c] @ m[:, c]
            spread = 0.0
            known_u0[c] = True
        else:
            undetermined.append(f"U0_{AXES[c]}")
            continue
        var = spread + model_var(c, u0_weights[c]) + float(u0_weights[c] ** 2 @ noise[:, c])
        std_U0[c] = np.sqrt(var) if (fit is not None or spread > 0) else np.nan
    # the specific force along each axis in each window: |a| = 1 g, the horizontal components from their channels
    K = np.diag(gain)
    for _ in range(2):
        a = (m - U0) / np.diag(K)
        for c in range(3):
            v = np.flatnonzero(vert[:, c])
            if v.size == 0 or not known_u0[c]:
                continue
            others = [j for j in range(3) if j != c]
            a_c = np.sign(dirs[v, c]) * np.sqrt(np.clip(1.0 - np.sum(a[np.ix_(v, others)] ** 2, axis=1), 0.0, 1.0))
            k = (m[v, c] - U0[c]) / a_c
            K[c, c] = k.mean()
            # K_cc = mean over v of (m_v - U0) / a_v: its weights on the window means
            weights = -u0_weights[c] * np.sum(1.0 / a_c) / v.size
            weights[v] += 1.0 / (a_c * v.size)
            spread = k.var(ddof=1) / v.size if v.size > 1 else 0.0
            var = spread + model_var(c, weights) + float(weights**2 @ noise[:, c])
            # one vertical window: nothing checks the estimate (on simulated sweeps it is off by about 1 ppm against
            # a propagated 0.15 ppm), so no number is given
            std_K[c] = np.sqrt(var) if v.size > 1 else np.nan
    for c in range(3):
        if not (vert[:, c].any() and known_u0[c]):
            undetermined.append(f"K_{AXES[c]}{AXES[c]}")
    roles = {
        AXES[c]: {"vertical": np.flatnonzero(vert[:, c]).tolist(), "horizontal": np.flatnonzero(horiz[:, c]).tolist()}
        for c in range(3)
    }
    return OrientationBase(K, U0, std_K, std_U0, undetermined, roles, np.asarray(gain_v_per_g, dtype=float))


def with_constants(data: BlockData, K0: np.ndarray, U0: np.ndarray) -> BlockData:
    """``data`` with each window's specific force recomputed with the constants ``K0`` (3, 3) V/g, ``U0`` (3,) V
    (from the window's block averages)."""
    windows = []
    for w in data.windows:
        sel = data.window == w.index
        a0 = specific_force_g(K0, U0, data.u_v[sel].mean(axis=0)) if sel.any() else np.array(w.a0_g)
        windows.append(dataclasses.replace(w, a0_g=tuple(float(x) for x in a0)))
    return dataclasses.replace(data, windows=windows, constants=(np.asarray(K0, float), np.asarray(U0, float)))


def sweep_base(
    data: list[BlockData], settings: DifferentialSettings = SWEEP_SETTINGS, normal_temp_c: float = 20.0
) -> OrientationBase:
    """The constants at T0 of a unit from its sweeps alone (no base passport): a first differential fit from the
    constants the block data were made with (the nominal gain, zero offsets: :func:`observe`) finds the temperature
    terms, :func:`constants_from_orientations` the constants."""
    K_nom, U_nom = data[0].constants if data[0].constants is not None else (None, None)
    if K_nom is None:
        raise CalibrationError("block data without the constants they were made with")
    first = fit_differential(data, K_nom, U_nom, float(normal_temp_c), settings)
    return constants_from_orientations(data, first.model, np.diag(K_nom), first)


# ---------------------------------------------------------------------------------------------------------------
# From runs to a passport


#: The passport's ``method`` for this recipe.
METHOD = "differential"


def base_constants(base_passport: dict | None, unit: str) -> tuple[np.ndarray, np.ndarray, float]:
    """K0 (3, 3) V/g, U0 (3,) V and T0 (C) of the base passport the differential method starts from (any method;
    its thermal model is not used); CalibrationError when it is of another unit or has no usable constants."""
    if base_passport.get("unit") not in (None, unit):
        raise CalibrationError(f"the base passport is for unit {base_passport.get('unit')}, the runs for {unit}")
    try:
        c = base_passport["coefficients"]
        K0, U0 = np.asarray(c["K"], float), np.asarray(c["U0"], float)
        t0 = float(base_passport.get("normal_temp_c", 20.0))
    except (KeyError, TypeError, ValueError) as e:
        raise CalibrationError(f"the base passport has no usable coefficients K, U0 ({e})") from None
    if K0.shape != (3, 3) or U0.shape != (3,) or not np.all(np.isfinite(K0)) or not np.all(np.isfinite(U0)):
        raise CalibrationError("the base passport's K must be 3x3 and U0 a 3-vector of finite numbers")
    return K0, U0, t0


class Differential(Method):
    """Seed 003's differential calibration: fixed orientations through a temperature cycle or sweep; starts from a
    normal-temperature passport when there is one, else from the constants the orientations determine."""

    name = "differential"
    passport_method = METHOD
    uses_base_passport = True

    def supports(self, recording: Recording) -> Support:
        """Orientations held :data:`SWEEP_MIN_HOLD_S` or more through :data:`SWEEP_MIN_SPAN_C` or more (two or
        more); per axis, whether its bias and scale factor separate (vertical in one orientation, horizontal in
        another)."""
        held = [
            p
            for p in recording.poses
            if p["longest_hold_s"] >= SWEEP_MIN_HOLD_S
            and None not in p["temp_range_c"]
            and p["temp_range_c"][1] - p["temp_range_c"][0] >= SWEEP_MIN_SPAN_C
        ]
        roles = axis_roles(held)
        both = [ax for ax, (v, h) in roles.items() if v and h]
        ok = len(held) >= 2
        det: list[str] = []
        if ok:
            det.append("per axis: bias temperature terms (polynomial in T, rate terms)")
            det += [
                f"axis {ax}: bias and scale factor separated (vertical in one orientation, horizontal in another)"
                for ax in both
            ]
            det += [
                f"axis {ax}: scale factor and its temperature terms undetermined without --base-passport (never "
                "vertical)"
                if not roles[ax][0]
                else f"axis {ax}: bias at T0 undetermined without --base-passport (never horizontal)"
                for ax in "xyz"
                if ax not in both
            ]
            det.append(
                "cross-axis constants: undetermined without --base-passport (only their temperature terms, "
                "where the orientations excite them)"
            )
        hold_h = f"{SWEEP_MIN_HOLD_S / 3600:.0f} h"
        span = f"{SWEEP_MIN_SPAN_C:.0f} C"
        return Support(
            supported=ok,
            why=(
                f"{len(held)} orientations held {hold_h} or more through {span} or more"
                if ok
                else f"needs two or more orientations each held {hold_h} or more through {span} or more; "
                f"found {len(held)}"
            ),
            determines=tuple(det),
            preference=PREFERENCE_SWEEP if recording.program.kind == "sweep" else PREFERENCE,
        )

    def observe(
        self,
        run,
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: dict | None = None,
        segmentation=None,
        differential: DifferentialSettings | None = None,
    ) -> ObservedRun:
        """The run's orientation windows and block averages (``data``, :func:`block_data`, with the base
        passport's normal-temperature constants, or without one the nominal gain and zero offsets) and its VP
        observations, if any (a run without plateaus simply has none; ``segmentation``: the run's, if already made
        with ``settings.segment``)."""
        if base_passport is None:
            K0, U0 = np.diag(nominal_gain_v_per_g([run])), np.zeros(3)
        else:
            K0, U0, _ = base_constants(base_passport, run.meta.unit_serial)
        data = block_data(run, K0, U0, differential or _settings_for(base_passport))
        try:
            observations = observe_run(run, settings.segment, segmentation)[0]
        except CalibrationError:
            observations = []
        return ObservedRun(
            meta=run.meta, source=run.source, observations=observations, warnings=list(run.warnings), data=data
        )

    def fit(
        self,
        observed: list[ObservedRun],
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: dict | None = None,
        differential: DifferentialSettings | None = None,
    ) -> Fitted:
        """The differential fit of one unit's observed runs, from a normal-temperature passport.

        The passport's ``thermal_model`` is the polynomial of order ``differential.poly_order`` (alpha, beta, gamma),
        ``rate_terms`` holds the rate terms and lag (see :class:`RateTerms`), ``differential`` the fit's details and
        ``base_passport`` the starting passport's unit, version and method. VP segments in the runs, if any, verify it
        as usual (without rate terms).

        Without ``base_passport`` (temperature sweeps, physics.md "Real recordings") the constants at T0 come from the
        orientations themselves (:func:`sweep_base`, default model :data:`SWEEP_SETTINGS`): the passport's
        ``orientation_base`` says how, and ``undetermined`` lists what the orientations cannot determine (kept at
        nominal values, never guessed).
        """
        serial = unit_of(observed)
        differential = differential or _settings_for(base_passport)
        data = [r.data for r in observed]
        orientation_base = None
        if base_passport is None:
            t0 = float(observed[0].meta.normal_temp_c)
            orientation_base = sweep_base(data, dataclasses.replace(differential, select_model=False), t0)
            K0, U0 = orientation_base.K, orientation_base.U0
            data = [with_constants(d, K0, U0) for d in data]
        else:
            K0, U0, t0 = base_constants(base_passport, serial)
        scores = []
        if differential.select_model:
            differential, scores = select_model(data, K0, U0, t0, differential)
        fit = fit_differential(data, K0, U0, t0, differential)
        covered = None
        if fit.windows:  # the temperatures the orientation windows went through
            covered = (
                round(min(w["temp_min_c"] for w in fit.windows), 1),
                round(max(w["temp_max_c"] for w in fit.windows), 1),
            )
        notes = list(fit.notes)
        if orientation_base is not None:
            notes.append(
                "no base passport: constants at T0 from the orientations; undetermined (kept at nominal "
                "values): " + ", ".join(orientation_base.undetermined)
            )
        unit_fit = UnitFit(
            unit=serial,
            normal_temp_c=t0,
            per_plateau=[],
            model=fit.model.static,
            skipped=notes,
            valid_temp_c=covered,
            uncertainty=fit_uncertainty(fit, base_passport=base_passport, orientation_base=orientation_base),
        )
        summary = fit.summary()
        if scores:
            summary["model_selection"] = {"folds_s": FOLD_S, "score_mean_s": SCORE_MEAN_S, "candidates": scores}
        fields = {
            "differential": summary,
            "rate_terms": fit.model.rate.to_dict(),
            "base_passport": (
                {k: base_passport.get(k) for k in ("unit", "version", "method", "created_utc")}
                if base_passport is not None
                else None
            ),
        }
        if orientation_base is not None:
            fields["orientation_base"] = orientation_base.to_dict()
            fields["undetermined"] = list(orientation_base.undetermined)
        identity = base_reference(base_passport) if base_passport is not None else {"base_passport_sha256": None}
        return Fitted(unit_fit, passport_fields=fields, settings_extra=identity)

    def plateau_observations(self, observations):
        """The plateaus that verified the passport (the fit uses none; a sweep's drifting stretches are no
        plateaus)."""
        return [o for o in observations if is_verification_position(o.position)]


def _settings_for(base_passport: dict | None) -> DifferentialSettings:
    return DifferentialSettings() if base_passport is not None else SWEEP_SETTINGS


#: a recording supports the differential method with two or more orientations each held this long (s) through at
#: least this temperature change (C)
SWEEP_MIN_HOLD_S = 3600.0
SWEEP_MIN_SPAN_C = 2.0
#: how much ``--method auto`` prefers the differential method (:attr:`pipeline.calibrate.method.Support.preference`):
#: first on a temperature sweep, between the tilt and the scalar method otherwise
PREFERENCE_SWEEP = 30.0
PREFERENCE = 10.0

#: the differential method, for the registry (:mod:`pipeline.calibrate.methods`)
CALIBRATION_METHOD = Differential()
observe = CALIBRATION_METHOD.observe
calibrate_observed = CALIBRATION_METHOD.calibrate_observed


def fit_uncertainty(
    fit: DifferentialFit, *, base_passport: dict | None = None, orientation_base: OrientationBase | None = None
) -> ThermalSigma:
    """The passport's ``uncertainty`` of a differential calibration (standard uncertainties, 1 sigma, in the units
    of the fields they qualify):

    - ``coefficients`` (K, U0 at T0): the base passport's own uncertainties (the method takes its constants), or,
      without a base, the spread of the constants between the orientations that give them (std / sqrt(n));
    - ``thermal_model`` and ``rate_terms``: every fitted coefficient's standard uncertainty
      (:func:`pipeline.uncertainty.regression_cov`) over the differenced pairs (residuals clustered in :data:`CLUSTER_S`
      stretches, or the block noise measured in the data, whichever is larger), conditional on the lag when the lag was
      fitted.

    A number without a measured uncertainty is null, and ``undetermined`` says why (a term the orientations do not
    excite, a cross-axis constant the orientations cannot separate, a base passport without uncertainties, a
    constant that one orientation alone gives)."""
    undetermined: dict[str, str] = {}
    if orientation_base is not None:
        ob = orientation_base
        K_sig = np.full((3, 3), np.nan)
        K_sig[np.diag_indices(3)] = ob.std_K
        U0_sig = np.asarray(ob.std_U0, dtype=float).copy()
        for name in ob.undetermined:  # "K_xy", "U0_x": kept at nominal values
            kind, ax = name.split("_")
            if kind == "K":
                K_sig[AXES.index(ax[0]), AXES.index(ax[1])] = np.nan
            else:
                U0_sig[AXES.index(ax)] = np.nan
            undetermined[f"{kind}.{ax}"] = (
                "not determined by the orientations (no base passport): kept at its nominal value"
            )
        for i in range(3):
            for name, sig in ((f"K.{AXES[i] * 2}", K_sig[i, i]), (f"U0.{AXES[i]}", U0_sig[i])):
                if not np.isfinite(sig) and name not in undetermined:
                    undetermined[name] = (
                        "one orientation alone gives it: no second orientation checks it, and "
                        "its error is not covered by the noise and the model's uncertainty alone"
                    )
        source = (
            "no base passport: the spread between the orientations that give each constant (std / sqrt(n)), "
            "the thermal model's error in bringing each window to T0 and the noise of the window means, "
            "in quadrature"
        )
    else:
        base_unc = ((base_passport or {}).get("uncertainty") or {}).get("coefficients") or {}
        K_sig = _as_sigma(base_unc.get("K"), (3, 3))
        U0_sig = _as_sigma(base_unc.get("U0"), (3,))
        bp = base_passport or {}
        ref = (
            f"base passport v{bp['version']}" if bp.get("version") is not None else "base passport"
        ) + f" ({bp.get('method', '-')})"
        for i in range(3):
            for j in range(3):
                if not np.isfinite(K_sig[i, j]):
                    undetermined[f"K.{AXES[i]}{AXES[j]}"] = f"taken from the {ref}, which records no uncertainty for it"
            if not np.isfinite(U0_sig[i]):
                undetermined[f"U0.{AXES[i]}"] = f"taken from the {ref}, which records no uncertainty for it"
        source = f"the {ref}'s own uncertainties (the method takes its constants at T0)"
    sig = fit.sigma
    K0 = fit.model.K0
    for c in range(3):
        terms = fit.terms[c]
        if "scale" not in terms:
            undetermined[f"beta.{AXES[c] * 2}"] = (
                f"no orientation had gravity along {AXES[c]}: its scale-factor "
                "temperature terms are not determined (left at 0)"
            )
            if fit.settings.rate_order:
                undetermined[f"rate_terms.beta_rate.{AXES[c] * 2}"] = undetermined[f"beta.{AXES[c] * 2}"]
        for j in range(3):
            if j == c:
                continue
            key = AXES[c] + AXES[j]
            fitted = f"cross_{AXES[j]}" in terms
            if K0[c, j] == 0:
                undetermined[f"gamma.{key}"] = (
                    "relative to K_"
                    + key
                    + " = 0 (not known): "
                    + (
                        "fitted as the absolute rate_terms.cross_axis_abs." + key
                        if fitted
                        else "not fitted (left at 0)"
                    )
                )
            elif not fitted:
                undetermined[f"gamma.{key}"] = (
                    "cross-axis temperature terms not fitted (cross_axis off)"
                    if not fit.settings.cross_axis
                    else f"the orientations do not excite axis {AXES[j]} for channel "
                    f"{AXES[c]}: not determined (left at 0)"
                )
            if sig.rate is not None and sig.rate.cross_abs is not None and not fitted:
                undetermined[f"rate_terms.cross_axis_abs.{key}"] = "not fitted (left at 0)"
    rate = None
    if sig.rate is not None:
        rate = {
            k: v
            for k, v in as_json_list(sig.rate.to_dict()).items()
            if k in ("order", "dt_order", "alpha_rate", "beta_rate", "cross_axis_abs")
        }
        rate["lag_tau_s"] = None
        undetermined["rate_terms.lag_tau_s"] = (
            "the lag is found by a search, its uncertainty not estimated; the coefficients' uncertainties are "
            "conditional on it"
            if fit.settings.lag_fit
            else "no lag fitted (lag_fit off): 0 by setting"
        )
    basis = {
        "level": "standard uncertainty (1 sigma)",
        "coefficients": source,
        "thermal_model": "least squares over the differenced block means: the larger of the sandwich "
        "estimate from the residuals (clustered in stretches of cluster_s of each "
        "orientation window) and the voltmeter noise measured in the blocks",
        "cluster_s": CLUSTER_S,
        "block_s": fit.settings.block_s,
        "residual_rms_g": fit.residual_rms_g.tolist(),
        "n_pairs": int(fit.n_pairs),
    }
    if orientation_base is not None:
        basis["identification"] = (
            "statistical uncertainties of the model the orientations identify: with few orientations, the "
            "temperature change of a cross-axis term they do not excite is folded into the fitted bias and scale "
            "terms, and the cross-axis constants left at 0 shift the offsets (and so the windows' specific force); "
            "neither can be seen in the data, so neither is in these numbers"
        )
    return ThermalSigma(
        K0=K_sig,
        U00=U0_sig,
        thermal_model=as_json_list(sig.static.to_dict()),
        birge_ratio=float("nan"),
        dof=0,
        extra={"rate_terms": rate, "undetermined": undetermined},
        basis=basis,
    )


def _as_sigma(values, shape) -> np.ndarray:
    """A passport's sigma list (None: not determined) as a float array (NaN); all NaN when absent."""
    if values is None:
        return np.full(shape, np.nan)
    try:
        a = np.array(values, dtype=float)  # None -> nan
    except (TypeError, ValueError):
        return np.full(shape, np.nan)
    return a if a.shape == shape else np.full(shape, np.nan)


calibrate = CALIBRATION_METHOD.calibrate
