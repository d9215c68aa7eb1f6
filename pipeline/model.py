"""The metrological model of seed 000 (eq. 1-2): U = K a + U0 and a_hat = K^-1 (U - U0).

K is 3x3 in V/g (diagonal: gains, off-diagonal: cross-axis sensitivities), U0 the zero-g offsets in V, a the
specific force along the AU axes in g. Functions take stacks: K of shape (n, 3, 3) or (3, 3), U0 and a of shape
(n, 3) or (3,).

The outputs may be in any linear unit (docs/physics.md, "Real recordings"): volts as docs/log-format.md says, or m/s^2
from a logger that records acceleration; K is then in that unit per g and U0 in that unit (:func:`output_unit`).
"""

from __future__ import annotations

import math
import re
from typing import Protocol

import numpy as np

#: the units an output U may be in, each with the smaller unit residuals and noise are printed in and its factor
OUTPUT_UNITS = {"V": ("uV", 1e6), "m/s^2": ("mm/s^2", 1e3)}
#: gains within this fraction of the local gravity (in m/s^2) mean outputs in m/s^2
_MPS2_GAIN_TOLERANCE = 0.1


def output_unit(gains, g_local_mps2: float = 9.80665) -> str:
    """The unit of outputs whose gains |K_ii| (output unit per g) are ``gains`` (3,): ``"m/s^2"`` when every gain
    lies within 10 % of the local gravity ``g_local_mps2`` (an axis pointing up reads about +9.8: a logger that
    records acceleration; no voltage output has such gains, docs/physics.md's plausible range being 0.05..5 V/g),
    else ``"V"`` (docs/log-format.md's unit)."""
    g = np.abs(np.asarray(gains, dtype=float))
    if g.size and np.all(np.abs(g / float(g_local_mps2) - 1.0) <= _MPS2_GAIN_TOLERANCE):
        return "m/s^2"
    return "V"


def small_unit(unit: str) -> tuple[str, float]:
    """The small unit amounts in the output unit ``unit`` (``OUTPUT_UNITS``: V, m/s^2; another: V) are printed in
    (uV, mm/s^2), and its factor."""
    return OUTPUT_UNITS.get(unit, OUTPUT_UNITS["V"])


def small_name(unit: str) -> str:
    """The name of :func:`small_unit`: uV, mm/s^2."""
    return small_unit(unit)[0]


def small_number(x: float, spec: str = ".1f", *, unit: str) -> str:
    """``x`` (in the output unit ``unit``: V or m/s^2) as a number of its small unit (:func:`small_name`)
    formatted by ``spec``. A fixed-point ``spec`` written for micro-volts keeps at least three significant digits
    in a larger small unit (mm/s^2 is a thousand micro-(m/s^2))."""
    _, scale = small_unit(unit)
    v = float(x) * scale
    m = re.fullmatch(r"([+ ]?)\.(\d+)f", spec)
    if m and scale != OUTPUT_UNITS["V"][1] and math.isfinite(v) and v != 0.0:
        d = int(m.group(2))
        d = max(d, min(d + 3, 2 - math.floor(math.log10(abs(v)))))
        spec = f"{m.group(1)}.{d}f"
    return f"{v:{spec}}"


def small(x: float, spec: str = ".1f", per: str = "", *, unit: str) -> str:
    """``x`` (in the output unit ``unit``) with its small unit: ``12.3 uV``, ``712 mm/s^2``; ``per``: e.g. ``/h``,
    ``/g``."""
    return f"{small_number(x, spec, unit=unit)} {small_name(unit)}{per}"


class ConstantsModel(Protocol):
    """Anything that gives the 12 constants at a temperature: the simulator's truth, a passport's thermal model."""

    def constants_at(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """K (n, 3, 3) in V/g and U0 (n, 3) in V at temperatures ``temp_c`` (n,) in C."""
        ...


def output_v(K: np.ndarray, U0: np.ndarray, a_g: np.ndarray) -> np.ndarray:
    """Output voltages U = K a + U0 (V) for specific force ``a_g`` (g). Broadcasts over a leading axis."""
    return np.einsum("...ij,...j->...i", K, a_g) + U0


def vector3(v) -> tuple[float, float, float]:
    """A 3-vector (array or sequence) as a tuple of three Python floats, as dataclasses and JSON keep it."""
    return (float(v[0]), float(v[1]), float(v[2]))


def specific_force_g(K: np.ndarray, U0: np.ndarray, u_v: np.ndarray) -> np.ndarray:
    """Estimated specific force a_hat = K^-1 (U - U0) in g from outputs ``u_v`` (V)."""
    K = np.asarray(K, dtype=float)
    rhs = np.asarray(u_v, dtype=float) - U0
    if K.ndim == 2:
        return np.linalg.solve(K, rhs.T).T
    return np.linalg.solve(K, rhs[..., None])[..., 0]


def gravity_module_error_g(a_hat_g: np.ndarray) -> np.ndarray:
    """Gravity-module error dg = |a_hat| - 1 in g (seed 000, eq. 14)."""
    return np.linalg.norm(a_hat_g, axis=-1) - 1.0


class FixedConstants:
    """Constants that do not depend on temperature (a :class:`ConstantsModel`)."""

    def __init__(self, K: np.ndarray, U0: np.ndarray):
        self.K = np.asarray(K, dtype=float)
        self.U0 = np.asarray(U0, dtype=float)

    def constants_at(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = np.size(temp_c)
        return np.broadcast_to(self.K, (n, 3, 3)).copy(), np.broadcast_to(self.U0, (n, 3)).copy()
