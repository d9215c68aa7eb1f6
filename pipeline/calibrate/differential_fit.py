"""The estimation of seed 003's differential specific-force thermal calibration (Zhuo and Du): orientation windows,
block averages, the differenced equations and their least-squares fit, compensation with the fitted model.

The recipe that turns runs into a passport is :mod:`pipeline.calibrate.differential`; without a base passport the
constants at T0 come from :mod:`pipeline.calibrate.orientation_base`.


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

from pipeline.dynamics import Thermosensor, smoothed_noise_span_s
from pipeline.errors import CalibrationError
from pipeline.model import specific_force_g, vector3
from pipeline.passport.document import Passport, load_passport
from pipeline.positions import AXES
from pipeline.run import NS_PER_S as _NS
from pipeline.thermal import DifferentialModel, PolynomialModel, RateTerms, rate_basis
from pipeline.uncertainty import regression_cov

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
    out: list[OrientationWindow] = []
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
                vector3(a0),
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
    """Orientation windows of ``run`` and the ``block_s`` averages of its outputs in them. Samples in a gap of the
    thermosensor are left out, and blocks with fewer than 80 % of their samples are dropped. Raises CalibrationError
    when the run has no orientation window."""
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
    ok = np.isfinite(u_v[idx]).all(axis=1) & ~sensor.in_gap(t_s[idx])  # no temperature in a thermosensor gap
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


def with_constants(data: BlockData, K0: np.ndarray, U0: np.ndarray) -> BlockData:
    """``data`` with each window's specific force recomputed with the constants ``K0`` (3, 3) V/g, ``U0`` (3,) V
    (from the window's block averages)."""
    windows = []
    for w in data.windows:
        sel = data.window == w.index
        a0 = specific_force_g(K0, U0, data.u_v[sel].mean(axis=0)) if sel.any() else np.array(w.a0_g)
        windows.append(dataclasses.replace(w, a0_g=vector3(a0)))
    return dataclasses.replace(data, windows=windows, constants=(np.asarray(K0, float), np.asarray(U0, float)))


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
    #: the standard uncertainty of every coefficient of ``model`` in the same layout (NaN: not fitted; its K0, U00
    #: are NaN too: they are the base's), conditional on the lag when it was fitted
    sigma: DifferentialModel
    #: per channel c, the covariance of its least-squares vector (terms ``terms[c]``, relative to K0_cc)
    covariance: list[np.ndarray]
    notes: list[str] = field(default_factory=list)

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
    cluster: np.ndarray  # (2, p) int: the stretch of time (run, window, CLUSTER_S; and the thermosensor's span,
    # :func:`sensor_span_s`) the pair's first block is in


def term_bases(
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
    parts: list[tuple] = []
    for d, a in zip(data, a_g):
        i, j = _half_pairs(d.window)
        temp, rate = d.temperature(lag_tau_s)
        f, g = term_bases(temp - normal_temp_c, rate, P, R, Kx)
        var = d.u_var_v2[i] + d.u_var_v2[j] if d.u_var_v2 is not None else np.zeros((len(i), 3))
        start = np.array([(w.t_start_ns - d.sensor.t_ref_ns) / _NS for w in d.windows])
        since = d.t_s[i] - start[d.window[i]]
        cluster = [
            len(parts) * 1_000_000_000
            + d.window[i].astype(np.int64) * 10_000_000
            + np.floor(since / span).astype(np.int64)
            for span in (CLUSTER_S, sensor_span_s(d.sensor, settings.temp_smooth_s))
        ]
        parts.append((f[j] - f[i], g[j] - g[i], a[d.window[i]], d.u_v[j] - d.u_v[i], var, np.array(cluster)))
    df, dg, a0, du, var = (np.concatenate([p[k] for p in parts]) for k in range(5))
    return _Equations(df, dg, a0, du, var, np.concatenate([p[5] for p in parts], axis=1))


def sensor_span_s(sensor: Thermosensor, smooth_s: float) -> float:
    """How far (s) the smoothed thermosensor's noise stays correlated: twice its smoothing window, which spans at
    least five readings (:func:`pipeline.dynamics.smooth_temperature`). Residuals clustered in stretches this long
    carry that noise into the coefficients' uncertainty: read once a minute, its 7 mC (1 mC every second) times
    the output's change with temperature is in every block for minutes, which the few :data:`CLUSTER_S` clusters
    estimate too noisily and the voltmeter's noise does not hold."""
    step_s = float(np.median(np.diff(sensor.t_s))) if sensor.t_s.size > 1 else 0.0
    return smoothed_noise_span_s(step_s, smooth_s)


def _cross_factor(K0: np.ndarray, c: int, j: int) -> float:
    """The cross-axis column's factor: K0_cj / K0_cc (relative gamma) where K0_cj is known, 1 (absolute dK_cj in
    units of K0_cc) where it is 0 (not determined: sweeps without a base passport)."""
    return K0[c, j] / K0[c, c] if K0[c, j] != 0 else 1.0


def term_columns(f: np.ndarray, g: np.ndarray, a: np.ndarray, c: int, names: list[str], K0: np.ndarray) -> np.ndarray:
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
    X = term_columns(eq.df, eq.dg, eq.a0, c, names, K0)
    y = eq.du[:, c] / K0[c, c]
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    from scipy.linalg import lstsq as scipy_lstsq  # (scipy: only where a differential fit runs, not to judge a run)

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
    from scipy.optimize import minimize_scalar  # ~0.3 s to import: only where a lag is searched

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
    fitted_abs = bool(np.any(value.cross_abs != 0))
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


def compensate_run(passport: Passport | dict, run) -> tuple[np.ndarray, np.ndarray]:
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
