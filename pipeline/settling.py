"""The reading's creep after each move of the fixture (docs/physics.md, effect ``tilt_settling``), found in the
static holds and taken out of their means.

After a move from one position to the next the reading creeps to its final value, U += -f (U_new - U_old)
exp(-(t - t_arrive)/tau_s): each hold's mean is off by a fixed fraction of the step it arrived by, and the
constants, which are differences of hold means, are off by tens of micro-V/g at f = 2e-4, tau_s = 30 s, far beyond
their noise. The creep's shape ties it down: it is proportional, channel by channel, to the step U_new - U_old (the
mean of the hold less the mean of the one before it), it decays with one time constant, and it begins as the hold
does. So two numbers for the whole run, the amplitude g (the fraction of the step left at a hold's first sample)
and tau_s, are fitted to every hold's samples at once (:func:`settling_fit`), each hold with its own mean and its
own quadratic in its temperature (the thermosensor's, interpolated onto its samples): a unit still approaching its
temperature (positions held without a soak, or on a ramp) drifts through each hold with the temperature, by the
thermal model's slope, and that drift, which also follows the steps (the slope depends on the position), is the
thermal model's business, not a creep (without it a program held without soaks, issue 23's, found a 'creep' of
1260 ppm, tau_s 415 s, at 14000 standard errors on a run without one and moved its hold means by up to 1.3 mV).
Where g stands out of the noise the hold means are corrected by the creep's mean over each hold. The ramp method,
which averages its own pieces of the holds from the samples, takes the same fitted creep out of each piece
(:meth:`Settling.creep_v`, :func:`pipeline.calibrate.ramp.cut_pieces`): it is fitted once, by the segmentation,
and its scale's uncertainty (:attr:`Settling.scale_sigma`) is a term of that method's sigmas.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.effects.base import log_grid
from pipeline.effects.tilt_settling import TiltSettling
from pipeline.run import SLAB_SAMPLES

#: the time constants tried (s): the catalogue effect's range, 10 % apart (a hold's mean creep depends on tau_s
#: nearly in proportion: a coarser grid leaves a bias)
TAU_GRID_S: tuple[float, ...] = log_grid(TiltSettling.grid[0], TiltSettling.grid[-1], 70)
#: a hold whose predecessor ended longer ago than this (s) is not taken to have arrived from it (the move is not seen)
MAX_MOVE_S = 120.0
#: the creep is taken out only where its amplitude stands out of the noise by this many standard errors
MIN_Z = 10.0
#: the largest plausible creep, as a fraction of the step (the catalogue effect's bound)
MAX_FRACTION = 0.01
#: :func:`hold_moments` takes e(t) = exp(-t/tau_s) on blocks of samples lasting at most tau_s / this
BLOCK_PER_TAU = 20.0
#: ... and on at least this many blocks to a hold
MIN_BLOCKS = 64


@dataclass(frozen=True)
class HoldMoments:
    """What :func:`settling_fit` needs of one hold's samples, per time constant of :data:`TAU_GRID_S`: with
    e(t) = exp(-(t - t_first)/tau_s) and ``e_mean`` its mean over the hold (n_tau,), r = e less its least-squares
    fit by the hold's nuisance terms (a constant and a quadratic in the hold's temperature:
    :func:`_nuisance_basis`), ``ee`` = sum r^2 (n_tau,) and ``eu`` = sum r (u_i - mean u_i) (n_tau, 3) V."""

    ee: np.ndarray
    eu: np.ndarray
    e_mean: np.ndarray


def hold_moments(
    t_s: np.ndarray, u_v: list[np.ndarray], mean_v: np.ndarray, temp_c: np.ndarray | None = None
) -> HoldMoments:
    """:class:`HoldMoments` of one hold from its sample times ``t_s`` (s, any origin), its three channels ``u_v``
    (V) with their means ``mean_v`` (V) and its temperature at those samples ``temp_c`` (C; None or non-finite:
    the hold's mean alone is a nuisance term)."""
    n_tau = len(TAU_GRID_S)
    ee, eu, e_mean = np.zeros(n_tau), np.zeros((n_tau, 3)), np.zeros(n_tau)
    n = t_s.size
    # the nuisance terms' columns (na, n) and R^-1 (q, q), the orthonormal basis A[:q]^T R^-1 (:func:`_nuisance_basis`)
    # never formed: its sums are those of A times R^-1
    cols_a, rinv = _nuisance_terms(n, temp_c)
    na, q = cols_a.shape[0], rinv.shape[0]
    if n < q + 2:
        return HoldMoments(ee, eu, e_mean)
    x = t_s - t_s[0]
    inv_tau = 1.0 / np.asarray(TAU_GRID_S)
    # each time constant on blocks of consecutive samples lasting at most tau_s / BLOCK_PER_TAU: within a block b,
    # e(t) = E_b (1 + <d^2>_b / (2 tau_s^2)) - E_b d / tau_s, E_b = e(the block's mean time), d = t - that time (the
    # block's mean and slope right; the rest, E_b (d^2 - <d^2>_b) / (2 tau_s^2) < 3.2e-4 E_b, averages out in the
    # block). Block lengths are powers of two, their sums made once for all time constants and levels (each level
    # by adding pairs of the one before): at 100 Hz a hold costs little more than at 10 Hz.
    dt_s = float(x[-1]) / (x.size - 1)  # (s, the mean interval)
    # (and at least MIN_BLOCKS blocks to a hold: the nuisance terms' shape within it resolved)
    length = np.minimum(np.asarray(TAU_GRID_S) / (BLOCK_PER_TAU * dt_s) if dt_s > 0 else 1.0, x.size / MIN_BLOCKS)
    length = np.maximum(1.0, length)
    level = np.floor(np.log2(length)).astype(int)
    # additive block sums, one row each (one array, its rows contiguous: each level one pass of pairs): the
    # nuisance columns A (na: 1, the first, is the samples' count), t A (t, ...), t^2, u (3, V, less its mean), t u
    iu = 2 * na + 1
    sums = np.empty((iu + 6, n))
    sums[:na] = cols_a
    np.multiply(x, cols_a, out=sums[na : 2 * na])
    np.multiply(x, x, out=sums[2 * na])
    for i, (c, m) in enumerate(zip(u_v, mean_v)):
        np.subtract(np.asarray(c, dtype=float), m, out=sums[iu + i])
    np.multiply(x, sums[iu : iu + 3], out=sums[iu + 3 : iu + 6])
    bu = rinv.T @ (sums[:q] @ sums[iu : iu + 3].T)  # (q, 3) basis^T u
    for lev in range(int(level.max()) + 1):
        if lev:  # pairs of the level before (an odd one out at the end alone)
            half = sums.shape[1] // 2
            pairs = np.empty((sums.shape[0], sums.shape[1] - half))
            np.add(sums[:, 0 : 2 * half : 2], sums[:, 1 : 2 * half : 2], out=pairs[:, :half])
            if pairs.shape[1] > half:
                pairs[:, half] = sums[:, -1]
            sums = pairs
        taus = np.flatnonzero(level == lev)
        if not taus.size:
            continue
        count, sx, sxx, su, sxu = sums[0], sums[na], sums[2 * na], sums[iu : iu + 3], sums[iu + 3 : iu + 6]
        sb, sxb = rinv.T @ sums[:q], rinv.T @ sums[na : na + q]  # (q, m) the basis' sums, t basis'
        xb = sx / count  # (m,) s, the blocks' mean times
        d2 = np.maximum(sxx - sx * xb, 0.0)  # (m,) s^2, sum of d^2 over each block
        du = sxu - xb * su  # (3, m) s V, sum of d u
        db = sxb - xb * sb  # (q, m) s, sum of d basis
        # with a = <d^2>_b, h = 1 / (2 tau_s^2), level_e = E_b (1 + a h) and slope = E_b / tau_s, every sum over the
        # blocks is one of E_b or E_b^2 times what depends on the block alone: one product by E_b of (m, 11 + 3 q)
        # and one by E_b^2 of (m, 3) for the time constants of this level
        a = d2 / count
        lin = np.concatenate([count[None], d2[None], sb, a * sb, db, su, a * su, du])  # (11 + 3 q, m)
        sq = np.stack([count, d2, d2 * a])  # (3, m)
        per = max(1, SLAB_SAMPLES // xb.size)  # time constants at a time: at most a slab's worth of e(t) in memory
        for k in range(0, taus.size, per):
            sel = taus[k : k + per]
            it, h = inv_tau[sel, None], 0.5 * inv_tau[sel, None] ** 2  # (per, 1)
            big_e = np.exp(-np.outer(inv_tau[sel], xb))  # (per, m) E_b
            e1 = big_e @ lin.T  # (per, 11 + 3 q)
            e2 = (big_e * big_e) @ sq.T  # (per, 3)
            e_mean[sel] = (e1[:, 0] + h[:, 0] * e1[:, 1]) / x.size
            # r = e - B (B^T e) with B the orthonormal nuisance basis, without forming r: r.r = e.e - |B^T e|^2,
            # r.u = e.u - (B^T e).(B^T u)
            eb = e1[:, 2 : 2 + q] + h * e1[:, 2 + q : 2 + 2 * q] - it * e1[:, 2 + 2 * q : 2 + 3 * q]  # (per, q)
            ee_all = e2[:, 0] + (2.0 * h[:, 0] + it[:, 0] ** 2) * e2[:, 1] + h[:, 0] ** 2 * e2[:, 2]
            ee[sel] = np.maximum(ee_all - np.einsum("kq,kq->k", eb, eb), 0.0)
            j = 2 + 3 * q
            eu[sel] = e1[:, j : j + 3] + h * e1[:, j + 3 : j + 6] - it * e1[:, j + 6 : j + 9] - eb @ bu
    return HoldMoments(ee=ee, eu=eu, e_mean=e_mean)


def _nuisance_terms(n: int, temp_c: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """A hold's nuisance terms at its n samples: their columns A (na, n), a constant 1 and, where the hold's
    temperature ``temp_c`` (C, at its n samples) is finite and varies, d and d^2 with d that temperature less its
    mean over its RMS (the drift of a unit still approaching its temperature, :mod:`pipeline.settling`), and
    R^-1 (q, q), q <= na, the inverse of the triangle of their QR factorisation: A[:q]^T R^-1 are orthonormal
    columns spanning them (:func:`_nuisance_basis`); a column the others already span is left out."""
    cols = [np.ones(n)]
    if temp_c is not None and n > 0 and np.all(np.isfinite(temp_c)):
        d = np.asarray(temp_c, dtype=float) - float(np.mean(temp_c))
        spread_c = float(np.sqrt(np.mean(d * d)))
        if spread_c > 0:
            d = d / spread_c
            cols += [d, d * d]
    cols_a = np.stack(cols)
    if n == 0:
        return cols_a, np.eye(1)
    r = np.asarray(np.linalg.qr(cols_a.T, mode="r"))  # (na, na) the triangle
    diag = np.abs(np.diag(r))
    keep = diag > 1e-9 * diag[0]
    q = int(np.argmin(keep)) if not keep.all() else keep.size  # (the leading columns: d never lies in 1's span)
    return cols_a, np.linalg.inv(r[:q, :q])


def _nuisance_basis(n: int, temp_c: np.ndarray | None) -> np.ndarray:
    """Orthonormal columns (n, q) spanning a hold's nuisance terms (:func:`_nuisance_terms`)."""
    cols_a, rinv = _nuisance_terms(n, temp_c)
    return cols_a[: rinv.shape[0]].T @ rinv if n else np.zeros((0, 1))


@dataclass(frozen=True)
class Settling:
    """The creep fitted over a run's holds: ``fraction`` (the part of each step still missing at a hold's first
    sample, > 0 for a creep towards the final value), ``tau_s`` (s), ``z`` (the amplitude over its standard error),
    ``correction_v`` (n_holds, 3) V, what to subtract from each hold's mean, and ``amplitude_v`` (n_holds, 3) V, the
    creep at each hold's first sample (g times its step; both zero unless ``used``)."""

    fraction: float
    tau_s: float
    z: float
    used: bool
    correction_v: np.ndarray
    amplitude_v: np.ndarray
    #: the relative standard uncertainty of the correction, taken as one scale of every hold's: the amplitude's
    #: (1 / z) and, in quadrature, the largest relative change of the corrections over the time constants whose
    #: chi-square is within 1 of the best (g refitted at each)
    scale_sigma: float = 0.0

    def creep_v(self, hold: np.ndarray, x_s: np.ndarray) -> np.ndarray:
        """The creep (m, 3) V in the samples ``x_s`` (m,) s after the first sample of their holds ``hold`` (m,),
        indices of the holds :func:`settling_fit` was given: what to subtract from those samples."""
        return self.amplitude_v[hold] * np.exp(-np.asarray(x_s, dtype=float) / self.tau_s)[:, None]

    def mean_creep_v(self, hold: np.ndarray, x0_s: np.ndarray, x1_s: np.ndarray) -> np.ndarray:
        """The creep's mean (m, 3) V over the time from ``x0_s`` to ``x1_s`` (m,) s after the first sample of the
        holds ``hold`` (m,) (its value at ``x0_s`` where they are equal)."""
        x0, x1 = np.asarray(x0_s, dtype=float), np.asarray(x1_s, dtype=float)
        a, b = np.exp(-x0 / self.tau_s), np.exp(-x1 / self.tau_s)
        span = x1 - x0
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(span > 0, self.tau_s * (a - b) / np.where(span > 0, span, 1.0), a)
        return self.amplitude_v[hold] * mean[:, None]

    def line(self, n_holds: int) -> str:
        """The warning that says what was found and done."""
        return (
            f"voltmeter: the reading creeps after each move (tilt_settling): {self.fraction * 1e6:.0f} ppm of the "
            f"step at the start of a hold, time constant {self.tau_s:.0f} s ({self.z:.0f} standard errors); the "
            f"means of {n_holds} holds corrected by up to {np.abs(self.correction_v).max() * 1e6:.2f} micro-V"
        )


def settling_fit(
    moments: list[HoldMoments],
    mean_v: np.ndarray,
    std_v: np.ndarray,
    start_s: np.ndarray,
    end_s: np.ndarray,
    moved: np.ndarray,
) -> Settling:
    """The creep after each move over a run's holds, in time order: their :class:`HoldMoments`, means and standard
    deviations ``mean_v``, ``std_v`` (n, 3) V, first and last sample times ``start_s``, ``end_s`` (n,) s, and
    ``moved`` (n - 1,): whether a move lies between hold k and k + 1 (not a mere cut of one still stretch, e.g.
    where a plateau begins).

    The step of hold k is mean_v[k] - mean_v[k-1] where a move lies between them and hold k-1 ended at most
    :data:`MAX_MOVE_S` before hold k began (else 0: no creep is modelled). Channels are weighted by their median
    noise variance. For each tau_s of :data:`TAU_GRID_S` the amplitude g is the weighted least-squares fit of
    u = nuisance + g step e(t) (each hold's nuisance: its mean and a quadratic in its temperature,
    :class:`HoldMoments`); the tau_s with the largest reduction of chi-square is taken, refined between the grid's
    points. The correction g step e_mean per hold is used where tau_s lies inside the grid (a best fit at its end,
    900 s, is a slow drift through the holds that happens to follow the steps, not a creep: clean short programs
    show one of up to 300 standard errors at 1 micro-V of noise, from the unit's temperature still settling), g < 0
    (the reading starts short of its final value), its z is at least :data:`MIN_Z` and -g at most
    :data:`MAX_FRACTION`."""
    n = len(moments)
    zero = Settling(0.0, float("nan"), 0.0, False, np.zeros((n, 3)), np.zeros((n, 3)))
    if n < 2:
        return zero
    step = np.zeros((n, 3))
    moved = np.asarray(moved, dtype=bool) & (start_s[1:] - end_s[:-1] <= MAX_MOVE_S)
    step[1:][moved] = (mean_v[1:] - mean_v[:-1])[moved]
    var = np.median(np.asarray(std_v, dtype=float) ** 2, axis=0)
    if not np.all(var > 0):
        return zero
    w = 1.0 / var  # (3,)
    ee = np.stack([m.ee for m in moments])  # (n, n_tau)
    eu = np.stack([m.eu for m in moments])  # (n, n_tau, 3)
    num = np.einsum("ki,kti,i->t", step, eu, w)
    den = np.einsum("ki,kt,i->t", step**2, ee, w)
    ok = den > 0
    if not ok.any():
        return zero
    chi2 = np.where(ok, num**2 / np.where(ok, den, 1.0), 0.0)
    best = int(np.argmax(chi2))
    # between the grid's time constants: num, den and the holds' e_mean are smooth in log(tau_s), quadratic
    # through the best one and its neighbours (1e-4 of their values at 10 % spacing)
    nodes = np.clip(np.arange(best - 1, best + 2), 0, len(TAU_GRID_S) - 1)
    log_tau = np.log(np.asarray(TAU_GRID_S))
    near, shift = np.zeros(0, dtype=np.intp), np.zeros((0, n))
    if len(set(nodes.tolist())) == 3 and ok[nodes].all():
        fine = np.linspace(log_tau[nodes[0]], log_tau[nodes[2]], _FINE)
        lag = _lagrange(log_tau[nodes], fine)  # (_FINE, 3)
        num_f, den_f = lag @ num[nodes], lag @ den[nodes]
        chi2_f = num_f**2 / den_f
        j = int(np.argmax(chi2_f))
        weights, tau_s = lag[j], float(np.exp(fine[j]))
        near = np.flatnonzero(chi2_f >= chi2_f[j] - 1.0)  # the time constants within 1 of the best chi-square
        e_near = lag[near] @ np.stack([m.e_mean[nodes] for m in moments]).T  # (q, n)
        shift = (num_f[near] / den_f[near])[:, None] * e_near  # g e_mean of each hold at each of them
    else:
        weights, tau_s = np.eye(3)[1], float(TAU_GRID_S[best])
    num_b, den_b = float(weights @ num[nodes]), float(weights @ den[nodes])
    g = num_b / den_b
    z = abs(num_b) / np.sqrt(den_b)
    resolved = 0 < best < len(TAU_GRID_S) - 1  # (at the grid's end: a drift through the holds, not a creep)
    used = resolved and g < 0 and z >= MIN_Z and -g <= MAX_FRACTION
    e_mean = np.array([m.e_mean[nodes] @ weights for m in moments])
    amplitude = g * step if used else np.zeros((n, 3))
    scale_sigma = 0.0
    if used:
        # the corrections' relative change over the time constants near the best: g e_mean of each hold, weighted
        # by the steps (a correction is g e_mean times the step)
        size = np.sqrt(np.einsum("ki,i->k", step**2, w))
        base = g * e_mean * size
        spread = float(np.max(np.abs(shift * size[None, :] - base[None, :]).sum(axis=1))) if near.size else 0.0
        scale_sigma = float(np.hypot(1.0 / z, spread / np.abs(base).sum()))
    return Settling(-g, tau_s, float(z), used, amplitude * e_mean[:, None], amplitude, scale_sigma)


#: points of the fine search of tau_s between two neighbours of the grid's best
_FINE = 201


def _lagrange(nodes: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Weights (len(x), 3) of the quadratic through three ``nodes`` evaluated at ``x``."""
    w = np.ones((x.size, 3))
    for a in range(3):
        for b in range(3):
            if a != b:
                w[:, a] *= (x - nodes[b]) / (nodes[a] - nodes[b])
    return w
