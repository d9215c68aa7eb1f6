"""Compensation of temperature errors (seed 000), two methods.

Method 1: correct the passport constants to the current temperature and invert the model:
    a = K(T)^-1 (U - U0(T)).
Method 2: compute a_hat0 with the normal-temperature constants and add the first-order change of the estimate
caused by the constants' temperature change (seed 000 eq. 3 with eq. 4/5, i.e. eq. 6/7):

    da_i = - sum_j dK_ij (U_j - U0_j) / (K_ii K_jj) - dU0_i / K_ii + sum_{j != i} K_ij dU0_j / (K_ii K_jj)

The paper writes this as the temperature error Delta a_T that is removed from a_hat0; a_hat0 + da is the same
correction with the sign folded in. The simplified form (eq. 8/9) keeps only the j = i terms (drops the CAS terms,
two orders smaller). All inputs: U (n, 3) V, temperatures (n,) C; outputs in g.
"""

from __future__ import annotations

import numpy as np

from pipeline.model import specific_force_g


def method1(model, u_v: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
    """Specific force (n, 3) in g with the constants corrected to ``temp_c`` (method 1)."""
    K, U0 = model.constants_at(np.atleast_1d(temp_c))
    return specific_force_g(K, U0, np.atleast_2d(u_v))


def temperature_correction_g(model, u_v: np.ndarray, temp_c: np.ndarray, *, full: bool = True) -> np.ndarray:
    """The first-order change da (n, 3) in g of the estimate between T0 and ``temp_c`` (seed 000 eq. 6/7, or 8/9
    with ``full=False``). ``model`` has K0, U00 and deltas(temp_c) -> (dK, dU0)."""
    u_v = np.atleast_2d(u_v)
    dK, dU0 = model.deltas(np.atleast_1d(temp_c))
    K0, U00 = model.K0, model.U00
    d = np.diag(K0)  # (3,) gains, V/g
    x = u_v - U00  # (n, 3) V
    dd = np.outer(d, d)  # K_ii K_jj
    if full:
        term_k = -np.einsum("nij,nj->ni", dK / dd, x)
        cas = K0 / dd
        np.fill_diagonal(cas, 0.0)
        term_u = -dU0 / d + dU0 @ cas.T
    else:
        dK_diag = np.diagonal(dK, axis1=1, axis2=2)  # (n, 3)
        term_k = -dK_diag * x / d**2
        term_u = -dU0 / d
    return term_k + term_u


def method2(model, u_v: np.ndarray, temp_c: np.ndarray, *, full: bool = True) -> np.ndarray:
    """Specific force (n, 3) in g: normal-temperature constants plus the temperature correction (method 2)."""
    a0 = specific_force_g(model.K0, model.U00, np.atleast_2d(u_v))
    return a0 + temperature_correction_g(model, u_v, temp_c, full=full)


def uncompensated(model, u_v: np.ndarray) -> np.ndarray:
    """Specific force (n, 3) in g with the normal-temperature constants only."""
    return specific_force_g(model.K0, model.U00, np.atleast_2d(u_v))
