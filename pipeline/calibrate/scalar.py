"""Scalar (orientation-free) calibration of an accelerometer triad (seed 004, Lakoza and Meleshko).

In every static position the specific force has modulus 1 g, whatever the orientation, so the constants can be
fitted without knowing the positions. With a preliminary gain ``k_p`` (V/g) and offset ``u0_p`` (V) per channel the
normalised outputs are ``B_i = (U_i - u0_p_i) / k_p_i`` and the paper's signal model (eq. 4) is

    B = D0 + (I + diag(D1) + M) a + D2 a^2 + noise

with offset errors D0 (g), scale-factor errors D1, quadratic errors D2 (1/g) and misalignments M (off-diagonal).
Only the symmetric combinations of M change |B|, so the scalar method determines the pairwise combinations
(docs/physics.md, docs/methods.md)

    psi_xy = M_xy + M_yx,  psi_xz = M_xz + M_zx,  psi_yz = M_yz + M_zy

(the paper's a_xz - a_yz, a_zy - a_xy, a_yx - a_zx), never the individual misalignments: a rotation of the whole triad
leaves every |a| unchanged. This module fixes that rotation gauge by taking K lower-triangular (the x axis along the
x channel's sensitive axis, the y axis in the plane of the x and y sensitive axes), so that M holds psi below the
diagonal and zeros above it.

- :func:`scalar_first_order`: the paper's linear solution. To first order in the errors (a replaced by B, eq. 11)

      (Bx^2 + By^2 + Bz^2 - 1) / 2 = sum_i (D0_i B_i + D1_i B_i^2 [+ D2_i B_i^3]) + sum_{i<j} psi_ij B_i B_j

  is linear in the 9 (or 12) unknowns; least squares over the positions.
- :func:`scalar_nonlinear`: the exact problem, |T (B - d)| = 1 at every position with T = (I + diag(D1) + M)^-1
  lower-triangular (6 parameters) and d = D0 (3): 9 parameters by nonlinear least squares (Levenberg-Marquardt).
  ``model="diagonal"`` assumes orthogonal axes (3 gains and 3 offsets), which six positions can determine.

Both return a :class:`ScalarFit` with K (3, 3) V/g, U0 (3,) V in the model of docs/physics.md (U = K a + U0).
:func:`calibrate` makes a passport (method ``scalar``) from runs: all static segments on the normal-temperature
plateau, named or not.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.calibrate.method import Fitted, Method, Support
from pipeline.calibrate.observations import ObservedRun, observations_from_segmentation, unit_of
from pipeline.calibrate.recording import Recording
from pipeline.calibrate.result import PlateauConstants, UnitFit
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import CalibrationError
from pipeline.model import gravity_module_error_g, specific_force_g
from pipeline.passport.document import Passport
from pipeline.positions import AXES
from pipeline.segment import segment_run
from pipeline.thermal import PolynomialModel
from pipeline.uncertainty import ThermalSigma, as_json_list

#: channel pairs of psi_xy, psi_xz, psi_yz
PSI_PAIRS = ((0, 1), (0, 2), (1, 2))
PSI_NAMES = ("xy", "xz", "yz")
_LOWER = np.tril_indices(3, -1)  # (1,0), (2,0), (2,1): psi_xy, psi_xz, psi_yz in the lower gauge
_TRIL = np.tril_indices(3)  # the 6 entries of a lower-triangular T
#: smallest singular value of the first-order design per sqrt(weight) that counts as "determined" (a direction
#: product B_i B_j of RMS 0.26 over random orientations gives about 0.1; six axis-aligned positions give ~0)
MIN_SPREAD = 0.02


@dataclass(frozen=True)
class ScalarFit:
    """Result of a scalar calibration.

    ``K`` (3, 3) V/g lower-triangular (the rotation gauge of the module doc), ``U0`` (3,) V. In the paper's terms,
    relative to the preliminary constants: ``d0`` (3,) offset errors in g, ``d1`` (3,) scale-factor errors,
    ``psi`` (3,) the misalignment combinations psi_xy, psi_xz, psi_yz, ``d2`` (3,) quadratic errors in 1/g (first
    order with ``quadratic=True`` only; not part of K). ``norm_error_g`` (m,) = |a_hat| - 1 at the positions used,
    with K and U0. ``spread`` is the smallest singular value of the first-order design per sqrt(weight).
    ``std`` (9,): standard errors of (d0, d1, psi) from the fit's residual scatter and its Jacobian (NaN where not
    fitted, or with no redundancy).
    """

    K: np.ndarray
    U0: np.ndarray
    d0: np.ndarray
    d1: np.ndarray
    psi: np.ndarray
    norm_error_g: np.ndarray
    method: str  # "scalar_first_order" | "scalar_nonlinear"
    model: str  # "full" | "diagonal"
    n_positions: int
    spread: float
    #: distinct positions among the ``n_positions`` (repeats of one orientation count once)
    n_distinct: int = 0
    std: np.ndarray = field(default_factory=lambda: np.full(9, np.nan))
    d2: np.ndarray | None = None
    k_prelim_v_per_g: np.ndarray = field(default_factory=lambda: np.ones(3))
    u0_prelim_v: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def summary(self) -> dict:
        """JSON-able summary (the passport's ``scalar`` field)."""
        out = {
            "method": self.method,
            "model": self.model,
            "n_positions": int(self.n_positions),
            "gauge": "K lower-triangular: x along the x channel's sensitive axis, y in the x-y sensitive plane",
            "d0_g": self.d0.tolist(),
            "d1": self.d1.tolist(),
            "psi": dict(zip(PSI_NAMES, self.psi.tolist())),
            "k_prelim_v_per_g": np.asarray(self.k_prelim_v_per_g).tolist(),
            "u0_prelim_v": np.asarray(self.u0_prelim_v).tolist(),
            "norm_error_rms_g": float(np.sqrt(np.mean(self.norm_error_g**2))),
            "norm_error_max_abs_g": float(np.max(np.abs(self.norm_error_g))),
            "spread": float(self.spread),
            "std": {  # null where not fitted or without redundancy (gauge_notes names why)
                "d0_g": as_json_list(self.std[0:3]),
                "d1": as_json_list(self.std[3:6]),
                "psi": dict(zip(PSI_NAMES, as_json_list(self.std[6:9]))),
            },
        }
        if self.d2 is not None:
            out["d2_per_g"] = self.d2.tolist()
        return out


def normalise(u_v: np.ndarray, k_prelim_v_per_g, u0_prelim_v) -> np.ndarray:
    """B = (U - u0_p) / k_p per channel (m, 3), in g."""
    return (np.atleast_2d(np.asarray(u_v, dtype=float)) - np.asarray(u0_prelim_v, float)) / np.asarray(
        k_prelim_v_per_g, float
    )


def preliminary_from_outputs(u_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A rough preliminary gain (V/g) and offset (V) per channel from the spread of the outputs, no positions needed:
    offset = (max + min) / 2 and gain = (max - min) / 2 over the positions (the six-position formula when each axis
    was up and down once; within a few per cent otherwise).

    The gains come out positive: the sign of a gain cannot be seen in |a| = 1 (a reflected K fits as well), and the
    fitted K keeps the preliminary's signs. Pass a signed nominal gain where it is known."""
    u = np.atleast_2d(np.asarray(u_v, dtype=float))
    hi, lo = u.max(axis=0), u.min(axis=0)
    return (hi - lo) / 2.0, (hi + lo) / 2.0


def _design(B: np.ndarray, model: str, quadratic: bool) -> np.ndarray:
    """First-order regressors (m, p): B_i (D0), B_i^2 (D1), [B_i B_j (psi)], [B_i^3 (D2)]."""
    cols = [B, B**2]
    if model == "full":
        cols.append(np.column_stack([B[:, i] * B[:, j] for i, j in PSI_PAIRS]))
    if quadratic:
        cols.append(B**3)
    return np.concatenate(cols, axis=1)


def n_parameters(model: str, quadratic: bool = False) -> int:
    """The parameters the scalar ``model`` fits: 3 offsets, 3 gains, the 3 misalignment combinations (``full``),
    3 quadratic terms (``quadratic``)."""
    return 6 + 3 * (model == "full") + 3 * quadratic


def _check_positions(B: np.ndarray, w: np.ndarray, model: str, quadratic: bool) -> tuple[float, int]:
    """Smallest singular value of the weighted first-order design per sqrt(sum w), and the number of distinct
    positions; CalibrationError when the positions cannot determine the model."""
    A = _design(B, model, quadratic)
    p = A.shape[1]
    distinct = len(np.unique(np.round(B, 2), axis=0))
    if distinct < p:
        need = {
            "full": "9 well-spread positions (12 with quadratic terms)",
            "diagonal": "6 positions (each axis up and down)",
        }[model]
        raise CalibrationError(
            f"scalar calibration ({model} model) needs at least {p} distinct static positions, "
            f"got {distinct}: use {need}"
        )
    sv = np.linalg.svd(A * np.sqrt(w / w.sum())[:, None], compute_uv=False)
    spread = float(sv[-1])
    if spread < MIN_SPREAD:
        hint = (
            (
                "the pairwise misalignments need positions with gravity between two axes (e.g. VP1..VP6); "
                "with axis-aligned positions only use model='diagonal'"
            )
            if model == "full"
            else "each axis must point roughly up and down"
        )
        raise CalibrationError(
            f"static positions are not spread enough for the scalar {model} model "
            f"(smallest singular value {spread:.2g} < {MIN_SPREAD}): {hint}"
        )
    return spread, distinct


def _weights(m: int, weights) -> np.ndarray:
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (m,) or not np.all(w > 0):
        raise ValueError(f"weights must be {m} positive numbers")
    return w


def _standard_errors(
    jac: np.ndarray, resid: np.ndarray, transform: np.ndarray | None = None, floor_g: float = 0.0
) -> np.ndarray:
    """sqrt(diag(G cov G^T)) with cov = s^2 (J^T J)^-1, s^2 = |r|^2 / (m - p), at least ``floor_g``^2 (the norm
    error the readings' resolution alone leaves in one position, g); NaN without redundancy."""
    m, p = jac.shape
    if m <= p:
        return np.full(p if transform is None else transform.shape[0], np.nan)
    cov = np.linalg.pinv(jac.T @ jac) * max(float(resid @ resid) / (m - p), floor_g**2)
    if transform is not None:
        cov = transform @ cov @ transform.T
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


def _pad9(model: str, values: np.ndarray) -> np.ndarray:
    """(d0, d1[, psi]) -> (9,), NaN for the psi of the diagonal model."""
    return values[:9] if model == "full" else np.concatenate([values[:6], np.full(3, np.nan)])


def _to_constants(k_p, u0_p, d0, kn) -> tuple[np.ndarray, np.ndarray]:
    """K = diag(k_p) Kn, U0 = u0_p + k_p d0 (Kn: the normalised K = I + diag(D1) + M)."""
    k_p = np.asarray(k_p, dtype=float)
    return k_p[:, None] * kn, np.asarray(u0_p, dtype=float) + k_p * d0


def _inputs(u_v, k_prelim_v_per_g, u0_prelim_v, weights, model):
    if model not in ("full", "diagonal"):
        raise ValueError(f"unknown scalar model {model!r} (full, diagonal)")
    u = np.atleast_2d(np.asarray(u_v, dtype=float))
    if u.ndim != 2 or u.shape[1] != 3 or not np.all(np.isfinite(u)):
        raise CalibrationError("scalar calibration needs finite mean outputs of shape (m, 3)")
    k_p = np.asarray(k_prelim_v_per_g, dtype=float) * np.ones(3)
    u0_p = np.asarray(u0_prelim_v, dtype=float) * np.ones(3)
    if np.any(k_p == 0):
        raise ValueError("preliminary gains must be non-zero")
    return u, k_p, u0_p, _weights(len(u), weights)


def scalar_first_order(
    u_v: np.ndarray,
    k_prelim_v_per_g,
    u0_prelim_v,
    *,
    model: str = "full",
    quadratic: bool = False,
    weights: np.ndarray | None = None,
) -> ScalarFit:
    """The paper's linear first-order solution (seed 004, eq. 11) from mean outputs ``u_v`` (m, 3) V in m static
    positions of unknown orientation.

    ``k_prelim_v_per_g``, ``u0_prelim_v``: the preliminary gains (V/g, signed) and offsets (V) that normalise the
    outputs; the method is valid while the remaining errors (D0, D1, psi) are small compared with 1 (the paper: up
    to about 1 % for a 5 % error of the estimates; misalignment terms of 0.005-0.01 already cost 10-20 %).
    ``model="diagonal"`` drops the psi terms, ``quadratic=True`` adds D2 (B_i^3 regressors; reported, not in K).
    ``weights`` (m,) e.g. the sample counts.
    """
    u, k_p, u0_p, w = _inputs(u_v, k_prelim_v_per_g, u0_prelim_v, weights, model)
    B = normalise(u, k_p, u0_p)
    spread, distinct = _check_positions(B, w, model, quadratic)
    A = _design(B, model, quadratic)
    y = (np.sum(B**2, axis=1) - 1.0) / 2.0
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)
    std = _pad9(model, _standard_errors(A * sw[:, None], (y - A @ coef) * sw))
    d0, d1 = coef[0:3], coef[3:6]
    psi = coef[6:9] if model == "full" else np.zeros(3)
    d2 = coef[-3:] if quadratic else None
    kn = np.eye(3) + np.diag(d1)
    kn[_LOWER] = psi
    K, U0 = _to_constants(k_p, u0_p, d0, kn)
    dg = gravity_module_error_g(specific_force_g(K, U0, u))
    return ScalarFit(
        K=K,
        U0=U0,
        d0=d0,
        d1=d1,
        psi=psi,
        norm_error_g=dg,
        method="scalar_first_order",
        model=model,
        n_positions=len(u),
        spread=spread,
        n_distinct=distinct,
        std=std,
        d2=d2,
        k_prelim_v_per_g=k_p,
        u0_prelim_v=u0_p,
    )


def _unpack(p: np.ndarray, model: str) -> tuple[np.ndarray, np.ndarray]:
    """Parameters -> offsets d (3,) and T (3, 3) lower-triangular (diagonal for the diagonal model)."""
    T = np.zeros((3, 3))
    if model == "full":
        T[_TRIL] = p[3:]
    else:
        T[np.diag_indices(3)] = p[3:]
    return p[:3], T


def _residual_and_jacobian(B: np.ndarray, sw: np.ndarray, model: str):
    def residual(p):
        d, T = _unpack(p, model)
        return (np.linalg.norm((B - d) @ T.T, axis=1) - 1.0) * sw

    def jacobian(p):
        d, T = _unpack(p, model)
        x = B - d  # (m, 3)
        a = x @ T.T
        n = a / np.linalg.norm(a, axis=1)[:, None]  # d|a|/da
        jd = -n @ T  # d/dd
        if model == "full":
            jt = n[:, _TRIL[0]] * x[:, _TRIL[1]]  # d|a|/dT_ij = n_i x_j
        else:
            jt = n * x
        return np.concatenate([jd, jt], axis=1) * sw[:, None]

    return residual, jacobian


def _output_transform(kn: np.ndarray, model: str) -> np.ndarray:
    """d(d0, d1[, psi]) / d(d, T parameters) at the solution: d kn = -kn dT kn."""
    idx = _TRIL if model == "full" else np.diag_indices(3)
    out = [(np.arange(3), np.arange(3))] + ([_LOWER] if model == "full" else [])
    n_t = len(idx[0])
    G = np.zeros((3 + 3 + (3 if model == "full" else 0), 3 + n_t))
    G[0:3, 0:3] = np.eye(3)
    for k, (i, j) in enumerate(zip(*idx)):
        dkn = -np.outer(kn[:, i], kn[j, :])
        G[3:, 3 + k] = np.concatenate([dkn[o] for o in out])
    return G


def scalar_nonlinear(
    u_v: np.ndarray,
    k_prelim_v_per_g,
    u0_prelim_v,
    *,
    model: str = "full",
    weights: np.ndarray | None = None,
    start: ScalarFit | None = None,
    resolution_v=None,
) -> ScalarFit:
    """The constants up to a rotation by nonlinear least squares of |K^-1 (U - U0)| - 1 over the positions.

    In normalised outputs B (see :func:`normalise`) the unknowns are the offsets d (3, g) and T = K_n^-1
    lower-triangular (6), 9 parameters (``model="diagonal"``: T diagonal, 6 parameters), started from the identity
    (the preliminary constants) or from ``start``. Valid for errors of any size the preliminary constants leave
    (low-grade sensors, offsets of several per cent, cross-axis terms of 0.03), where the first-order solution is
    not. Raises CalibrationError when the positions are too few or not spread enough (at least 9 well-spread
    positions for the full model). ``resolution_v`` (3,) V: the readings' resolution, a floor of the residual
    scatter the uncertainties are scaled by (a noiseless recording's are then its data's resolution, never 0).
    """
    u, k_p, u0_p, w = _inputs(u_v, k_prelim_v_per_g, u0_prelim_v, weights, model)
    B = normalise(u, k_p, u0_p)
    spread, distinct = _check_positions(B, w, model, False)
    if start is not None:
        kn0 = np.asarray(start.K, float) / k_p[:, None]
        d_init = (np.asarray(start.U0, float) - u0_p) / k_p
        t_init = np.linalg.inv(kn0)
    else:
        d_init, t_init = np.zeros(3), np.eye(3)
    p0 = np.concatenate([d_init, t_init[_TRIL] if model == "full" else np.diag(t_init)])
    residual, jacobian = _residual_and_jacobian(B, np.sqrt(w / w.mean()), model)
    from scipy.optimize import least_squares  # ~0.3 s to import: only where a scalar fit runs, not to judge a run

    sol = least_squares(
        residual, p0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200 * len(p0)
    )
    if not np.all(np.isfinite(sol.x)):
        raise CalibrationError("scalar nonlinear fit did not converge")
    d, T = _unpack(sol.x, model)
    if np.any(np.diag(T) <= 0):
        raise CalibrationError(
            "scalar nonlinear fit converged to a reflected solution; check the preliminary gains' signs"
        )
    kn = np.linalg.inv(T)
    K, U0 = _to_constants(k_p, u0_p, d, kn)
    dg = gravity_module_error_g(specific_force_g(K, U0, u))
    # one position's norm error from the readings' resolution q alone: q / k per channel, uniform within a step,
    # along a direction averaging a_c^2 = 1/3
    q_g = np.zeros(3) if resolution_v is None else np.asarray(resolution_v, dtype=float) / np.abs(k_p)
    floor_g = float(np.sqrt(np.mean(q_g**2) / 12.0))
    std = _pad9(model, _standard_errors(jacobian(sol.x), sol.fun, _output_transform(kn, model), floor_g))
    return ScalarFit(
        K=K,
        U0=U0,
        d0=d,
        d1=np.diag(kn) - 1.0,
        psi=kn[_LOWER].copy(),
        norm_error_g=dg,
        method="scalar_nonlinear",
        model=model,
        n_positions=len(u),
        spread=spread,
        n_distinct=distinct,
        std=std,
        k_prelim_v_per_g=k_p,
        u0_prelim_v=u0_p,
    )


def constants_sigma(fit: ScalarFit) -> tuple[np.ndarray, np.ndarray]:
    """Standard uncertainties of the scalar fit's K (3, 3) V/g and U0 (3,) V, from the fit's own parameter standard
    errors (residual-scaled, :func:`_standard_errors`): K = diag(k_p) K_n and U0 = u0_p + k_p d0, so sigma(K_ij) =
    |k_p_i| sigma(d1_i) on the diagonal and |k_p_i| sigma(psi) below it, sigma(U0_i) = |k_p_i| sigma(d0_i).
    The upper entries are 0 exactly, by the rotation gauge (:func:`gauge_notes`): sigma 0. The diagonal model has no
    cross-axis terms at all (orthogonal axes assumed): NaN (not determined). Without redundancy (no more positions
    than parameters) the fitted entries are NaN too (:func:`gauge_notes` names them)."""
    k = np.abs(np.asarray(fit.k_prelim_v_per_g, dtype=float))
    K_sig = np.full((3, 3), np.nan)
    K_sig[np.diag_indices(3)] = k * fit.std[3:6]
    if fit.model == "full":
        K_sig[_LOWER] = k[_LOWER[0]] * fit.std[6:9]
        K_sig[np.triu_indices(3, 1)] = 0.0
    return K_sig, k * fit.std[0:3]


def gauge_notes(fit: ScalarFit) -> tuple[dict[str, str], dict[str, str]]:
    """The passport's ``uncertainty.fixed_by_convention`` and ``uncertainty.undetermined`` of a scalar fit: K's
    upper entries are 0 by the rotation gauge (|a| = 1 cannot see a rotation of the triad: their uncertainty is 0,
    the convention fixes them); with the diagonal model the cross-axis entries are not determined (0 by the
    assumption of orthogonal axes; uncertainty null)."""
    upper = [f"K.{AXES[i]}{AXES[j]}" for i, j in zip(*np.triu_indices(3, 1))]
    lower = [f"K.{AXES[i]}{AXES[j]}" for i, j in zip(*_LOWER)]
    fitted = [f"U0.{a}" for a in AXES] + [f"K.{a}{a}" for a in AXES] + (lower if fit.model == "full" else [])
    n_params = n_parameters(fit.model)
    unscaled = (
        {}
        if fit.n_positions > n_params
        else {
            n: f"{fit.n_positions} positions for the {n_params} parameters of the {fit.model} scalar model: no "
            f"redundancy, so no scatter to measure its uncertainty by (at least {n_params + 1} positions)"
            for n in fitted
        }
    )
    if fit.model == "full":
        return (
            {
                n: "0 by the rotation gauge: K lower-triangular (x along the x channel's sensitive axis, y in the "
                "x-y sensitive plane); a scalar calibration cannot see a rotation of the triad"
                for n in upper
            },
            unscaled,
        )
    return {}, {
        **unscaled,
        **{
            n: "diagonal scalar model: orthogonal axes assumed, cross-axis sensitivity not determined (0)"
            for n in upper + lower
        },
    }


def lower_gauge(K: np.ndarray) -> np.ndarray:
    """The lower-triangular K' = K R^T (R a rotation) with the same K K^T and the signs of K's diagonal: the form
    in which a scalar calibration can recover ``K`` (for comparing a fit with a truth)."""
    K = np.asarray(K, dtype=float)
    L = np.linalg.cholesky(K @ K.T)  # lower, positive diagonal, L L^T = K K^T
    s = np.sign(np.diag(K))
    return L * s[None, :]  # flip columns: L diag(s) diag(s) L^T = K K^T


# ---------------------------------------------------------------------------------------------------------------
# The recipe: from runs to a passport

#: The passport's ``method`` for this recipe.
METHOD = "scalar"


#: a scalar calibration needs at least this many distinct poses for the full model (gains, offsets, 3 psi
#: combinations), and this many for gains and offsets only (``inspect``: poses within 3 C of T0)
FULL_POSES = 9
DIAGONAL_POSES = 6
#: how much ``--method auto`` prefers the scalar method (:attr:`pipeline.calibrate.method.Support.preference`):
#: above the tilt method on many poses at one temperature when no fixture log says where they are (poses named
#: from gravity alone are not known to a fixture's precision: a hand-turned fixture) and the tilt method would not
#: determine a thermal model, or when it cannot run at all; last otherwise, and always on a sweep
PREFERENCE_POSES = 25.0
PREFERENCE = 0.0


class Scalar(Method):
    """Seed 004's scalar calibration: |a| = 1 g in every static pose, the poses need not be known."""

    name = "scalar"
    passport_method = METHOD

    def supports(self, recording: Recording) -> Support:
        """Distinct static poses within 3 C of T0: the full model from :data:`FULL_POSES`, gains and offsets from
        :data:`DIAGONAL_POSES`."""
        t0 = float(recording.run.meta.normal_temp_c)
        k = len(recording.poses_near(t0))
        n = len(recording.constant_plateaus)
        preferred = recording.program.kind != "sweep" and (
            (k >= FULL_POSES and not recording.fixture_logged and n < 2) or (k >= DIAGONAL_POSES and n == 0)
        )
        return Support(
            supported=k >= DIAGONAL_POSES,
            why=f"{k} distinct static poses within 3 C of T0 ({t0:g} C)",
            determines=(
                (
                    "gains and offsets at T0",
                    "psi_xy, psi_xz, psi_yz (sums of cross-axis pairs; the "
                    "individual cross-axis terms are not determined)",
                )
                if k >= FULL_POSES
                else (
                    "gains and offsets at T0 (orthogonal axes assumed: too few poses for the cross-axis combinations)",
                )
                if k >= DIAGONAL_POSES
                else ()
            ),
            preference=PREFERENCE_POSES if preferred else PREFERENCE,
        )

    def observe(
        self,
        run,
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        segmentation=None,
        **fit_options,
    ) -> ObservedRun:
        """The run's observations (named segments, for the verification and the plateau summary) and, as
        ``data``, every static segment on a plateau with finite mean outputs, named or not (orientations are not
        used). ``segmentation``: the run's, if already made with ``settings.segment``; ``fit_options``: the
        fit's (:meth:`fit`), not used here."""
        seg = segmentation if segmentation is not None else segment_run(run, settings.segment)
        static = [s for s in seg.segments if s.plateau is not None and s.count > 0 and np.all(np.isfinite(s.mean_v))]
        return ObservedRun(
            meta=run.meta,
            source=run.source,
            warnings=list(run.warnings),
            data=static,
            observations=observations_from_segmentation(run.meta.run_id, seg, run.source),
        )

    def fit(
        self,
        observed: list[ObservedRun],
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        normal_temp_c: float | None = None,
        model: str = "auto",
        k_prelim_v_per_g=None,
        u0_prelim_v=None,
    ) -> Fitted:
        """The scalar nonlinear fit over every static segment on the plateaus within ``settings.cluster_tol_c`` of
        the normal temperature, polynomial thermal model of order 0 (K and U0 at T0).

        Preliminary constants: the runs' ``nominal_gain_v_per_g`` (sign included) and zero offsets when the
        metadata has a gain, else :func:`preliminary_from_outputs`. ``model``: ``full`` (>= 9 spread positions,
        e.g. the standard program's TP and VP positions at +20 C), ``diagonal`` (orthogonal axes, >= 6 positions)
        or ``auto`` (full when the positions determine it, else diagonal, with a note in the passport). The
        passport's field ``scalar`` holds the fit's details (:meth:`ScalarFit.summary`).
        """
        serial = unit_of(observed)
        meta = observed[0].meta
        t0 = float(meta.normal_temp_c if normal_temp_c is None else normal_temp_c)
        static = [(r.meta.run_id, s) for r in observed for s in r.data if abs(s.temp_c - t0) <= settings.cluster_tol_c]
        if not static:
            raise CalibrationError(
                f"no static segment on a plateau within {settings.cluster_tol_c} C of the normal temperature "
                f"{t0:+.1f} C",
                stream="voltmeter",
            )
        u = np.array([s.mean_v for _, s in static])
        w = np.array([s.count for _, s in static], dtype=float)
        if k_prelim_v_per_g is None:
            k_auto, u0_auto = preliminary_from_outputs(u)
            gain = meta.nominal_gain_v_per_g
            k_prelim_v_per_g = np.full(3, gain) if gain else k_auto
            u0_prelim_v = np.zeros(3) if gain else u0_auto
        elif u0_prelim_v is None:
            u0_prelim_v = np.zeros(3)
        notes: list[str] = []
        q = [o.resolution_v for r in observed for o in r.observations]
        res = {"resolution_v": np.max(np.array(q), axis=0) if q else None}
        if model == "auto":
            try:
                fit_s = scalar_nonlinear(u, k_prelim_v_per_g, u0_prelim_v, model="full", weights=w, **res)
            except CalibrationError as e:
                fit_s = scalar_nonlinear(u, k_prelim_v_per_g, u0_prelim_v, model="diagonal", weights=w, **res)
                notes.append(
                    f"scalar: the full model is not determined ({e.message}); fitted the diagonal model "
                    "(orthogonal axes: three gains and three offsets, no cross-axis terms)"
                )
        else:
            fit_s = scalar_nonlinear(u, k_prelim_v_per_g, u0_prelim_v, model=model, weights=w, **res)
        temp = float(np.average([s.temp_c for _, s in static], weights=w))
        names = [s.position or "unnamed" for _, s in static]
        # output residual: the norm error seen through the gains, dg |K_ii| (V)
        resid_v = fit_s.norm_error_g[:, None] * np.abs(np.diag(fit_s.K))[None, :]
        K_sig, U0_sig = constants_sigma(fit_s)
        plateau = PlateauConstants(
            run_id=static[0][0],
            plateau=int(static[0][1].plateau),
            temp_c=temp,
            K=fit_s.K,
            U0=fit_s.U0,
            positions=tuple(dict.fromkeys(names)),
            method=fit_s.method,
            residual_rms_v=float(np.sqrt(np.mean(resid_v**2))),
            K_sigma=K_sig,
            U0_sigma=U0_sig,
        )
        thermal = PolynomialModel(fit_s.K, fit_s.U0, t0, 0, np.zeros((0, 3)), np.zeros((0, 3, 3)))
        seg_temps = [s.temp_c for _, s in static]
        fixed, undetermined = gauge_notes(fit_s)
        sigma = ThermalSigma(
            K0=K_sig,
            U00=U0_sig,
            thermal_model={"kind": "polynomial", "order": 0, "alpha": {}, "beta": {}, "gamma": {}},
            birge_ratio=float("nan"),
            dof=0,
            extra={"fixed_by_convention": fixed, "undetermined": undetermined},
            basis={
                "level": "standard uncertainty (1 sigma)",
                "coefficients": "the nonlinear fit's parameter covariance, scaled by its residuals "
                "(the norm errors |a| - 1 over the positions)",
                "n_positions": int(fit_s.n_positions),
                "model": fit_s.model,
            },
        )
        unit_fit = UnitFit(
            unit=serial,
            normal_temp_c=t0,
            per_plateau=[plateau],
            model=thermal,
            skipped=notes,
            valid_temp_c=(round(min(seg_temps), 1), round(max(seg_temps), 1)),
            uncertainty=sigma,
        )
        # as many distinct positions as parameters: |a| = 1 holds at every one of them by construction
        n_params = n_parameters(fit_s.model)
        exact = fit_s.n_distinct <= n_params
        return Fitted(
            unit_fit,
            passport_fields={"scalar": fit_s.summary()},
            exact=frozenset((run_id, int(s.t_start_ns)) for run_id, s in static) if exact else frozenset(),
            exact_why=f"{fit_s.n_distinct} distinct positions for the {n_params} parameters of the "
            f"{fit_s.model} scalar model",
        )


#: the scalar method, for the registry (:mod:`pipeline.calibrate.methods`)
CALIBRATION_METHOD = Scalar()
observe = CALIBRATION_METHOD.observe
calibrate_observed = CALIBRATION_METHOD.calibrate_observed
calibrate = CALIBRATION_METHOD.calibrate
