"""Standard uncertainties (1 sigma) of the passport constants and of their temperature model.

Three steps, each linear propagation of independent errors:

1. **Segment means.** Each averaged static segment's mean output carries the voltmeter noise measured in it,
   ``std_v**2 / count`` (V^2), plus an *excess scatter* ``tau**2`` per channel: what the fit's residuals show beyond
   that noise (fixture face errors, settling, non-linearity). ``tau`` is pooled over all plateaus of the calibration,
   because one plateau leaves only two or three residual degrees of freedom per channel (:func:`excess_scatter_v`).
2. **Constants per plateau.** The six-position closed form and the least-squares fit are linear in the segment
   means, ``[K_i., U0_i] = W u_i`` for channel i; their variances are ``sum_k W[:, k]**2 var(u_ik)``
   (:func:`estimator_matrix`, :func:`plateau_sigma`).
3. **Temperature model.** Every coefficient of the polynomial or piecewise model of one constant is a function of
   that constant's values on the plateaus only (plateaus are independent). Each plateau value is moved by its own
   standard uncertainty and the model refitted; the changes, added in quadrature, are the coefficients' standard
   uncertainties (exact for the linear coefficients, first order for the relative beta and gamma, which divide by
   K(T0)). Where one constant's plateau values scatter about the model by more than their uncertainties allow, that
   excess scatter (per constant, :func:`model_excess_scatter`) is added in quadrature to each plateau's uncertainty
   of that constant before propagating (:func:`thermal_sigma`). Per constant and additive, not one pooled
   chi^2-per-dof ratio multiplying all: on a noiseless run some plateau values carry uncertainties at the readings'
   resolution (1e-16 V/g) and the model's own misfit (1e-10 V/g) divided by them made a ratio of thousands that
   multiplied every other uncertainty (49 ppm of K for constants exact to 1e-7 V/g).

A value the data cannot determine (a relative coefficient of a zero constant) is ``None``, never a made-up number.

The differential method (seed 003) fits its temperature coefficients by linear least squares over differenced block
means; :func:`regression_cov` gives their covariance from the fit's residuals (a sandwich estimator
clustered in time, so slowly varying misfit counts as what it is: correlated error) and from the noise measured in
the blocks, whichever is larger.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.positions import TEST_POSITIONS, gravity_vector_g


def estimator_matrix(positions: list[str], method: str) -> np.ndarray:
    """W (4, m): the fitted ``[K_ix, K_iy, K_iz, U0_i]`` of any channel i as ``W @ u_i`` over the m segment means.

    ``method``: ``six_position`` (repeats of a position averaged first, then the closed form of seed 000 eq. 11,
    which equals least squares over TP1..TP6) or ``least_squares`` (unweighted, over all m segments).
    """
    if method == "six_position":
        avg = np.zeros((len(TEST_POSITIONS), len(positions)))
        for r, name in enumerate(TEST_POSITIONS):
            idx = [k for k, p in enumerate(positions) if p == name]
            avg[r, idx] = 1.0 / len(idx)
        return np.linalg.pinv(design_matrix(list(TEST_POSITIONS))) @ avg
    return np.linalg.pinv(design_matrix(positions))


def segment_noise_var_v2(std_v: np.ndarray, count: np.ndarray, resolution_v: np.ndarray | None = None) -> np.ndarray:
    """Variance (V^2) of each segment mean from the noise measured in it, std^2 / n, plus the part of the readings'
    resolution q (``resolution_v``, (m, 3) or (3,) V) that averaging does not remove: shape (m, 3). Rounding to a
    step of q errs by a sawtooth in the true value; noise of standard deviation s dithers it, leaving a bias of the
    mean whose k-th harmonic is damped by exp(-2 pi^2 k^2 s^2 / q^2), so over an unknown position within a step its
    mean square is sum_k q^2 / (2 pi^2 k^2) exp(-4 pi^2 k^2 s^2 / q^2): q^2 / 12 where the readings do not move
    (a noiseless recording states its data's resolution, never 0), nothing where the noise spans a few steps (its
    rounding is then noise, already in std^2 / n). s is the measured std less the rounding's share (Sheppard's
    q^2 / 12): exact from about q / 2 of noise up, above the actual below that (a bound)."""
    std_v = np.asarray(std_v, dtype=float)
    n = np.maximum(np.asarray(count, dtype=float), 1.0)
    var = std_v**2 / n[:, None]
    if resolution_v is None:
        return var
    q = np.broadcast_to(np.asarray(resolution_v, dtype=float), var.shape)
    # the noise beneath the rounding: the measured variance less the rounding's own q^2 / 12 (Sheppard)
    noise2 = np.maximum(np.nan_to_num(std_v) ** 2 - q**2 / 12.0, 0.0)
    ratio2 = np.divide(noise2, q**2, out=np.full(var.shape, np.inf), where=q > 0)
    k2 = (np.arange(1, _RESOLUTION_HARMONICS + 1, dtype=float) ** 2)[:, None, None]
    bias2 = np.sum(q**2 / (2 * np.pi**2 * k2) * np.exp(-4 * np.pi**2 * k2 * ratio2), axis=0)
    return var + bias2


#: harmonics of the rounding error summed in :func:`segment_noise_var_v2` (at no noise the terms left out, about
#: q^2 / (2 pi^2 k), are 0.24 % of the q^2 / 12 the sum tends to at 256)
_RESOLUTION_HARMONICS = 256


def design_matrix(positions: list[str]) -> np.ndarray:
    """A (m, 4): the rows [a_x, a_y, a_z, 1] (g) of the segments' positions."""
    return np.array([np.append(gravity_vector_g(p), 1.0) for p in positions])


def excess_scatter_v(
    residuals_v: list[np.ndarray],
    noise_var_v2: list[np.ndarray],
    estimators: list[np.ndarray],
    designs: list[np.ndarray],
) -> np.ndarray:
    """Per channel (3,), V: the scatter of the segment means about the plateau fits beyond their measured noise.

    ``residuals_v`` (m_p, 3), ``noise_var_v2`` (m_p, 3), ``estimators`` (W, (4, m_p)) and ``designs`` (A, (m_p, 4))
    per plateau. A residual's
    expected square from noise alone is ``(1 - h_k) var_k`` (h_k the leverage of segment k); the excess of the
    pooled sum of squares over that, divided by the pooled degrees of freedom, is tau^2 (0 when the noise explains
    the residuals).
    """
    ss = np.zeros(3)
    expected = np.zeros(3)
    dof = 0.0
    for r, var, W, A in zip(residuals_v, noise_var_v2, estimators, designs):
        H = A @ W  # fitted means = H u
        lev = np.clip(np.diag(H), 0.0, 1.0)
        ss += np.sum(np.asarray(r) ** 2, axis=0)
        expected += np.sum((1.0 - lev)[:, None] * var, axis=0)
        dof += float(np.sum(1.0 - lev))
    if dof <= 0.5:
        return np.zeros(3)
    return np.sqrt(np.maximum(ss - expected, 0.0) / dof)


def plateau_sigma(W: np.ndarray, var_v2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standard uncertainties of one plateau's constants: K (3, 3) V/g and U0 (3,) V, from the segment-mean
    variances ``var_v2`` (m, 3) and the estimator W (4, m)."""
    var = (W**2) @ var_v2  # (4, 3): rows K_.x, K_.y, K_.z, U0; columns channel i
    sig = np.sqrt(var)
    return sig[:3].T.copy(), sig[3].copy()


@dataclass(frozen=True)
class ThermalSigma:
    """Standard uncertainties of a fitted temperature model: the normal-temperature constants and the model's
    coefficients in the passport's layout (``thermal_model`` dict with the same keys, values in the same units)."""

    K0: np.ndarray  # (3, 3) V/g
    U00: np.ndarray  # (3,) V
    thermal_model: dict
    birge_ratio: float  # sqrt(chi^2 / dof) of the plateau constants about the model (pooled), or nan
    dof: int
    #: further fields of the passport's ``uncertainty`` block, e.g. ``rate_terms`` (the differential method's rate
    #: terms, same layout as the passport's), ``undetermined`` ({field: why it has no uncertainty}) and
    #: ``fixed_by_convention`` ({field: the convention that fixes it; its uncertainty is 0})
    extra: dict | None = None
    #: what the uncertainties rest on (the passport's ``uncertainty.basis``); None: the tilt method's basis
    basis: dict | None = None


def thermal_sigma(
    fit_model, temps_c: np.ndarray, K: np.ndarray, U0: np.ndarray, K_sigma: np.ndarray, U0_sigma: np.ndarray
) -> ThermalSigma:
    """Propagate per-plateau uncertainties through ``fit_model(temps_c, K, U0) -> model`` (a polynomial or piecewise
    model of :mod:`pipeline.thermal` with ``K0``, ``U00``, ``constants_at`` and ``to_dict``).

    ``K`` (p, 3, 3), ``U0`` (p, 3) at ``temps_c`` (p,), ``K_sigma``/``U0_sigma`` their standard uncertainties.
    Each plateau is moved by +-1 sigma in all 12 constants at once: every output depends on one constant's column
    only, so one refit per plateau and sign gives the contributions of that plateau to every output.
    """
    temps_c = np.asarray(temps_c, dtype=float)
    base = fit_model(temps_c, K, U0)
    base_vec, layout = _flatten_model(base)
    ratio, dof = _birge(base, temps_c, K, U0, K_sigma, U0_sigma)  # reported, as measured before the excess
    tau_K, tau_U0 = model_excess_scatter(base, temps_c, K, U0, K_sigma, U0_sigma)
    K_sigma = np.sqrt(np.asarray(K_sigma, dtype=float) ** 2 + tau_K**2)
    U0_sigma = np.sqrt(np.asarray(U0_sigma, dtype=float) ** 2 + tau_U0**2)
    var = np.zeros_like(base_vec)
    for p in range(len(temps_c)):
        f = _step_factor(K[p], U0[p], K_sigma[p], U0_sigma[p])
        Kp, Kmi = K.copy(), K.copy()
        Up, Umi = U0.copy(), U0.copy()
        Kp[p] += f * K_sigma[p]
        Kmi[p] -= f * K_sigma[p]
        Up[p] += f * U0_sigma[p]
        Umi[p] -= f * U0_sigma[p]
        plus, _ = _flatten_model(fit_model(temps_c, Kp, Up))
        minus, _ = _flatten_model(fit_model(temps_c, Kmi, Umi))
        var += ((plus - minus) / (2.0 * f)) ** 2
    sig = np.sqrt(var)
    undetermined = ~np.isfinite(base_vec) | _undetermined_mask(base, layout)
    sig = np.where(undetermined, np.nan, sig)
    K0_sig = sig[:9].reshape(3, 3)
    U00_sig = sig[9:12]
    return ThermalSigma(
        K0=K0_sig,
        U00=U00_sig,
        thermal_model=_unflatten_model(base, sig[12:], layout),
        birge_ratio=float(ratio),
        dof=int(dof),
    )


def _step_factor(K: np.ndarray, U0: np.ndarray, K_sigma: np.ndarray, U0_sigma: np.ndarray) -> float:
    """How many times its uncertainties a plateau's constants are moved to propagate them (:func:`thermal_sigma`):
    1, unless the smallest non-zero uncertainty is within 1024 float64 spacings of the constants (a noiseless
    recording: uncertainties at the readings' resolution, which a move of one sigma loses to rounding, giving 0);
    then a power of two that lifts it there, at most to a move of 1e-6 of the largest constant (the relative
    coefficients stay linear to first order)."""
    s = np.concatenate([np.ravel(K_sigma), np.ravel(U0_sigma)])
    s = s[np.isfinite(s) & (s > 0)]
    if not s.size:
        return 1.0
    big = float(max(np.max(np.abs(K)), np.max(np.abs(U0))))
    lift = 1024.0 * float(np.spacing(big)) / float(s.min())
    if lift <= 1.0:
        return 1.0
    cap = max(1.0, 1e-6 * big / float(s.max()))
    return float(min(2.0 ** np.ceil(np.log2(lift)), 2.0 ** np.floor(np.log2(cap))))


def model_excess_scatter(
    model, temps_c: np.ndarray, K: np.ndarray, U0: np.ndarray, K_sigma: np.ndarray, U0_sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per constant, the scatter of its plateau values about the temperature model beyond their uncertainties:
    K (3, 3) V/g and U0 (3,) V. With n plateaus and dof = n - (the model's parameters) residual degrees of freedom,
    tau^2 = max(0, sum r^2 - (dof / n) sum sigma^2) / dof (the noise alone leaves about dof / n of each plateau's
    variance in its residual); 0 without residual degrees of freedom."""
    Km, U0m = model.constants_at(temps_c)
    n = len(temps_c)
    dof = n - _n_params(model)
    if dof <= 0:
        return np.zeros((3, 3)), np.zeros(3)
    r = np.concatenate([(K - Km).reshape(n, 9), U0 - U0m], axis=1)
    s = np.concatenate([np.asarray(K_sigma, dtype=float).reshape(n, 9), np.asarray(U0_sigma, dtype=float)], axis=1)
    s = np.where(np.isfinite(s), s, 0.0)
    tau2 = np.maximum(np.sum(r**2, axis=0) - dof / n * np.sum(s**2, axis=0), 0.0) / dof
    tau = np.sqrt(np.where(np.isfinite(tau2), tau2, 0.0))
    return tau[:9].reshape(3, 3), tau[9:]


def _birge(model, temps_c, K, U0, K_sigma, U0_sigma) -> tuple[float, int]:
    """sqrt(chi^2/dof) of the plateau constants about the model, pooled over the 12 constants (nan if dof = 0)."""
    Km, U0m = model.constants_at(temps_c)
    r = np.concatenate([(K - Km).reshape(len(temps_c), 9), U0 - U0m], axis=1)
    s = np.concatenate([K_sigma.reshape(len(temps_c), 9), U0_sigma], axis=1)
    n_params = _n_params(model)
    dof = len(temps_c) - n_params
    if dof <= 0:
        return float("nan"), 0
    ok = s > 0
    chi2 = float(np.sum((r[ok] / s[ok]) ** 2))
    cols = int(np.sum(np.any(ok, axis=0)))
    return float(np.sqrt(chi2 / max(1, dof * cols))), int(dof)


def _n_params(model) -> int:
    if hasattr(model, "order"):
        return int(model.order) + 1
    return len(model.nodes_c)


def _flatten_model(model) -> tuple[np.ndarray, list]:
    """K0 (9), U00 (3) and every number of ``model.to_dict()``'s coefficients, in a fixed order; the layout lists
    (path, length) of each coefficient list so the sigmas can be put back in the same shape."""
    parts = [np.asarray(model.K0, float).reshape(9), np.asarray(model.U00, float).reshape(3)]
    layout = []
    d = model.to_dict()
    for path, values in _coefficient_lists(d):
        arr = np.atleast_1d(np.asarray(values, dtype=float))
        layout.append((path, arr.size, np.ndim(values) == 0))
        parts.append(arr)
    return np.concatenate(parts), layout


def _coefficient_lists(d: dict):
    """(path, value) for each coefficient in a thermal-model dict, in a fixed order."""
    if d.get("kind") == "polynomial":
        for group in ("alpha", "beta", "gamma"):
            for key in sorted(d.get(group) or {}):
                yield (group, key), d[group][key]
    else:
        for s, seg in enumerate(d.get("segments") or []):
            for group in ("alpha", "beta", "gamma"):
                for key in sorted(seg.get(group) or {}):
                    yield ("segments", s, group, key), seg[group][key]


def _undetermined_mask(model, layout) -> np.ndarray:
    """True where a relative coefficient (beta, gamma) divides by a zero constant: not determined by the data."""
    K0 = np.asarray(model.K0, float)
    mask = [False] * 12
    for path, n, _ in layout:
        group, key = path[-2], path[-1]
        zero = False
        if group in ("beta", "gamma"):
            i, j = "xyz".index(key[0]), "xyz".index(key[1])
            zero = K0[i, j] == 0
        mask += [zero] * n
    return np.array(mask)


def _unflatten_model(model, sig: np.ndarray, layout) -> dict:
    """The model's dict with every coefficient replaced by its standard uncertainty (None where undetermined)."""
    d = model.to_dict()
    out = {k: v for k, v in d.items() if k not in ("alpha", "beta", "gamma", "segments")}
    if d.get("kind") != "polynomial":
        out["segments"] = [
            {k: v for k, v in seg.items() if k not in ("alpha", "beta", "gamma")} for seg in d.get("segments") or []
        ]
    pos = 0
    for path, n, scalar in layout:
        vals = [None if not np.isfinite(v) else float(v) for v in sig[pos : pos + n]]
        pos += n
        value = vals[0] if scalar else vals
        if path[0] == "segments":
            out["segments"][path[1]].setdefault(path[2], {})[path[3]] = value
        else:
            out.setdefault(path[0], {})[path[1]] = value
    return out


def as_json_list(a):
    """Sigmas as plain JSON: arrays as nested lists, dicts and lists recursively, every undetermined (non-finite)
    value None."""
    if isinstance(a, dict):
        return {k: as_json_list(v) for k, v in a.items()}
    if isinstance(a, (list, tuple)):
        return [as_json_list(x) for x in a]
    if isinstance(a, (str, bool, int)) or a is None:
        return a
    a = np.asarray(a, dtype=float)
    if a.ndim == 0:
        return None if not np.isfinite(a) else float(a)
    return [as_json_list(x) for x in a]


def regression_cov(X: np.ndarray, resid: np.ndarray, noise_var: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """Covariance (p, p) of the coefficients of an unweighted least-squares fit ``y = X b`` (X (n, p)), in the units
    of b; NaN rows and columns for a column of zeros (a term the data does not hold).

    Two estimates, the larger variance kept per coefficient (with the correlations of the first):

    - from the residuals ``resid`` (n,): the sandwich ``(X'X)^-1 (sum_g s_g s_g') (X'X)^-1`` with ``s_g`` the sum
      of ``x_k r_k`` over the equations of cluster g (``clusters`` (n,), e.g. stretches of time), times
      ``G/(G-1) (n-1)/(n-p)``: residuals that are correlated within a cluster (a misfit that drifts with the
      temperature) count as correlated, not as independent noise. ``clusters`` (k, n): k ways of clustering (long
      stretches for a slow misfit, short ones for a short-range correlation that few long clusters estimate too
      noisily), the largest sandwich variance kept per coefficient;
    - from the noise measured in the data: ``(X'X)^-1 X' diag(noise_var) X (X'X)^-1`` with ``noise_var`` (n,) the
      variance of each equation's left side from the voltmeter noise alone.
    """
    X = np.asarray(X, dtype=float)
    n, p = X.shape
    scale = np.linalg.norm(X, axis=0)
    empty = scale == 0
    scale[empty] = 1.0
    Xs = X / scale
    bread = np.linalg.pinv(Xs.T @ Xs)
    var_r = []
    for k, ids in enumerate(np.atleast_2d(np.asarray(clusters))):
        _, inv = np.unique(ids, return_inverse=True)
        G = int(inv.max()) + 1 if inv.size else 0
        S = np.zeros((G, p))
        np.add.at(S, inv, Xs * np.asarray(resid, dtype=float)[:, None])
        factor = G / (G - 1) * (n - 1) / (n - p) if G > 1 and n > p else 1.0
        cov_k = bread @ (S.T @ S) @ bread * factor
        if k == 0:
            cov_r = cov_k
        var_r.append(np.diag(cov_k))
    var_n = np.diag(bread @ ((Xs.T * np.asarray(noise_var, dtype=float)) @ Xs) @ bread)
    sd_r = np.sqrt(np.maximum(np.diag(cov_r), 0.0))
    sd = np.sqrt(np.maximum(np.max(var_r, axis=0), np.maximum(var_n, 0.0)))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.where(np.outer(sd_r, sd_r) > 0, cov_r / np.outer(sd_r, sd_r), np.eye(p))
    cov = corr * np.outer(sd, sd) / np.outer(scale, scale)
    cov[empty, :] = np.nan
    cov[:, empty] = np.nan
    return cov
