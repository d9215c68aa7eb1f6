"""The 12 passport constants at one temperature from static positions (seed 000, eq. 1 and 11).

Inputs are per-position averages: ``a_g`` (m, 3) the known specific force in g, ``u_v`` (m, 3) the mean outputs in V.
Outputs: K (3, 3) in V/g and U0 (3,) in V.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.positions import TEST_POSITIONS


@dataclass(frozen=True)
class ConstantsFit:
    """Constants at one temperature and how well they fit the positions used."""

    K: np.ndarray  # (3, 3) V/g
    U0: np.ndarray  # (3,) V
    residual_v: np.ndarray  # (m, 3) U - (K a + U0) at the positions used, V
    positions: tuple[str, ...]
    method: str  # "six_position" | "least_squares"


def six_position(u_by_position_v: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Closed form of seed 000 eq. 11 from the mean outputs in TP1..TP6 (V).

    K_ix = (U_i6 - U_i5)/2, K_iy = (U_i4 - U_i2)/2, K_iz = (U_i1 - U_i3)/2 (V/g); U0_i = mean over the six positions
    (the paper's eq. 11 line for U0y is a misprint, see docs/physics.md).
    """
    missing = [p for p in TEST_POSITIONS if p not in u_by_position_v]
    if missing:
        raise ValueError(f"six-position form needs TP1..TP6; missing {', '.join(missing)}")
    U = {p: np.asarray(u_by_position_v[p], dtype=float) for p in TEST_POSITIONS}
    K = np.column_stack([(U["TP6"] - U["TP5"]) / 2.0, (U["TP4"] - U["TP2"]) / 2.0, (U["TP1"] - U["TP3"]) / 2.0])
    U0 = np.mean([U[p] for p in TEST_POSITIONS], axis=0)
    return K, U0


def least_squares(
    a_g: np.ndarray, u_v: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve U = K a + U0 for K (3, 3) V/g and U0 (3,) V over m >= 4 positions by (weighted) least squares.

    Each channel is an independent linear regression on [a_x, a_y, a_z, 1]. Returns K, U0 and the residuals (m, 3) V.
    Raises ValueError when the positions do not span three directions.
    """
    a_g = np.asarray(a_g, dtype=float)
    u_v = np.asarray(u_v, dtype=float)
    A = np.column_stack([a_g, np.ones(len(a_g))])
    if np.linalg.matrix_rank(A) < 4:
        raise ValueError(
            "positions do not determine the 12 constants (need gravity along three independent axes "
            "with both signs or an offset reference)"
        )
    w = np.ones(len(a_g)) if weights is None else np.asarray(weights, dtype=float)
    sw = np.sqrt(w)[:, None]
    coef, *_ = np.linalg.lstsq(A * sw, u_v * sw, rcond=None)  # (4, 3): rows a_x, a_y, a_z, 1; cols channel
    K = coef[:3].T
    U0 = coef[3]
    return K, U0, u_v - (a_g @ K.T + U0)


#: the methods ``fit_constants`` (and ``calibrate --constants-method``) takes
CONSTANTS_METHODS = ("auto", "six_position", "least_squares")


def fit_constants(
    positions: list[str], u_v: np.ndarray, *, method: str = "auto", weights: np.ndarray | None = None
) -> ConstantsFit:
    """Constants from named positions and their mean outputs.

    ``method``: ``"six_position"`` (needs TP1..TP6, each once; repeats are averaged), ``"least_squares"`` (all
    given positions), or ``"auto"``: least squares when more than six positions are given, else the closed form.
    """
    from pipeline.positions import gravity_vector_g

    u_v = np.asarray(u_v, dtype=float)
    a_g = np.array([gravity_vector_g(p) for p in positions])
    if method == "auto":
        method = "least_squares" if len(positions) > 6 else "six_position"
    if method == "six_position":
        by_pos: dict[str, list[np.ndarray]] = {}
        for p, u in zip(positions, u_v):
            by_pos.setdefault(p, []).append(u)
        K, U0 = six_position({p: np.mean(v, axis=0) for p, v in by_pos.items()})
        resid = u_v - (a_g @ K.T + U0)
    elif method == "least_squares":
        K, U0, resid = least_squares(a_g, u_v, weights)
    else:
        raise ValueError(f"unknown constants method {method!r}")
    return ConstantsFit(K=K, U0=U0, residual_v=resid, positions=tuple(positions), method=method)
