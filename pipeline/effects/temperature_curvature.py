"""``temperature_curvature``: the true temperature dependence has a cubic part, U0_i += c_i dT^3 and
Kii *= (1 + c_rel_i dT^3).

Shows between calibration temperatures (ramps, the VP plateaus at -10 and +45 C). A base thermal polynomial of
order 3 contains it; its own term is mostly absorbed by the base model at the calibration points, so a diagnosis
shows it by refitting without it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.effects.base import Effect, Shown, SignalContext, Vec3, axis_columns, too_big
from pipeline.positions import AXES

#: a cubic term beyond this at 50 C from T0 (V, or relative scale) is not a small left-out term
_LIMIT_AT_50C = 5e-3


@dataclass(frozen=True)
class TemperatureCurvature(Effect):
    """A cubic part of the temperature dependence: U0_i += c_i dT^3 and Kii *= (1 + c_rel_i dT^3)."""

    id: ClassVar[str] = "temperature_curvature"
    order: ClassVar[int] = 5
    where: ClassVar[str] = "between calibration temperatures (ramps, VP plateaus at -10 and +45 C)"
    shown_by_refit: ClassVar[bool] = True
    in_base_from_order: ClassVar[int | None] = 3
    c_v_per_c3: Vec3 = (1.5e-9, -1.0e-9, 1.0e-9)
    c_rel_per_c3: Vec3 = (1.0e-9, 1.5e-9, -1.0e-9)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        k, _ = ctx.k_u0
        kii = np.diagonal(k, axis1=1, axis2=2)
        dt3 = (ctx.dt_c**3)[:, None]
        return dt3 * (np.asarray(self.c_v_per_c3) + kii * np.asarray(self.c_rel_per_c3) * ctx.a_g)

    @classmethod
    def fit_columns(cls, ctx, value):
        cols = axis_columns(cls, "c_v_per_c3", ctx, c_rel_per_c3=0.0) + axis_columns(
            cls, "c_rel_per_c3", ctx, c_v_per_c3=0.0
        )
        return [f"c_{a}" for a in AXES] + [f"crel_{a}" for a in AXES], cols

    @classmethod
    def fit_parameters(cls, coef, value, labels):
        return {"c_v_per_c3": [float(c) for c in coef[:3]], "c_rel_per_c3": [float(c) for c in coef[3:6]]}

    @classmethod
    def implausible(cls, p):
        return too_big(p, "c_v_per_c3", _LIMIT_AT_50C / 50**3, "V/C^3") or too_big(
            p, "c_rel_per_c3", _LIMIT_AT_50C / 50**3, "1/C^3"
        )

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        c50 = np.asarray(p["c_v_per_c3"]) * 50.0**3
        r50 = np.asarray(p["c_rel_per_c3"]) * 50.0**3 * 1e6
        return (
            f"The temperature dependence has a cubic part the passport's polynomial lacks (at 50 C from T0: "
            f"offsets {shown.vector(c50)}, gains {', '.join(f'{a} {x:+.0f}' for a, x in zip(AXES, r50))} ppm): up "
            f"to {shown.amount(shown.peak)} on {shown.axes}{shown.temps}, where a polynomial through the "
            "calibration temperatures cannot follow it."
        )
