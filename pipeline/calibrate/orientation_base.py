"""The constants at T0 of a unit from its temperature sweeps alone, without a base passport (docs/physics.md, "Real
recordings"): the sweep model chosen by two-fold validation (:func:`select_model`), and K (diagonal) and U0 from
the orientation windows whose temperature terms the model describes (:func:`constants_from_orientations`,
:func:`sweep_base`), with what the orientations leave undetermined (:class:`OrientationBase`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.calibrate.differential_fit import (
    BlockData,
    DifferentialFit,
    DifferentialSettings,
    compensate_blocks,
    fit_differential,
    term_bases,
    term_columns,
)
from pipeline.errors import CalibrationError
from pipeline.positions import AXES
from pipeline.thermal import DifferentialModel

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


def _spreads_g(model: DifferentialModel, data: BlockData) -> np.ndarray:
    """Per window (with three or more) and axis, the std of the compensated specific force's SCORE_MEAN_S means
    (g), flattened; which windows count depends on the data alone, so every model's spreads of one fold pair up."""
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
    return np.concatenate(out) if out else np.zeros(0)


def _complexity(order: int, rate: int, cross: bool) -> tuple[int, int, int]:
    """How many coefficients a candidate fits per channel (bias and scale polynomials, two cross-axis ones, bias
    and scale rate terms), then its polynomial and rate orders: the simpler first."""
    return (order * (2 + 2 * int(cross)) + 2 * rate, order, rate)


def select_model(
    data: list[BlockData], K0: np.ndarray, U0: np.ndarray, normal_temp_c: float, settings: DifferentialSettings
) -> tuple[DifferentialSettings, list[dict]]:
    """The polynomial order (1..``settings.poly_order``), the rate order (0..``settings.rate_order``) and whether to
    fit cross-axis terms, chosen where the data supports them: each candidate is fitted on alternate
    :data:`FOLD_S` chunks of the windows and scored on the others (the spread of the compensated
    :data:`SCORE_MEAN_S` means, both ways round: the mean over the folds of each window's and axis's spread).
    The simplest candidate (:func:`_complexity`) whose score is within one standard error of the lowest wins (the
    standard error of the mean of their paired per-window, per-axis differences): a term that lowers the score by
    less than the score's own noise is not fitted (on a simulated cycle the rate term changed the score by 0.3 %
    either way, so the chosen model, and the constants with it, flipped with the noise and the thermosensor's
    rate). Returns the chosen settings (``select_model`` off) and every candidate's score and standard error (g)."""
    folds = []
    for d in data:
        odd = (np.floor(d.t_s / FOLD_S).astype(np.int64) % 2).astype(bool)
        folds.append((_fold(d, ~odd), _fold(d, odd)))
    scores: list[dict[str, Any]] = []
    spreads: list[np.ndarray] = []  # per candidate: every fold's, window's and axis's spread, weighted as in its score
    grid = [
        (o, r, c)
        for r in range(settings.rate_order + 1)
        for o in range(1, settings.poly_order + 1)
        for c in ((False, True) if settings.cross_axis else (False,))
    ]
    for order, rate, cross in grid:
        cand = dataclasses.replace(settings, poly_order=order, rate_order=rate, cross_axis=cross, select_model=False)
        try:
            parts = []
            for k in (0, 1):
                fit = fit_differential([f[k] for f in folds], K0, U0, normal_temp_c, cand)
                for f in folds:
                    s = _spreads_g(fit.model, f[1 - k])
                    # the score: the mean over the two folds of the mean over the runs of each run's mean spread
                    parts.append(s / (2 * len(folds) * s.size) if s.size else np.array([np.inf]))
        except CalibrationError:
            continue
        spreads.append(np.concatenate(parts))
        scores.append(
            {"poly_order": order, "rate_order": rate, "cross_axis": cross, "score_g": float(spreads[-1].sum())}
        )
    if not scores:
        return dataclasses.replace(settings, select_model=False), []
    lowest = int(np.argmin([x["score_g"] for x in scores]))
    for x, s in zip(scores, spreads):
        d = (s - spreads[lowest]) * s.size  # the paired differences, each on the score's scale
        x["score_se_g"] = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 and np.all(np.isfinite(d)) else 0.0
    best = min(
        (x for x in scores if x["score_g"] <= scores[lowest]["score_g"] + x["score_se_g"]),
        key=lambda x: _complexity(x["poly_order"], x["rate_order"], x["cross_axis"]),
    )
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
    means: list[np.ndarray] = []
    dir_rows: list[np.ndarray] = []
    grads: list[list[np.ndarray]] = []  # empty without ``fit``
    noise_rows: list[np.ndarray] = []
    for d in data:
        temp, rate = d.temperature(model.lag_tau_s)
        K, U0 = model.constants_at(temp, rate)
        a0 = d.a0_g()
        a_unit = a0 / np.linalg.norm(a0, axis=1, keepdims=True)
        corrected = d.u_v - (U0 - U_nom) - np.einsum("mij,mj->mi", K - K_nom, a_unit[d.window])
        if fit is not None:
            st = fit.settings
            f, g = term_bases(temp - model.normal_temp_c, rate, st.poly_order, st.rate_order, st.rate_dt_order)
            rows = [term_columns(f, g, a_unit[d.window], c, fit.terms[c], K_nom) * -K_nom[c, c] for c in range(3)]
        for w in d.windows:
            sel = d.window == w.index
            if sel.any():
                means.append(corrected[sel].mean(axis=0))
                dir_rows.append(a_unit[w.index])
                # d(window mean of channel c) / d(channel c's coefficients), V; the noise of the mean, V^2
                grads.append([r[sel].mean(axis=0) for r in rows] if fit is not None else [])
                noise_rows.append(d.u_var_v2[sel].mean(axis=0) / sel.sum() if d.u_var_v2 is not None else np.zeros(3))
    m, dirs, noise = np.array(means), np.array(dir_rows), np.array(noise_rows)

    def model_var(c: int, weights: np.ndarray) -> float:
        """Variance (V^2) of sum_w weights[w] * (window w's mean of channel c) from the model's coefficients."""
        if fit is None:
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
            spread = _horizontal_spread(m[h, c], dirs[h], c)
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
            others = np.array([j for j in range(3) if j != c])
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


def _horizontal_spread(m_v: np.ndarray, dirs: np.ndarray, c: int) -> float:
    """The variance (V^2) of the mean of channel ``c``'s outputs ``m_v`` over the windows where it is horizontal
    (``dirs`` their unit gravity directions), from their scatter: about the part linear in the other two
    components of gravity where the windows leave a degree of freedom beyond it (4 or more windows: the
    cross-axis sensitivities make opposite windows differ by 2 K_cj, a difference their mean cancels and no
    scatter of it), else about their mean (var / n, as with 2 or 3 windows, where the two cannot be told apart)."""
    n = m_v.size
    if n < 2:
        return 0.0
    others = [j for j in range(3) if j != c]
    X = np.column_stack([np.ones(n), np.round(dirs[:, others])])
    if n > X.shape[1] and np.linalg.matrix_rank(X) == X.shape[1]:
        coef, *_ = np.linalg.lstsq(X, m_v, rcond=None)
        r = m_v - X @ coef
        return float(r @ r) / (n - X.shape[1]) / n
    return float(m_v.var(ddof=1)) / n


def sweep_base(
    data: list[BlockData], settings: DifferentialSettings = SWEEP_SETTINGS, normal_temp_c: float = 20.0
) -> OrientationBase:
    """The constants at T0 of a unit from its sweeps alone (no base passport): a first differential fit from the
    constants the block data were made with (the nominal gain, zero offsets: :func:`observe`) finds the temperature
    terms, :func:`constants_from_orientations` the constants."""
    if data[0].constants is None:
        raise CalibrationError("block data without the constants they were made with")
    K_nom, U_nom = data[0].constants
    first = fit_differential(data, K_nom, U_nom, float(normal_temp_c), settings)
    return constants_from_orientations(data, first.model, np.diag(K_nom), first)
