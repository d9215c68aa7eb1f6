"""Temperature models of the 12 constants (seed 000, eq. 4-5, 12-13).

Relative forms in dT = T - T0 (docs/physics.md):

    U0_i(T)  = U0_i + sum_n alpha_ni dT^n                 alpha in V/C^n
    K_ii(T)  = K_ii (1 + sum_n beta_nii dT^n)             beta  in 1/C^n
    K_ij(T)  = K_ij (1 + sum_n gamma_nij dT^n)            gamma in 1/C^n

or piecewise linear with breakpoints at the calibration temperatures. Both models are
:class:`pipeline.model.ConstantsModel`: ``constants_at(temp_c)`` gives K (n, 3, 3) V/g and U0 (n, 3) V.
Internally a relative coefficient array ``rel`` of shape (..., 3, 3) holds beta on the diagonal and gamma off it.

Seed 003's differential method adds terms in the temperature rate r (C/min) and a lag of the sensing element behind
the thermosensor (s): :class:`RateTerms`, and :class:`DifferentialModel` (a polynomial model plus rate terms, whose
``constants_at(temp_c, rate_c_per_min)`` gives K and U0 at a temperature and rate). ``pipeline.calibrate.differential``
fits them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.positions import AXES

OFF_DIAGONAL = [(i, j) for i in range(3) for j in range(3) if i != j]
DIAG_KEYS = [AXES[i] * 2 for i in range(3)]  # "xx", "yy", "zz"
OFF_KEYS = [AXES[i] + AXES[j] for i, j in OFF_DIAGONAL]  # "xy", "xz", "yx", "yz", "zx", "zy"


def cluster_temperatures(temps_c: np.ndarray, tol_c: float = 3.0) -> np.ndarray:
    """Group temperatures (C) that lie within ``tol_c`` of their neighbour; returns a label per input (0..k-1, by
    increasing temperature)."""
    temps_c = np.asarray(temps_c, dtype=float)
    order = np.argsort(temps_c)
    labels = np.empty(len(temps_c), dtype=int)
    if len(temps_c) == 0:
        return labels
    breaks = np.concatenate([[0], np.cumsum(np.diff(temps_c[order]) > tol_c)])
    labels[order] = breaks
    return labels


def _rel_to_dict(rel: np.ndarray, alpha: np.ndarray) -> tuple[dict, dict, dict]:
    """Split (..., 3, 3) relative and (..., 3) alpha arrays into the passport's keyed dicts (last axis = order)."""
    a = {AXES[i]: alpha[..., i].tolist() for i in range(3)}
    b = {DIAG_KEYS[i]: rel[..., i, i].tolist() for i in range(3)}
    g = {OFF_KEYS[k]: rel[..., i, j].tolist() for k, (i, j) in enumerate(OFF_DIAGONAL)}
    return a, b, g


def _rel_from_dict(alpha: dict, beta: dict, gamma: dict) -> tuple[np.ndarray, np.ndarray]:
    a = np.stack([np.asarray(alpha[ax], dtype=float) for ax in AXES], axis=-1)
    shape = a.shape[:-1]
    rel = np.zeros(shape + (3, 3))
    for i in range(3):
        rel[..., i, i] = np.asarray(beta[DIAG_KEYS[i]], dtype=float)
    for k, (i, j) in enumerate(OFF_DIAGONAL):
        rel[..., i, j] = np.asarray(gamma[OFF_KEYS[k]], dtype=float)
    return rel, a


@dataclass
class PolynomialModel:
    """Polynomial temperature model of order ``order`` (0 = no temperature dependence).

    ``alpha`` (order, 3) V/C^n; ``rel`` (order, 3, 3): beta (1/C^n) on the diagonal, gamma (1/C^n) off it.
    """

    K0: np.ndarray
    U00: np.ndarray
    normal_temp_c: float
    order: int
    alpha: np.ndarray
    rel: np.ndarray

    def deltas(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """dK (n, 3, 3) V/g and dU0 (n, 3) V: the change of the constants from T0 to ``temp_c``."""
        dT = np.atleast_1d(np.asarray(temp_c, dtype=float)) - self.normal_temp_c
        powers = dT[:, None] ** np.arange(1, self.order + 1)[None, :]  # (n, order)
        dU0 = powers @ self.alpha if self.order else np.zeros((len(dT), 3))
        rel = np.einsum("nk,kij->nij", powers, self.rel) if self.order else np.zeros((len(dT), 3, 3))
        return rel * self.K0, dU0

    def constants_at(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dK, dU0 = self.deltas(temp_c)
        return self.K0 + dK, self.U00 + dU0

    def to_dict(self) -> dict:
        """Contract form: one list per constant, index n-1 holding the coefficient of dT^n."""
        a, b, g = _rel_to_dict(self.rel, self.alpha)
        return {"kind": "polynomial", "order": int(self.order), "alpha": a, "beta": b, "gamma": g}

    @classmethod
    def from_dict(cls, d: dict, K0: np.ndarray, U00: np.ndarray, normal_temp_c: float) -> PolynomialModel:
        order = int(d["order"])
        if order == 0:
            rel, alpha = np.zeros((0, 3, 3)), np.zeros((0, 3))
        else:
            rel, alpha = _rel_from_dict(d["alpha"], d["beta"], d["gamma"])
        return cls(np.asarray(K0, float), np.asarray(U00, float), float(normal_temp_c), order, alpha, rel)


@dataclass
class PiecewiseModel:
    """Piecewise-linear temperature model: the constants at ``nodes_c`` (m,), linear between them and extrapolated
    with the end slopes. T0 is always one of the nodes."""

    normal_temp_c: float
    nodes_c: np.ndarray  # (m,) C, increasing
    K_nodes: np.ndarray  # (m, 3, 3) V/g
    U0_nodes: np.ndarray  # (m, 3) V

    @property
    def _i0(self) -> int:
        return int(np.argmin(np.abs(self.nodes_c - self.normal_temp_c)))

    @property
    def K0(self) -> np.ndarray:
        return self.K_nodes[self._i0]

    @property
    def U00(self) -> np.ndarray:
        return self.U0_nodes[self._i0]

    def constants_at(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = np.atleast_1d(np.asarray(temp_c, dtype=float))
        x = self.nodes_c
        if len(x) == 1:
            return (
                np.broadcast_to(self.K_nodes[0], (len(T), 3, 3)).copy(),
                np.broadcast_to(self.U0_nodes[0], (len(T), 3)).copy(),
            )
        seg = np.clip(np.searchsorted(x, T) - 1, 0, len(x) - 2)
        w = (T - x[seg]) / (x[seg + 1] - x[seg])
        K = self.K_nodes[seg] + w[:, None, None] * (self.K_nodes[seg + 1] - self.K_nodes[seg])
        U0 = self.U0_nodes[seg] + w[:, None] * (self.U0_nodes[seg + 1] - self.U0_nodes[seg])
        return K, U0

    def deltas(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        K, U0 = self.constants_at(temp_c)
        return K - self.K0, U0 - self.U00

    def segments(self) -> list[dict]:
        """Per sub-band coefficients in seed 000's relative form: alpha V/C, beta and gamma 1/C (relative to the
        constants at T0), each the slope between the sub-band's two end temperatures."""
        out = []
        K0 = self.K0
        with np.errstate(divide="ignore", invalid="ignore"):
            for lo in range(len(self.nodes_c) - 1):
                t_lo, t_hi = self.nodes_c[lo], self.nodes_c[lo + 1]
                span = t_hi - t_lo
                alpha = (self.U0_nodes[lo + 1] - self.U0_nodes[lo]) / span
                rel = np.where(K0 != 0, (self.K_nodes[lo + 1] - self.K_nodes[lo]) / (K0 * span), 0.0)
                a, b, g = _rel_to_dict(rel, alpha)
                out.append({"t_lo_c": float(t_lo), "t_hi_c": float(t_hi), "alpha": a, "beta": b, "gamma": g})
        return out

    def to_dict(self) -> dict:
        return {
            "kind": "piecewise_linear",
            "breakpoints_c": [float(t) for t in self.nodes_c],
            "segments": self.segments(),
        }

    @classmethod
    def from_dict(cls, d: dict, K0: np.ndarray, U00: np.ndarray, normal_temp_c: float) -> PiecewiseModel:
        nodes = np.asarray(d["breakpoints_c"], dtype=float)
        K0 = np.asarray(K0, dtype=float)
        m = len(nodes)
        K_nodes = np.zeros((m, 3, 3))
        U0_nodes = np.zeros((m, 3))
        i0 = int(np.argmin(np.abs(nodes - normal_temp_c)))
        K_nodes[i0], U0_nodes[i0] = K0, U00
        segs = d["segments"]
        for lo in range(i0, m - 1):  # upward from T0
            rel, alpha = _rel_from_dict(segs[lo]["alpha"], segs[lo]["beta"], segs[lo]["gamma"])
            span = nodes[lo + 1] - nodes[lo]
            K_nodes[lo + 1] = K_nodes[lo] + rel * K0 * span
            U0_nodes[lo + 1] = U0_nodes[lo] + alpha * span
        for lo in range(i0 - 1, -1, -1):  # downward from T0
            rel, alpha = _rel_from_dict(segs[lo]["alpha"], segs[lo]["beta"], segs[lo]["gamma"])
            span = nodes[lo + 1] - nodes[lo]
            K_nodes[lo] = K_nodes[lo + 1] - rel * K0 * span
            U0_nodes[lo] = U0_nodes[lo + 1] - alpha * span
        return cls(float(normal_temp_c), nodes, K_nodes, U0_nodes)


ThermalModel = PolynomialModel | PiecewiseModel


def fit_polynomial(
    temps_c: np.ndarray, K: np.ndarray, U0: np.ndarray, order: int, normal_temp_c: float = 20.0
) -> PolynomialModel:
    """Least-squares polynomial of ``order`` in dT through per-plateau constants (exact, as seed 000's Cramer's-rule
    solution, when there are order+1 distinct temperatures). ``K`` (p, 3, 3) V/g, ``U0`` (p, 3) V at ``temps_c``."""
    temps_c = np.asarray(temps_c, dtype=float)
    dT = temps_c - normal_temp_c
    A = dT[:, None] ** np.arange(order + 1)[None, :]  # (p, order+1)
    if np.linalg.matrix_rank(A) < order + 1:
        raise ValueError(f"a polynomial of order {order} needs {order + 1} distinct temperatures")
    Y = np.concatenate([K.reshape(len(K), 9), U0], axis=1)  # (p, 12)
    coef, *_ = np.linalg.lstsq(A, Y, rcond=None)  # (order+1, 12)
    K0 = coef[0, :9].reshape(3, 3)
    U00 = coef[0, 9:]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(K0 != 0, coef[1:, :9].reshape(order, 3, 3) / K0, 0.0)
    return PolynomialModel(K0, U00, float(normal_temp_c), int(order), coef[1:, 9:], rel)


def fit_piecewise(
    temps_c: np.ndarray, K: np.ndarray, U0: np.ndarray, normal_temp_c: float = 20.0, cluster_tol_c: float = 3.0
) -> PiecewiseModel:
    """Piecewise-linear model with breakpoints at the calibration temperatures (seed 000, eq. 5 and 13).

    Plateaus within ``cluster_tol_c`` of each other are one calibration temperature (their constants and
    temperatures averaged). The constants at T0 are interpolated between the neighbouring calibration temperatures
    and T0 replaces a calibration temperature that lies within ``cluster_tol_c`` of it.
    """
    temps_c = np.asarray(temps_c, dtype=float)
    labels = cluster_temperatures(temps_c, cluster_tol_c)
    k = labels.max() + 1
    nodes = np.array([temps_c[labels == c].mean() for c in range(k)])
    K_nodes = np.array([K[labels == c].mean(axis=0) for c in range(k)])
    U0_nodes = np.array([U0[labels == c].mean(axis=0) for c in range(k)])
    model = PiecewiseModel(float(normal_temp_c), nodes, K_nodes, U0_nodes)
    K_T0, U0_T0 = (a[0] for a in model.constants_at(np.array([normal_temp_c])))
    near = np.abs(nodes - normal_temp_c) <= cluster_tol_c
    keep = ~near
    nodes = np.concatenate([nodes[keep], [normal_temp_c]])
    K_nodes = np.concatenate([K_nodes[keep], K_T0[None]])
    U0_nodes = np.concatenate([U0_nodes[keep], U0_T0[None]])
    order = np.argsort(nodes)
    return PiecewiseModel(float(normal_temp_c), nodes[order], K_nodes[order], U0_nodes[order])


def default_order(temps_c: np.ndarray, cluster_tol_c: float = 3.0) -> int:
    """Default polynomial order: number of distinct calibration temperatures - 1, at most 3."""
    n = int(cluster_temperatures(np.asarray(temps_c, float), cluster_tol_c).max() + 1) if len(temps_c) else 0
    return max(0, min(3, n - 1))


#: the thermal models ``fit_thermal_model`` (and ``calibrate --thermal-model``) takes; ``auto``: the default order
THERMAL_MODELS = ("auto", "poly1", "poly2", "poly3", "piecewise")


def fit_thermal_model(
    temps_c: np.ndarray,
    K: np.ndarray,
    U0: np.ndarray,
    kind: str = "auto",
    normal_temp_c: float = 20.0,
    cluster_tol_c: float = 3.0,
) -> ThermalModel:
    """Fit the model named ``kind``: ``poly1`` | ``poly2`` | ``poly3`` | ``piecewise`` | ``auto`` (the default
    polynomial order)."""
    if kind == "piecewise":
        return fit_piecewise(temps_c, K, U0, normal_temp_c, cluster_tol_c)
    if kind == "auto":
        order = default_order(temps_c, cluster_tol_c)
    elif kind in ("poly0", "poly1", "poly2", "poly3"):
        order = int(kind[-1])
    else:
        raise ValueError(f"unknown thermal model {kind!r} ({', '.join(THERMAL_MODELS[1:])})")
    return fit_polynomial(temps_c, K, U0, order, normal_temp_c)


def thermal_model_from_dict(d: dict, K0: np.ndarray, U00: np.ndarray, normal_temp_c: float) -> ThermalModel:
    kind = d.get("kind")
    if kind == "polynomial":
        return PolynomialModel.from_dict(d, K0, U00, normal_temp_c)
    if kind == "piecewise_linear":
        return PiecewiseModel.from_dict(d, K0, U00, normal_temp_c)
    raise ValueError(f"unknown thermal model kind {kind!r}")


#: unit of the temperature rate r in the rate terms
RATE_UNIT = "C/min"


# ---------------------------------------------------------------------------------------------------------------
# Temperature-rate terms and lag (seed 003's differential method; pipeline.calibrate.differential fits them)


@dataclass
class RateTerms:
    """Temperature-rate terms and lag: ``alpha_rate`` (n, k+1, 3) in V/(C/min)^n/C^k for the bias and
    ``beta_rate`` (n, k+1, 3) in 1/(C/min)^n/C^k for the relative scale factors, index [n-1, k, axis] multiplying
    r^n dT^k; ``lag_tau_s`` the element lag (0: none). The rate r is the thermosensor's, smoothed over
    ``temp_smooth_s``. ``cross_abs`` (m, 3, 3), V/g/C^m: cross-axis temperature terms dK_ij = sum_m cross_abs[m-1,
    i, j] dT^m where the cross-axis constant K_ij itself is not known (a sweep calibrated without a base passport:
    the polynomial model's gamma is relative to K_ij); None: none."""

    alpha_rate: np.ndarray
    beta_rate: np.ndarray
    temp_smooth_s: float
    lag_tau_s: float = 0.0
    cross_abs: np.ndarray | None = None

    @property
    def order(self) -> int:
        return self.alpha_rate.shape[0]

    @property
    def dt_order(self) -> int:
        return self.alpha_rate.shape[1] - 1

    def to_dict(self) -> dict:
        d: dict[str, Any] = {
            "order": self.order,
            "dt_order": self.dt_order,
            "rate_unit": RATE_UNIT,
            "temp_smooth_s": float(self.temp_smooth_s),
            "lag_tau_s": float(self.lag_tau_s),
            "units": {"alpha_rate": "V/(C/min)^n/C^k", "beta_rate": "1/(C/min)^n/C^k"},
            "index": "[n-1][k] multiplies r^n dT^k",
            "alpha_rate": {AXES[i]: self.alpha_rate[..., i].tolist() for i in range(3)},
            "beta_rate": {AXES[i] * 2: self.beta_rate[..., i].tolist() for i in range(3)},
        }
        if self.cross_abs is not None:
            d["units"]["cross_axis_abs"] = "V/g/C^m, [m-1] multiplies dT^m"
            d["cross_axis_abs"] = {
                OFF_KEYS[k]: self.cross_abs[:, i, j].tolist() for k, (i, j) in enumerate(OFF_DIAGONAL)
            }
        return d

    @classmethod
    def from_dict(cls, d: dict) -> RateTerms:
        shape = (int(d["order"]), int(d["dt_order"]) + 1)
        a = np.stack([np.asarray(d["alpha_rate"][ax], dtype=float).reshape(shape) for ax in AXES], axis=-1)
        b = np.stack([np.asarray(d["beta_rate"][ax * 2], dtype=float).reshape(shape) for ax in AXES], axis=-1)
        cross = None
        if d.get("cross_axis_abs"):
            m = len(next(iter(d["cross_axis_abs"].values())))
            cross = np.zeros((m, 3, 3))
            for k, (i, j) in enumerate(OFF_DIAGONAL):
                cross[:, i, j] = np.asarray(d["cross_axis_abs"].get(OFF_KEYS[k], [0.0] * m), dtype=float)
        return cls(a, b, float(d["temp_smooth_s"]), float(d.get("lag_tau_s", 0.0)), cross)


def rate_basis(dt_c, rate, order: int, dt_order: int) -> np.ndarray:
    """r^n dT^k, shape (m, order, dt_order + 1)."""
    dt_c = np.asarray(dt_c, dtype=float)
    rate = np.asarray(rate, dtype=float)
    n = np.arange(1, order + 1)
    k = np.arange(dt_order + 1)
    return rate[:, None, None] ** n[None, :, None] * dt_c[:, None, None] ** k[None, None, :]


@dataclass
class DifferentialModel:
    """Constants K(T, r) and U0(T, r): the thermal model ``static`` (polynomial from the differential fit) plus the
    ``rate`` terms (None: without). With a lag, T is the element temperature
    (:meth:`pipeline.dynamics.Thermosensor.at` with ``lag_tau_s``)."""

    static: ThermalModel
    rate: RateTerms | None = None

    @property
    def K0(self) -> np.ndarray:
        return self.static.K0

    @property
    def U00(self) -> np.ndarray:
        return self.static.U00

    @property
    def normal_temp_c(self) -> float:
        return self.static.normal_temp_c

    @property
    def lag_tau_s(self) -> float:
        return self.rate.lag_tau_s if self.rate is not None else 0.0

    def constants_at(
        self, temp_c: np.ndarray, rate_c_per_min: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """K (m, 3, 3) V/g and U0 (m, 3) V at temperatures ``temp_c`` (m,) C and rates (m,) C/min."""
        K, U0 = self.static.constants_at(temp_c)
        if self.rate is not None and self.rate.cross_abs is not None:
            dT = np.atleast_1d(np.asarray(temp_c, dtype=float)) - self.normal_temp_c
            powers = dT[:, None] ** np.arange(1, self.rate.cross_abs.shape[0] + 1)[None, :]
            K = K + np.einsum("nm,mij->nij", powers, self.rate.cross_abs)
        if self.rate is None or rate_c_per_min is None or self.rate.order == 0:
            return K, U0
        g = rate_basis(
            np.atleast_1d(temp_c) - self.normal_temp_c,
            np.atleast_1d(rate_c_per_min),
            self.rate.order,
            self.rate.dt_order,
        )
        U0 = U0 + np.einsum("mnk,nki->mi", g, self.rate.alpha_rate)
        K = K.copy()
        K[:, np.arange(3), np.arange(3)] += np.einsum("mnk,nki->mi", g, self.rate.beta_rate) * np.diag(self.K0)
        return K, U0


# ---------------------------------------------------------------------------------------------------------------
# A thermal model as a polynomial, and polynomial corrections (diagnose refits a passport's model with them)


def polynomial_reference(model, order: int | None = None) -> PolynomialModel:
    """A passport's thermal model as a :class:`PolynomialModel`: itself when polynomial; a piecewise-linear model
    becomes the polynomial through (or fitted to) its breakpoints, of ``order`` (default: breakpoints - 1, at most
    3)."""
    if isinstance(model, PolynomialModel):
        return model
    if isinstance(model, PiecewiseModel):
        nodes = np.asarray(model.nodes_c, float)
        k = min(3, len(nodes) - 1) if order is None else order
        return fit_polynomial(nodes, model.K_nodes, model.U0_nodes, k, model.normal_temp_c)
    raise TypeError(f"unsupported thermal model {type(model).__name__}")


def raise_order(model: PolynomialModel, order: int) -> PolynomialModel:
    """The same polynomial model written with ``order`` powers (the higher ones zero)."""
    extra = order - model.order
    if extra <= 0:
        return model
    return PolynomialModel(
        model.K0,
        model.U00,
        model.normal_temp_c,
        order,
        np.concatenate([np.asarray(model.alpha).reshape(-1, 3), np.zeros((extra, 3))]),
        np.concatenate([np.asarray(model.rel).reshape(-1, 3, 3), np.zeros((extra, 3, 3))]),
    )


def add_polynomial_correction(reference: PolynomialModel, correction: np.ndarray) -> PolynomialModel:
    """``reference`` plus a correction (3, order+1, 4) in absolute form (per channel i and power n: the change of
    K_n[i, j] in V/g/C^n for j = x, y, z, then of U0_n[i] in V/C^n)."""
    k = reference.order + 1
    k_abs = np.empty((k, 3, 3))
    u_abs = np.empty((k, 3))
    k_abs[0], u_abs[0] = reference.K0, reference.U00
    if reference.order:
        k_abs[1:] = reference.rel * reference.K0
        u_abs[1:] = reference.alpha
    k_abs += np.transpose(correction[:, :, :3], (1, 0, 2))
    u_abs += correction[:, :, 3].T
    k0 = k_abs[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(k0 != 0, k_abs[1:] / k0, 0.0)
    return PolynomialModel(k0, u_abs[0], reference.normal_temp_c, reference.order, u_abs[1:], rel)
