"""Calibration from positions held on temperature ramps (physics.md, "Fast programs"; Niu et al. 2013).

A fast program spends no time soaking: the tilt fixture keeps turning the unit through its positions while the
chamber ramps (up and then down, or in steps without soaks), so every static position is held at its own, changing
temperature. The method fits the 12 constants as continuous functions of temperature to all of them at once:

    U(piece) = sum_n [K_n a + U0_n] <dT^n>          n = 0..p,  dT = T_e - T0

with ``<dT^n>`` the mean of dT^n over the piece's time span (a static segment cut into pieces of at most
``piece_s``): the mean output of a polynomial model over a stretch whose temperature changes is exactly the model
at the mean powers, not at the mean temperature (a hold of 120 s at 2 C/min spans 4 C, and seed 000's offsets have
a curvature of about 1e-6 V/C^2: 1.3 micro-V between the two). The fit is linear in the 4 (p + 1) coefficients per
channel (:func:`design`), one least-squares solve for the three channels.

``T_e`` is the thermosensor, smoothed over ``temp_smooth_s`` (between readings further apart than :data:`FINE_S` a
cubic through the smoothed readings and their slopes, :func:`pipeline.dynamics.hermite`, evaluated every
:data:`FINE_S`: a thermosensor read once a minute on 1.5 C/min ramps with turns is not cut into straight chords),
or the sensing element's temperature behind it through
a first-order lag ``tau`` (``tau dT_e/dt = T - T_e``, physics.md ``thermal_lag``). On a program that passes every
temperature once heating and once cooling, a lag left out shifts the heating and the cooling legs in opposite
directions and the fit averages them (Niu et al.'s balanced up and down legs); fitted (``lag_fit``, a one-dimensional
search of the summed squared residuals), it is removed on each leg, and kept only where the data show it (an F-test,
:data:`TEST_P`). The polynomial order p (1..3) is the lowest that a higher one does not improve by the same test.

The result is a polynomial thermal model (the passport's ``thermal_model``) with, when a lag was kept, rate terms of
order 0 holding the lag (``rate_terms.lag_tau_s``: ``apply`` and every compensation evaluate the model at the
element temperature). Every VP hold verifies it at its own (element) temperature. Standard uncertainties come from
the fit (:func:`pipeline.uncertainty.regression_cov`: the larger of the residuals' scatter, clustered in stretches of
``cluster_s``, and the noise measured in the pieces), the lag's own uncertainty included.

The method (:class:`Ramp`, a :class:`pipeline.calibrate.method.Method`): ``observe`` (per run: the pieces and the
smoothed thermosensor, :func:`observe_run`), ``fit`` (:func:`fit_ramp`, and the holds as observations at their element
temperatures, :func:`hold_observations`, which the shared tail verifies: the VP holds, with the status never
``pass`` where they leave a side of T0 unverified); ``supports``: test positions that determine the 12 constants held
over 10 C or more, preferred by ``--method auto`` where most were held off the soaked plateaus, or where those
off them determine the constants more than 10 C beyond the plateaus that do (:func:`_beyond_the_plateaus`).
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass

import numpy as np

from pipeline.calibrate.method import Fitted, Method, Support
from pipeline.calibrate.observations import Observation, ObservedRun, determines_constants, unit_of
from pipeline.calibrate.recording import Recording
from pipeline.calibrate.result import UnitFit
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.dynamics import (
    first_order_lag,
    hermite,
    ramp_direction,
    smooth_temperature,
    smoothed_noise_span_s,
    stretch_cuts,
)
from pipeline.errors import CalibrationError
from pipeline.passport.document import Passport
from pipeline.positions import AXES, gravity_vector_g, is_test_position
from pipeline.run import NS_PER_S as _NS
from pipeline.thermal import OFF_DIAGONAL, OFF_KEYS, PolynomialModel, RateTerms
from pipeline.words import count_words

#: The passport's ``method`` for this recipe.
METHOD = "ramp"
#: a higher polynomial order, and a lag, are kept only where they lower the residuals by more than chance would
#: (F-test, this p-value)
TEST_P = 1e-3


@dataclass(frozen=True)
class RampSettings:
    """The method's own settings: pieces of at most ``piece_s`` (s) cut from each static segment; polynomial order
    ``order`` (0: chosen, 1..3: fixed; ``CalibrationSettings.thermal_model`` poly1..poly3 fixes it too); the lag
    fitted in 0..``lag_max_s`` (s) when ``lag_fit``; a hysteresis of the offsets fitted beside the model when
    ``hysteresis_fit`` (kept where significant; not part of the passport's model); the thermosensor smoothed over
    ``temp_smooth_s`` (s);
    residuals correlated within ``cluster_s`` (s) stretches when the uncertainties are estimated."""

    piece_s: float = 60.0
    order: int = 0
    max_order: int = 3
    lag_fit: bool = True
    hysteresis_fit: bool = True
    lag_max_s: float = 1800.0
    temp_smooth_s: float = 61.0
    cluster_s: float = 1800.0


#: the smoothed thermosensor is evaluated at least this often (s) between its readings (:func:`_sensor`): the mean
#: powers and the lag, exact for a temperature linear between grid points, then see the curve between readings a
#: minute apart (fast program, seeds 44-46 read every 59-61 s: |dK| at T0 0.9-2.6 micro-V/g with chords, 0.2-0.8
#: with the cubic every 5 s; read every second: the grid as it was)
FINE_S = 5.0


@dataclass
class Sensor:
    """A run's smoothed thermosensor on a time grid: ``t_s`` (s since ``t_ref_ns``), ``temp_c`` (C); ``step_s`` the
    thermosensor's own (median) step between readings (s; 0: that of ``t_s``)."""

    t_s: np.ndarray
    temp_c: np.ndarray
    t_ref_ns: int
    step_s: float = 0.0

    def reading_step_s(self) -> float:
        """The thermosensor's median step between readings (s)."""
        return self.step_s if self.step_s > 0 else float(np.median(np.diff(self.t_s)))

    def element(self, tau_s: float) -> np.ndarray:
        """The element temperature (C) on the grid: the sensor through a first-order lag ``tau_s`` (0: itself)."""
        return first_order_lag(self.t_s, self.temp_c, tau_s) if tau_s > 0 else self.temp_c

    def mean_powers(self, t0_s: np.ndarray, t1_s: np.ndarray, tau_s: float, t_ref_c: float, order: int) -> np.ndarray:
        """(m, order + 1): the time mean of (T_e - t_ref_c)^n, n = 0..order, over each span [t0_s, t1_s] (s)."""
        dT = self.element(tau_s) - t_ref_c
        powers = dT[:, None] ** np.arange(order + 1)[None, :]
        # the integral of dT^n over each step, exact for dT linear in the step (a, b its ends):
        # h (b^(n+1) - a^(n+1)) / ((n+1) (b - a)) = h sum_k a^k b^(n-k) / (n+1), which needs no division by b - a
        a, b = dT[:-1], dT[1:]
        step = np.zeros((a.size, order + 1))
        for n in range(order + 1):
            step[:, n] = sum(a**k * b ** (n - k) for k in range(n + 1)) / (n + 1)
        step *= np.diff(self.t_s)[:, None]
        cum = np.vstack([np.zeros((1, order + 1)), np.cumsum(step, axis=0)])
        lo = np.column_stack([np.interp(t0_s, self.t_s, cum[:, n]) for n in range(order + 1)])
        hi = np.column_stack([np.interp(t1_s, self.t_s, cum[:, n]) for n in range(order + 1)])
        span = np.asarray(t1_s, float) - np.asarray(t0_s, float)
        at = np.column_stack([np.interp(t0_s, self.t_s, powers[:, n]) for n in range(order + 1)])
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(span[:, None] > 0, (hi - lo) / span[:, None], at)


@dataclass
class Pieces:
    """What the method keeps of one run (:attr:`ObservedRun.data`): the static segments cut into pieces, each with
    its position, mean outputs ``u_v`` (m, 3) V, the noise variance of that mean ``noise_var_v2`` (m, 3) V^2 (from
    the sample-to-sample differences, which a ramp's drift does not inflate), time span ``t0_s``..``t1_s`` (s since
    the sensor's reference), the index of the segment it was cut from and the sample count; and the run's
    smoothed thermosensor."""

    run_id: str
    position: np.ndarray
    u_v: np.ndarray
    noise_var_v2: np.ndarray
    t0_s: np.ndarray
    t1_s: np.ndarray
    segment: np.ndarray
    count: np.ndarray
    sensor: Sensor
    direction: np.ndarray | None = None
    #: the change (m, 3) V of each piece's mean for one standard uncertainty of the scale of the creep after each
    #: move taken out of it (:attr:`pipeline.settling.Settling.scale_sigma`: one error shared by the run's pieces),
    #: None where none was taken out
    creep_sigma_v: np.ndarray | None = None

    def directions(self) -> np.ndarray:
        """Per piece, the direction the temperature last came from: +1 after heating, -1 after cooling, 0 before
        the first ramp (set by :func:`observe_run` from the run; pieces made without a run: from the sensor at the
        piece's middle, :func:`pipeline.dynamics.ramp_sign_from_temperature`)."""
        if self.direction is None:
            from pipeline.dynamics import ramp_sign_from_temperature

            sign = ramp_sign_from_temperature(self.sensor.t_s, self.sensor.temp_c)
            mid = (self.t0_s + self.t1_s) / 2.0
            self.direction = sign[np.clip(np.searchsorted(self.sensor.t_s, mid), 0, sign.size - 1)]
        return self.direction

    def select(self, mask: np.ndarray) -> Pieces:
        return Pieces(
            self.run_id,
            self.position[mask],
            self.u_v[mask],
            self.noise_var_v2[mask],
            self.t0_s[mask],
            self.t1_s[mask],
            self.segment[mask],
            self.count[mask],
            self.sensor,
            self.directions()[mask],
            None if self.creep_sigma_v is None else self.creep_sigma_v[mask],
        )

    def __len__(self) -> int:
        return int(self.position.size)


# ---------------------------------------------------------------------------------------------------------------
# observe: a run's static segments cut into pieces


def _sorted_voltmeter(run) -> tuple[np.ndarray, np.ndarray]:
    """Voltmeter times (n,) ns and outputs (n, 3) V in time order."""
    t = run.t_ns()
    u = run.u_v()
    if t.size > 1 and np.any(np.diff(t) < 0):
        order = np.argsort(t, kind="stable")
        t, u = t[order], u[order]
    return t, u


def _sensor(run, smooth_s: float) -> Sensor:
    tt, temp = run.thermosensor()
    order = np.argsort(tt, kind="stable")
    tt, temp = tt[order], temp[order]
    if tt.size < 5:
        raise CalibrationError(
            "too few thermosensor samples for a temperature model", path=run.source, stream="au_temperature"
        )
    t_ref = int(tt[0])
    t_s = (tt - t_ref) / _NS
    smooth, rate_c_per_min = smooth_temperature(t_s, temp, smooth_s)
    step_s = float(np.median(np.diff(t_s)))
    cuts = stretch_cuts(t_s)
    grid = fine_grid(t_s, cuts, FINE_S)
    if grid.size == t_s.size:
        return Sensor(t_s, smooth, t_ref, step_s)
    return Sensor(grid, hermite(grid, t_s, smooth, rate_c_per_min / 60.0, cuts), t_ref, step_s)


def fine_grid(t_s: np.ndarray, cuts: np.ndarray, fine_s: float) -> np.ndarray:
    """The sorted times ``t_s`` (s) with each interval longer than ``fine_s`` cut into equal steps of at most
    ``fine_s``, but for the intervals after ``cuts`` (gaps: nothing is known inside them)."""
    h = np.diff(t_s)
    n = np.maximum(np.ceil(h / fine_s - 1e-9), 1).astype(np.int64)
    if len(cuts):
        n[np.asarray(cuts, dtype=np.intp)] = 1
    if not np.any(n > 1):
        return t_s
    i = np.repeat(np.arange(h.size), n)
    k = np.arange(i.size) - np.repeat(np.cumsum(n) - n, n)
    return np.concatenate([t_s[i] + h[i] * k / n[i], t_s[-1:]])


def _mean_direction(direction, t0_s: np.ndarray, t1_s: np.ndarray, points: int = 9) -> np.ndarray:
    """The mean over each span [t0_s, t1_s] (s) of the direction the temperature last came from (``direction``, a
    step function of time, :func:`pipeline.dynamics.ramp_direction`: by the chamber setpoint where recorded, as a
    diagnosis takes it), from ``points`` evenly spaced times: a piece across a turn counts in part to each side."""
    w = np.linspace(0.0, 1.0, points)
    t = t0_s[:, None] + (t1_s - t0_s)[:, None] * w[None, :]
    return direction(t.ravel()).reshape(t.shape).mean(axis=1)


def cut_pieces(t_ns: np.ndarray, u_v: np.ndarray, spans_ns: np.ndarray, piece_s: float, creep=None):
    """Cut the spans [start, end] ns (k, 2) of static segments into pieces of equal length, at most ``piece_s``
    (s) each, and average the samples of each: (segment index (m,), times of the first and last finite sample
    (m,) ns, mean (m, 3) V, noise variance of the mean (m, 3) V^2 from the sample-to-sample differences d
    (var(d) / 2 / n: a drift along the piece does not count), finite sample count (m,)). ``t_ns`` sorted;
    non-finite samples are left out; a piece with fewer than 3 samples is dropped. ``creep``: None, or what to
    subtract from the samples before they are averaged, a function of their spans' indices (n,) and of their times
    since their span's start (n,) s giving (n, 3) V (the creep after each move the segmentation found,
    :meth:`pipeline.settling.Settling.creep_v`)."""
    spans = np.asarray(spans_ns, dtype=np.int64).reshape(-1, 2)
    dur_s = (spans[:, 1] - spans[:, 0]) / _NS
    n_pieces = np.maximum(1, np.ceil(dur_s / piece_s - 1e-9)).astype(int)
    seg = np.repeat(np.arange(len(spans)), n_pieces)
    k = np.arange(seg.size) - np.repeat(np.cumsum(n_pieces) - n_pieces, n_pieces)
    width = (spans[seg, 1] - spans[seg, 0]) / n_pieces[seg]
    start = spans[seg, 0] + np.round(k * width).astype(np.int64)
    end = spans[seg, 0] + np.round((k + 1) * width).astype(np.int64)
    i0 = np.searchsorted(t_ns, start, side="left")
    i1 = np.searchsorted(t_ns, end, side="left")
    finite = np.all(np.isfinite(u_v), axis=1)
    u0 = np.where(finite[:, None], u_v, 0.0)
    cnt = np.concatenate([[0], np.cumsum(finite)])
    count = cnt[i1] - cnt[i0]
    keep = count >= 3
    seg, start, end, i0, i1, count = seg[keep], start[keep], end[keep], i0[keep], i1[keep], count[keep]
    # per-piece sums without cumulative sums over the whole run (which lose precision): the samples of the pieces
    # gathered, with the index of their piece
    lengths = i1 - i0
    owner = np.repeat(np.arange(seg.size), lengths)
    idx = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths) + np.repeat(i0, lengths)
    w = finite[idx].astype(float)
    mean = np.zeros((seg.size, 3))
    for c in range(3):
        mean[:, c] = np.bincount(owner, u0[idx, c], minlength=seg.size) / count
    if creep is not None:  # (its mean over each piece's finite samples; the noise below is a difference of samples)
        taken = creep(seg[owner], (t_ns[idx] - spans[seg[owner], 0]) / _NS) * w[:, None]
        for c in range(3):
            mean[:, c] -= np.bincount(owner, taken[:, c], minlength=seg.size) / count
    # sample-to-sample differences inside each piece (both samples finite)
    same = (owner[1:] == owner[:-1]) & (w[1:] > 0) & (w[:-1] > 0)
    d = u0[idx[1:]] - u0[idx[:-1]]
    n_d = np.maximum(np.bincount(owner[1:][same], minlength=seg.size), 1)
    var = np.zeros((seg.size, 3))
    for c in range(3):  # the variance of the differences about their mean (a ramp's drift per sample) / 2
        m1 = np.bincount(owner[1:][same], d[same, c], minlength=seg.size) / n_d
        m2 = np.bincount(owner[1:][same], d[same, c] ** 2, minlength=seg.size) / n_d
        var[:, c] = np.maximum(m2 - m1**2, 0.0) / 2.0
    # the span of the samples themselves: the mean over evenly spaced samples of anything linear in time is its
    # time mean from the first sample to the last (not over [start, end), which is half a sample longer)
    t_fin = np.where(finite[idx], t_ns[idx], -1)
    last = np.full(seg.size, -1, dtype=np.int64)
    np.maximum.at(last, owner, t_fin)
    t_fin = np.where(finite[idx], t_ns[idx], np.iinfo(np.int64).max)
    first = np.full(seg.size, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(first, owner, t_fin)
    return seg, first, last, mean, var / count[:, None], count


def observe_run(run, settings: CalibrationSettings, segmentation=None, ramp: RampSettings | None = None) -> ObservedRun:
    """The run's named static segments, wherever they are held (on plateaus, on ramps, while the unit approaches a
    temperature), cut into pieces (:func:`cut_pieces`), and its smoothed thermosensor, as the run's
    :attr:`ObservedRun.data` (:class:`Pieces`; ``segmentation``: the run's, if already made with
    ``settings.segment``). CalibrationError naming the file when no test position is held anywhere."""
    from pipeline.segment import NO_PLATEAU_WARNING, segment_run

    ramp = ramp or RampSettings()
    seg = segmentation if segmentation is not None else segment_run(run, settings.segment)
    named = [s for s in seg.segments if s.position is not None and s.count > 0]
    if not any(is_test_position(str(s.position)) for s in named):
        t = run.t_ns()
        raise CalibrationError(
            "no static test position (TP1..TP6) found anywhere in the run",
            path=run.source,
            stream="voltmeter",
            where=f"t_ns={int(t.min())}..{int(t.max())}" if t.size else None,
        )
    sensor = _sensor(run, ramp.temp_smooth_s)
    t_ns, u_v = _sorted_voltmeter(run)
    spans = np.array([[s.t_start_ns, s.t_end_ns] for s in named], dtype=np.int64)
    creep = None
    if seg.settling is not None:  # the creep after each move the segmentation took out of its means: out of the
        found, hold = seg.settling, np.array([s.index for s in named], dtype=np.intp)  # pieces too

        def creep(k: np.ndarray, x_s: np.ndarray) -> np.ndarray:
            return found.creep_v(hold[k], x_s)

    k, start, end, mean, var, count = cut_pieces(t_ns, u_v, spans, ramp.piece_s, creep)
    pieces = Pieces(
        run_id=run.meta.run_id,
        position=np.array([named[i].position for i in k], dtype=object),
        u_v=mean,
        noise_var_v2=var,
        t0_s=(start - sensor.t_ref_ns) / _NS,
        t1_s=(end - sensor.t_ref_ns) / _NS,
        segment=np.array([named[i].index for i in k], dtype=int),
        count=count,
        sensor=sensor,
    )
    pieces.direction = _mean_direction(ramp_direction(run, sensor.t_ref_ns), pieces.t0_s, pieces.t1_s)
    if creep is not None:
        x0_s, x1_s = (start - spans[k, 0]) / _NS, (end - spans[k, 0]) / _NS
        pieces.creep_sigma_v = found.scale_sigma * found.mean_creep_v(hold[k], x0_s, x1_s)
    # a run without a temperature plateau is what this method is for: the segmentation's warning of it is no news
    seg_warnings = [w for w in seg.warnings if seg.plateaus or not w.startswith(NO_PLATEAU_WARNING)]
    return ObservedRun(
        meta=run.meta, source=run.source, observations=[], warnings=list(run.warnings) + seg_warnings, data=pieces
    )


# ---------------------------------------------------------------------------------------------------------------
# the fit


def design(a_g: np.ndarray, powers: np.ndarray) -> np.ndarray:
    """(m, 4 (p + 1)): each piece's row [a_x P, a_y P, a_z P, P] with P = its mean powers (m, p + 1) of dT; the
    coefficients of channel i are then [K_ix,0..p, K_iy,0..p, K_iz,0..p, U0_i,0..p]."""
    a1 = np.column_stack([a_g, np.ones(len(a_g))])  # (m, 4)
    return (a1[:, :, None] * powers[:, None, :]).reshape(len(a_g), -1)


@dataclass
class LinearFit:
    """One least-squares fit at a given order and lag: coefficients (4 (p + 1), 3; one more row, the hysteresis,
    with ``hyst``), residuals (m, 3) V, weighted residual sum of squares (the channels each in units of its own
    noise), and the design."""

    order: int
    tau_s: float
    coef: np.ndarray
    resid: np.ndarray
    rss: float
    X: np.ndarray
    hyst: bool = False

    @property
    def model_coef(self) -> np.ndarray:
        """The coefficients of the model (4 (p + 1), 3), without the hysteresis."""
        return self.coef[: 4 * (self.order + 1)]

    @property
    def hysteresis_v(self) -> np.ndarray:
        """The hysteresis h (3,) V of the offsets (0 where not fitted)."""
        return self.coef[-1] if self.hyst else np.zeros(3)


def _stack(
    pieces: list[Pieces], tau_s: float, t0_c: float, order: int, hyst: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(design (m, 4 (p + 1)), outputs (m, 3)) of the test-position pieces of every run; with ``hyst`` one more
    column, the direction the temperature came from (its coefficient: the hysteresis h of each channel's offset,
    physics.md ``thermal_hysteresis``)."""
    X, Y = [], []
    for p in pieces:
        powers = p.sensor.mean_powers(p.t0_s, p.t1_s, tau_s, t0_c, order)
        a = np.array([gravity_vector_g(x) for x in p.position])
        X.append(np.column_stack([design(a, powers), p.directions()]) if hyst else design(a, powers))
        Y.append(p.u_v)
    return np.vstack(X), np.vstack(Y)


def fit_linear(
    pieces: list[Pieces], tau_s: float, t0_c: float, order: int, weight: np.ndarray, hyst: bool = False
) -> LinearFit:
    """Least squares of all channels at once at lag ``tau_s`` and polynomial ``order`` (with ``hyst``, a hysteresis
    of the offsets beside it); ``weight`` (3,) 1/V^2 per channel for the summed squared residuals (the fit itself
    is unweighted: the pieces have like noise)."""
    X, Y = _stack(pieces, tau_s, t0_c, order, hyst)
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    coef, *_ = np.linalg.lstsq(X / scale, Y, rcond=None)
    coef = coef / scale[:, None]
    resid = Y - X @ coef
    return LinearFit(order, float(tau_s), coef, resid, float(np.sum(resid**2 * weight)), X, hyst)


def _f_test(rss_small: float, rss_big: float, extra: int, dof: int) -> float:
    """p-value of the F-test that a model with ``extra`` more parameters (residual dof ``dof``) fits better."""
    from scipy.stats import f as f_dist

    if dof <= 0 or rss_big <= 0:
        return 0.0 if rss_small > rss_big else 1.0
    stat = max(rss_small - rss_big, 0.0) / extra / (rss_big / dof)
    return float(f_dist.sf(stat, extra, dof))


def _best_lag(pieces, t0_c: float, order: int, weight: np.ndarray, lag_max_s: float, hyst: bool) -> LinearFit:
    """The fit at the lag (0..lag_max_s, s) with the smallest residuals: a coarse grid, then a bounded search
    around its best point."""
    from scipy.optimize import minimize_scalar

    grid = np.concatenate([[0.0], np.geomspace(5.0, lag_max_s, 16)])
    rss = [fit_linear(pieces, g, t0_c, order, weight, hyst).rss for g in grid]
    k = int(np.argmin(rss))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    if hi > lo:
        res = minimize_scalar(
            lambda tau: fit_linear(pieces, tau, t0_c, order, weight, hyst).rss,
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 0.01},
        )
        if res.fun < rss[k]:
            return fit_linear(pieces, float(res.x), t0_c, order, weight, hyst)
    return fit_linear(pieces, float(grid[k]), t0_c, order, weight, hyst)


@dataclass
class RampFit:
    """The fitted model: polynomial ``model`` (K0, U00, alpha, rel) at the element temperature with lag ``tau_s``
    (0: the smoothed thermosensor), the linear fit it came from, the tests that chose the order and the lag, and
    the uncertainties."""

    model: PolynomialModel
    tau_s: float
    fit: LinearFit
    order_tests: list[dict]
    lag_test: dict | None
    hysteresis_test: dict | None
    cov: list[np.ndarray]  # per channel (4 (p + 1), 4 (p + 1)), the lag's uncertainty included
    tau_sigma_s: float | None
    hysteresis_sigma_v: np.ndarray | None
    n_pieces: int
    n_segments: int
    temp_range_c: tuple[float, float]
    residual_rms_v: np.ndarray
    noise_rms_v: np.ndarray


def fit_ramp(pieces: list[Pieces], t0_c: float, thermal_model: str = "auto", ramp: RampSettings = RampSettings()):
    """Fit the constants as polynomials in the element temperature to the test-position pieces of ``pieces``: the
    order (``thermal_model`` poly1..poly3 or ``ramp.order`` fix it; else the lowest of 1..max_order that the next
    does not beat, :data:`TEST_P`), the lag (fitted and kept where significant, ``ramp.lag_fit``), a hysteresis of
    the offsets beside the model (``ramp.hysteresis_fit``, kept where significant: the direction the temperature
    came from, which every program passing each temperature up and down shows; left out, it would be taken up by
    the lag and the constants), and every coefficient's standard uncertainty. The candidates for the order carry
    the lag and the hysteresis; each of the two is then dropped where the F-test does not keep it."""
    tp = [p.select(np.array([is_test_position(x) for x in p.position], dtype=bool)) for p in pieces]
    tp = [p for p in tp if len(p)]
    m = sum(len(p) for p in tp)
    positions = sorted({x for p in tp for x in p.position})
    if not determines_constants(positions):
        raise CalibrationError(
            f"the test positions held ({', '.join(positions)}) do not determine the 12 constants "
            "(U = K a + U0 needs positions whose [a, 1] rows have rank 4, e.g. five of TP1..TP6)",
            stream="voltmeter",
        )
    noise = np.vstack([p.noise_var_v2 for p in tp])
    weight = 1.0 / np.maximum(np.median(noise, axis=0), 1e-30)
    if thermal_model in ("poly1", "poly2", "poly3"):
        fixed = int(thermal_model[-1])
    elif thermal_model in ("auto",):
        fixed = ramp.order
    else:
        raise CalibrationError(
            f"thermal model {thermal_model}: the ramp method fits a polynomial (auto, poly1, poly2, poly3)"
        )

    hyst = ramp.hysteresis_fit and any(np.any(p.directions() > 0) and np.any(p.directions() < 0) for p in tp)

    def at(order: int, lag: bool, with_h: bool) -> LinearFit:
        if lag:
            return _best_lag(tp, t0_c, order, weight, ramp.lag_max_s, with_h)
        return fit_linear(tp, 0.0, t0_c, order, weight, with_h)

    tests: list[dict] = []
    orders = [fixed] if fixed else list(range(1, ramp.max_order + 1))
    if m <= 3 * (4 * (max(orders) + 1) + 1):
        raise CalibrationError(
            f"{m} test-position pieces are too few for a temperature model of order {max(orders)} "
            f"({4 * (max(orders) + 1)} coefficients per channel)",
            stream="voltmeter",
        )
    fits = {o: at(o, ramp.lag_fit, hyst) for o in orders}
    nuisance = int(ramp.lag_fit) + 3 * int(hyst)
    order = orders[0]
    for lo, hi in zip(orders, orders[1:]):
        dof = 3 * (m - 4 * (hi + 1)) - nuisance
        pv = _f_test(fits[lo].rss, fits[hi].rss, 12, dof)
        tests.append({"order": hi, "against": lo, "p_value": pv, "kept": pv < TEST_P})
        if pv >= TEST_P:
            break
        order = hi
    best = fits[order]
    dof = 3 * (m - 4 * (order + 1)) - nuisance
    hysteresis_test = None
    if hyst:
        without = at(order, ramp.lag_fit, False)
        pv = _f_test(without.rss, best.rss, 3, dof)
        hysteresis_test = {"h_v": best.hysteresis_v.tolist(), "p_value": pv, "kept": pv < TEST_P}
        if not hysteresis_test["kept"]:
            best, hyst, dof = without, False, dof + 3
    lag_test = None
    if ramp.lag_fit:
        none = fit_linear(tp, 0.0, t0_c, order, weight, hyst)
        pv = _f_test(none.rss, best.rss, 1, dof)
        step = min(p.sensor.reading_step_s() for p in tp)
        # a lag shorter than the thermosensor's sample step is no lag the data resolve
        lag_test = {"tau_s": best.tau_s, "p_value": pv, "kept": pv < TEST_P and best.tau_s >= step}
        if not lag_test["kept"]:
            best = none
    cov, tau_sigma, h_sigma = _covariances(
        tp, best, t0_c, noise, ramp.cluster_s, with_lag=best.tau_s > 0, smooth_s=ramp.temp_smooth_s
    )
    model = _polynomial(best.model_coef, order, t0_c)
    temps = np.concatenate(
        [p.sensor.mean_powers(p.t0_s, p.t1_s, best.tau_s, 0.0, 1)[:, 1] for p in tp]
    )  # mean element temperature of each piece
    return RampFit(
        model=model,
        tau_s=best.tau_s,
        fit=best,
        order_tests=tests,
        lag_test=lag_test,
        hysteresis_test=hysteresis_test,
        cov=cov,
        tau_sigma_s=tau_sigma,
        hysteresis_sigma_v=h_sigma,
        n_pieces=m,
        n_segments=sum(len(set(p.segment.tolist())) for p in tp),
        temp_range_c=(float(temps.min()), float(temps.max())),
        residual_rms_v=np.sqrt(np.mean(best.resid**2, axis=0)),
        noise_rms_v=np.sqrt(np.mean(noise, axis=0)),
    )


def _polynomial(coef: np.ndarray, order: int, t0_c: float) -> PolynomialModel:
    """The passport's polynomial model from the coefficients (4 (p + 1), 3) of :func:`design`."""
    c = coef.reshape(4, order + 1, 3)  # [column j of K (x, y, z) or U0][power n][channel i]
    K = np.transpose(c[:3], (1, 2, 0))  # (p + 1, i, j)
    U0 = c[3]  # (p + 1, i)
    K0 = K[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(K0 != 0, K[1:] / K0, 0.0)
    return PolynomialModel(K0.copy(), U0[0].copy(), float(t0_c), int(order), U0[1:].copy(), rel)


def _clusters(pieces: list[Pieces], cluster_s: float, smooth_s: float) -> np.ndarray:
    """(2, m): each piece's stretch of ``cluster_s`` (a slow misfit), and of the span the smoothed thermosensor's
    noise stays correlated over (:func:`pipeline.dynamics.smoothed_noise_span_s`: read once a minute, its 7 mC
    times the outputs' change with temperature is shared by the pieces of ten minutes, which the few long clusters
    estimate too noisily)."""
    return np.vstack(
        [
            np.concatenate([k * 1_000_000 + np.floor(p.t0_s / span(p)).astype(np.int64) for k, p in enumerate(pieces)])
            for span in (lambda p: cluster_s, lambda p: smoothed_noise_span_s(p.sensor.reading_step_s(), smooth_s))
        ]
    )


def _covariances(
    pieces: list[Pieces],
    fit: LinearFit,
    t0_c: float,
    noise: np.ndarray,
    cluster_s: float,
    with_lag: bool,
    smooth_s: float = RampSettings.temp_smooth_s,
) -> tuple[list[np.ndarray], float | None, np.ndarray | None]:
    """Per channel, the covariance of its 4 (p + 1) coefficients (:func:`pipeline.uncertainty.regression_cov`),
    with the lag's uncertainty included when a lag was fitted (its column: the change of the prediction per second
    of lag); and the lag's standard uncertainty (s), the channels' estimates combined by inverse variance."""
    from pipeline.uncertainty import regression_cov

    clusters = _clusters(pieces, cluster_s, smooth_s)
    J = None
    if with_lag:
        h = max(1.0, 0.01 * fit.tau_s)
        Xp, _ = _stack(pieces, fit.tau_s + h, t0_c, fit.order, fit.hyst)
        Xm, _ = _stack(pieces, max(fit.tau_s - h, 0.0), t0_c, fit.order, fit.hyst)
        J = (Xp - Xm) @ fit.coef / (fit.tau_s + h - max(fit.tau_s - h, 0.0))  # (m, 3) V/s
    covs, tau_var, h_sig = [], [], []
    n = 4 * (fit.order + 1)
    creep = _creep_coef_shifts(pieces, fit)
    for c in range(3):
        X = fit.X if J is None else np.column_stack([fit.X, J[:, c]])
        cov = regression_cov(X, fit.resid[:, c], noise[:, c], clusters)
        for d in creep:  # each run's creep correction: one scale error for all its pieces
            cov[: d.shape[0], : d.shape[0]] += np.outer(d[:, c], d[:, c])
        if J is not None:
            tau_var.append(cov[-1, -1])
        if fit.hyst:
            h_sig.append(np.sqrt(cov[n, n]))
        covs.append(cov[:n, :n])  # the model's coefficients, the lag's and the hysteresis's uncertainty included
    tau_sigma = None
    if tau_var:
        inv = sum(1.0 / v for v in tau_var if np.isfinite(v) and v > 0)
        tau_sigma = float(np.sqrt(1.0 / inv)) if inv > 0 else None
    return covs, tau_sigma, (np.array(h_sig) if h_sig else None)


def _creep_coef_shifts(pieces: list[Pieces], fit: LinearFit) -> list[np.ndarray]:
    """Per run whose pieces had the creep after each move taken out (:attr:`Pieces.creep_sigma_v`), the change
    (columns of ``fit.X``, 3) of the fit's coefficients for one standard uncertainty of that creep's scale: the
    least-squares solution for those changes of the pieces' means (the lag and the order held)."""
    out = []
    row = 0
    for p in pieces:
        if p.creep_sigma_v is not None and np.any(p.creep_sigma_v != 0):
            dy = np.zeros((fit.X.shape[0], 3))
            dy[row : row + len(p)] = p.creep_sigma_v
            scale = np.linalg.norm(fit.X, axis=0)
            scale[scale == 0] = 1.0
            out.append(np.linalg.lstsq(fit.X / scale, dy, rcond=None)[0] / scale[:, None])
        row += len(p)
    return out


def sigma_of(fit: RampFit):
    """The standard uncertainties in the passport's layout: (K0 (3, 3) V/g, U00 (3,) V, thermal-model dict with the
    sigma of every alpha (V/C^n), beta and gamma (1/C^n, first order in the ratio to K0))."""
    p = fit.model.order
    coef = fit.fit.model_coef.reshape(4, p + 1, 3)
    K0_sig = np.zeros((3, 3))
    U00_sig = np.zeros(3)
    alpha_sig = np.zeros((p, 3))
    rel_sig = np.zeros((p, 3, 3))
    for i in range(3):
        cov = fit.cov[i]

        def idx(j: int, n: int) -> int:
            return j * (p + 1) + n

        U00_sig[i] = np.sqrt(cov[idx(3, 0), idx(3, 0)])
        for n in range(1, p + 1):
            alpha_sig[n - 1, i] = np.sqrt(cov[idx(3, n), idx(3, n)])
        for j in range(3):
            K0_sig[i, j] = np.sqrt(cov[idx(j, 0), idx(j, 0)])
            k0 = coef[j, 0, i]
            for n in range(1, p + 1):
                kn = coef[j, n, i]
                g = np.array([1.0 / k0, -kn / k0**2]) if k0 != 0 else np.array([np.nan, np.nan])
                sub = cov[np.ix_([idx(j, n), idx(j, 0)], [idx(j, n), idx(j, 0)])]
                rel_sig[n - 1, i, j] = np.sqrt(max(float(g @ sub @ g), 0.0))
    alpha = {AXES[i]: alpha_sig[:, i].tolist() for i in range(3)}
    beta = {AXES[i] * 2: rel_sig[:, i, i].tolist() for i in range(3)}
    gamma = {OFF_KEYS[k]: rel_sig[:, i, j].tolist() for k, (i, j) in enumerate(OFF_DIAGONAL)}
    return K0_sig, U00_sig, {"kind": "polynomial", "order": p, "alpha": alpha, "beta": beta, "gamma": gamma}


# ---------------------------------------------------------------------------------------------------------------
# the holds as observations at their element temperature (what the VP verification takes)


def hold_observations(pieces: Pieces, fit: RampFit, source: str = "") -> list[Observation]:
    """One observation per static hold (segment) of a run, at its mean element temperature (the lag ``fit.tau_s``):
    its mean outputs referred to that temperature (the model's mean output over the hold, at the mean powers of dT,
    less its output at the mean temperature, with the position's nominal specific force: a second-order
    correction, about 1 micro-V for a 120-s hold at 2 C/min with seed 000's curvature of the offsets), and as its
    ``plateau`` the index of the leg it lies on (the run of holds between turns of the temperature: a verification
    "visit"). What :meth:`Method.finish` verifies (the VP holds) and judges the verified range by (the test
    positions)."""
    t0_c = fit.model.normal_temp_c
    order = fit.model.order
    powers = pieces.sensor.mean_powers(pieces.t0_s, pieces.t1_s, fit.tau_s, t0_c, order)
    legs = _legs(pieces)
    out = []
    for seg in dict.fromkeys(pieces.segment.tolist()):
        sel = pieces.segment == seg
        span = pieces.t1_s[sel] - pieces.t0_s[sel]
        w = span / span.sum() if span.sum() > 0 else np.full(span.size, 1.0 / span.size)
        n = pieces.count[sel]
        u = (pieces.u_v[sel] * n[:, None]).sum(axis=0) / n.sum()
        mean_powers = w @ powers[sel]  # (order + 1,)
        temp = t0_c + mean_powers[1]
        position = str(pieces.position[sel][0])
        a = np.asarray(gravity_vector_g(position))[None]
        over = design(a, mean_powers[None]) @ fit.fit.model_coef
        at_mean = design(a, ((temp - t0_c) ** np.arange(order + 1))[None]) @ fit.fit.model_coef
        std = np.sqrt((pieces.noise_var_v2[sel] * n[:, None] ** 2).sum(axis=0) / n.sum())  # per sample
        out.append(
            Observation(
                run_id=pieces.run_id,
                plateau=int(legs[np.flatnonzero(sel)[0]]),
                position=position,
                u_v=_vec3(u - (over[0] - at_mean[0])),
                std_v=_vec3(std),
                count=int(n.sum()),
                temp_c=float(temp),
                t_start_ns=int(pieces.sensor.t_ref_ns + round(pieces.t0_s[sel].min() * _NS)),
                t_end_ns=int(pieces.sensor.t_ref_ns + round(pieces.t1_s[sel].max() * _NS)),
                source=source,
            )
        )
    return out


def _vec3(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _legs(pieces: Pieces) -> np.ndarray:
    """Per piece, the index of the leg it lies on: legs change where the thermosensor's direction (heating,
    cooling, neither before the first ramp) changes between consecutive pieces."""
    at = pieces.directions()
    mid = (pieces.t0_s + pieces.t1_s) / 2.0
    order = np.argsort(mid, kind="stable")
    legs = np.empty(len(pieces), dtype=int)
    legs[order] = np.concatenate([[0], np.cumsum(np.diff(at[order]) != 0)])
    return legs


# ---------------------------------------------------------------------------------------------------------------
# the method

#: ``--method auto``'s preference where most test-position holds lie off the soaked plateaus (or reach beyond them,
#: :func:`_beyond_the_plateaus`): above the tilt method's with a fixture log (28), below the differential method's on a
#: sweep it supports (30)
PREFERENCE_RAMPS = 29.0
#: ... and on a sweep whose long-held orientations leave an axis undetermined (:func:`_partial_sweep`): above the
#: differential method's (30)
PREFERENCE_OVER_SWEEP = 31.0
PREFERENCE = 5.0
#: test positions held over at least this temperature span (C)
MIN_SPAN_C = 10.0


def visits(segments) -> list:
    """One segment per hold of ``segments`` (the first of each): consecutive static segments of one position, on
    one plateau (or off every one) and alike settling or not, are one hold, however many pieces the static test
    cut it into (the voltages drifting with temperature through a ramp sit near its threshold: at a lower or uneven
    voltmeter rate a stay in one position comes in ten pieces instead of two). Counted in holds, not pieces, ``auto``
    judges a recording alike at any rate."""

    def hold(s):
        return s.position, s.plateau, s.settling is None

    named = sorted((s for s in segments if s.position and s.count > 0), key=lambda s: s.t_start_ns)
    return [next(group) for _, group in itertools.groupby(named, key=hold)]


def _beyond_the_plateaus(off_holds, plateau_temps_c: list[float]) -> str | None:
    """Where test-position holds off every soaked plateau (``off_holds``, :func:`visits`) determine the 12 constants
    more than :data:`MIN_SPAN_C` below the coldest or above the warmest of the soaks whose test positions determine
    them (``plateau_temps_c``, the tilt method's), the clause saying so, else None: the tilt method leaves those
    holds out and its passport stops short of them (a stepped program whose soaks do not wait out the unit's lag:
    a stage's holds drift through the plateau test), the ramp method takes every hold at its own temperature."""
    if not off_holds:
        return None
    temps = np.array([h.temp_c for h in off_holds])
    if plateau_temps_c:
        lo, hi = min(plateau_temps_c), max(plateau_temps_c)
        sides = [(f"below the plateaus' {lo:+.1f} .. {hi:+.1f} C", temps < lo - MIN_SPAN_C)]
        sides.append((f"above the plateaus' {lo:+.1f} .. {hi:+.1f} C", temps > hi + MIN_SPAN_C))
    else:
        sides = [("where no plateau holds the test positions", np.isfinite(temps))]
    for where, sel in sides:
        names = [h.position for h, s in zip(off_holds, sel) if s]
        if determines_constants(names):
            return (
                f"{', '.join(sorted(set(names)))} held off the soaked plateaus at {temps[sel].min():+.1f} .. "
                f"{temps[sel].max():+.1f} C, {where}"
            )
    return None


def _partial_sweep(recording: Recording) -> str | None:
    """Where the orientations the differential method would take on this sweep (two or more held an hour or more,
    :func:`pipeline.calibrate.differential.held_orientations`) leave an axis whose bias and scale factor they do not
    separate (never vertical, or never horizontal), the clause saying so, else None: the differential method leaves
    that axis' constants at T0 at their nominal values (or the base passport's) and its scale-factor temperature terms
    at 0, where the test positions held on the ramps determine all 12 constants and their temperature model (a
    stepped program whose soaks do not wait out the unit's lag: no plateau, the fixture resting in one position
    through every ramp)."""
    from pipeline.calibrate.differential import held_orientations
    from pipeline.calibrate.recording import axis_roles

    held = held_orientations(recording)
    if len(held) < 2:
        return None
    roles = axis_roles(held)
    axes = [ax for ax, (vertical, horizontal) in roles.items() if not (vertical and horizontal)]
    if not axes:
        return None
    return (
        f"the {count_words(len(held), 'orientation')} held 1 h or more do not separate bias and scale factor on "
        f"axis {', '.join(axes)} (the differential method would leave them undetermined)"
    )


class Ramp(Method):
    """Positions held on temperature ramps (fast programs): see the module doc. Options: ``ramp``
    (:class:`RampSettings`)."""

    name = "ramp"
    passport_method = METHOD

    def supports(self, recording: Recording) -> Support:
        """Supported where the named test positions, wherever held, determine the 12 constants and span at least
        :data:`MIN_SPAN_C`; preferred by ``auto`` where most test-position holds lie off the soaked plateaus and off
        the settling before them (a program without soaks)."""
        tp = [s for s in recording.segmentation.segments if s.position and is_test_position(s.position) and s.count > 0]
        names = sorted({s.position for s in tp})
        temps = [s.temp_c for s in tp if np.isfinite(s.temp_c)]
        lo, hi = (min(temps), max(temps)) if temps else (float("nan"), float("nan"))
        ok = bool(tp) and determines_constants(names) and hi - lo >= MIN_SPAN_C
        holds = [h for h in visits(recording.segmentation.segments) if is_test_position(h.position)]
        off_holds = [h for h in holds if h.plateau not in recording.soaks and h.settling is None]
        off = len(off_holds)
        most = 2 * off > len(holds)
        beyond = (
            None if most or not ok else _beyond_the_plateaus(off_holds, [c[2] for c in recording.constant_plateaus])
        )
        partial = _partial_sweep(recording) if ok and most and recording.program.kind == "sweep" else None
        return Support(
            supported=ok,
            why=(
                f"test positions {', '.join(names)} held over {lo:+.1f} .. {hi:+.1f} C; {off} of "
                f"{count_words(len(holds), 'test-position hold')} off the soaked plateaus"
                + (f"; {beyond}" if beyond else "")
                + (f"; {partial}" if partial else "")
                if ok
                else f"needs test positions that determine the 12 constants held over {MIN_SPAN_C:.0f} C or more; "
                + (f"found {', '.join(names)} over {lo:+.1f} .. {hi:+.1f} C" if tp else "found none")
            ),
            determines=(
                (
                    f"K (9) and U0 (3) as polynomials in T (order up to 3) over {lo:+.1f} .. {hi:+.1f} C",
                    "the sensing element's lag behind the thermosensor, where the ramps show one",
                )
                if ok
                else ()
            ),
            preference=PREFERENCE_OVER_SWEEP
            if partial
            else PREFERENCE_RAMPS
            if ok and (most or beyond)
            else PREFERENCE,
        )

    def observe(
        self,
        run,
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        segmentation=None,
        ramp: RampSettings | None = None,
        **options,
    ) -> ObservedRun:
        """:func:`observe_run` (``base_passport`` is not used by this method)."""
        return observe_run(run, settings, segmentation, ramp)

    def fit(
        self,
        observed: list[ObservedRun],
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        ramp: RampSettings | None = None,
        **options,
    ) -> Fitted:
        """:func:`fit_ramp` over the runs' pieces; the passport's ``ramp`` (the fit's details) and, with a lag,
        ``rate_terms`` (order 0, the lag); the holds as observations at their element temperatures
        (:func:`hold_observations`) for the verification."""
        ramp = ramp or RampSettings()
        unit = unit_of(observed)
        t0_c = float(observed[0].meta.normal_temp_c)
        fit = fit_ramp([r.data for r in observed], t0_c, settings.thermal_model, ramp)
        rate = None
        if fit.tau_s > 0:
            rate = RateTerms(np.zeros((0, 1, 3)), np.zeros((0, 1, 3)), ramp.temp_smooth_s, fit.tau_s)
        unit_fit = UnitFit(
            unit=unit,
            normal_temp_c=t0_c,
            per_plateau=[],
            model=fit.model,
            skipped=[_order_note(fit), _lag_note(fit, ramp)] + _hysteresis_note(fit),
            uncertainty=_uncertainty(fit, ramp, rate is not None),
            valid_temp_c=(round(fit.temp_range_c[0], 1), round(fit.temp_range_c[1], 1)),
        )
        return Fitted(
            fit=unit_fit,
            passport_fields={"ramp": _summary(fit, ramp), **({"rate_terms": rate.to_dict()} if rate else {})},
            settings_extra={"ramp": asdict(ramp)} if ramp != RampSettings() else {},
            observations=[o for r in observed for o in hold_observations(r.data, fit, r.source)],
        )

    def plateau_observations(self, observations: list[Observation]) -> list[Observation]:
        """None: the method takes no plateaus (the passport's ``plateaus`` is empty; its legs are no plateaus)."""
        return []


def _uncertainty(fit: RampFit, ramp: RampSettings, with_lag: bool):
    from pipeline.uncertainty import ThermalSigma, as_json_list

    K0_sig, U00_sig, model_sig = sigma_of(fit)
    undetermined = {}
    if with_lag and fit.tau_sigma_s is None:
        undetermined["rate_terms.lag_tau_s"] = "the residuals do not change with the lag near its best value"
    return ThermalSigma(
        K0=K0_sig,
        U00=U00_sig,
        thermal_model=as_json_list(model_sig),
        birge_ratio=float("nan"),
        dof=0,
        extra={
            "rate_terms": (
                {"order": 0, "dt_order": 0, "alpha_rate": [], "beta_rate": [], "lag_tau_s": fit.tau_sigma_s}
                if with_lag
                else None
            ),
            "undetermined": undetermined,
        },
        basis={
            "level": "standard uncertainty (1 sigma)",
            "thermal_model": "least squares over the test-position pieces: the larger of the sandwich estimate from "
            "the residuals (clustered in stretches of cluster_s) and the voltmeter noise measured in the pieces "
            "(sample-to-sample differences), with the lag's and the hysteresis's own uncertainty where fitted",
            "cluster_s": ramp.cluster_s,
            "piece_s": ramp.piece_s,
            "residual_rms_v": fit.residual_rms_v.tolist(),
            "noise_rms_v": fit.noise_rms_v.tolist(),
            "n_pieces": fit.n_pieces,
        },
    )


def _order_note(fit: RampFit) -> str:
    tests = "; ".join(
        f"order {t['order']} against {t['against']}: p = {t['p_value']:.2g} ({'kept' if t['kept'] else 'not kept'})"
        for t in fit.order_tests
    )
    return (
        f"ramp: constants as polynomials of order {fit.model.order} in T over {fit.temp_range_c[0]:+.1f} .. "
        f"{fit.temp_range_c[1]:+.1f} C from {fit.n_pieces} pieces of {fit.n_segments} test-position holds"
        + (f" ({tests})" if tests else "")
    )


def _lag_note(fit: RampFit, ramp: RampSettings) -> str:
    if not ramp.lag_fit:
        return "ramp: element lag not fitted (lag_fit off): the temperature is the thermosensor's"
    t = fit.lag_test or {}
    if fit.tau_s > 0:
        sig = f" +- {fit.tau_sigma_s:.2g}" if fit.tau_sigma_s is not None else ""
        note = f"ramp: the sensing element lags the thermosensor by {fit.tau_s:.1f}{sig} s (p = {t['p_value']:.2g})"
        if fit.tau_s >= 0.999 * ramp.lag_max_s:
            # the search's bound: a longer lag is taken up by the constants and the hysteresis (6 C/min, 2400 s:
            # VP errors of 2.7 mg and a hysteresis of 120 uV that is not there)
            note += (
                f", the longest the search tries (lag_max_s {ramp.lag_max_s:g} s): the element may lag more; "
                "the constants and any hysteresis found are then suspect (a slower ramp or longer dwells tell)"
            )
        return note
    return (
        f"ramp: no element lag (the best, {t.get('tau_s', 0.0):.2g} s, is shorter than a thermosensor sample or "
        f"does not lower the residuals beyond chance, p = {t.get('p_value', 1.0):.2g})"
    )


def _hysteresis_note(fit: RampFit) -> list[str]:
    t = fit.hysteresis_test
    if not t or not t["kept"]:
        return []
    h = ", ".join(f"{a} {v * 1e6:+.1f}" for a, v in zip(AXES, fit.fit.hysteresis_v))
    return [
        f"ramp: the offsets depend on the direction the temperature came from: h = {h} uV (U0 + h after heating, "
        f"- h after cooling; p = {t['p_value']:.2g}); the passport's thermal model holds their mean, so "
        "compensated outputs keep +-h (thermocal diagnose names it: thermal_hysteresis)"
    ]


def _summary(fit: RampFit, ramp: RampSettings) -> dict:
    return {
        "order": fit.model.order,
        "order_tests": fit.order_tests,
        "lag_fit": ramp.lag_fit,
        "lag_tau_s": fit.tau_s,
        "lag_test": fit.lag_test,
        "hysteresis_fit": ramp.hysteresis_fit,
        "hysteresis_v": fit.fit.hysteresis_v.tolist(),
        "hysteresis_sigma_v": fit.hysteresis_sigma_v.tolist() if fit.hysteresis_sigma_v is not None else None,
        "hysteresis_test": fit.hysteresis_test,
        "pieces": fit.n_pieces,
        "holds": fit.n_segments,
        "piece_s": ramp.piece_s,
        "temp_range_c": [round(fit.temp_range_c[0], 3), round(fit.temp_range_c[1], 3)],
        "residual_rms_v": fit.residual_rms_v.tolist(),
        "noise_rms_v": fit.noise_rms_v.tolist(),
    }


CALIBRATION_METHOD = Ramp()
observe = CALIBRATION_METHOD.observe
calibrate_observed = CALIBRATION_METHOD.calibrate_observed
calibrate = CALIBRATION_METHOD.calibrate
