"""``scale_nonlinearity``: second-order scale factor (IEEE 1293 K2; seed 004's D2), U_i += k2_i a_i^2 (V/g^2).

Shows in the pair sums of a channel's own vertical positions (TP5+TP6 for x) against its horizontal pairs, and in
the VP errors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.effects.base import Effect, Shown, SignalContext, Vec3, too_big, vector_columns, vector_parameters


@dataclass(frozen=True)
class ScaleNonlinearity(Effect):
    """Second-order scale factor (IEEE 1293 K2): U_i += k2_i a_i^2."""

    id: ClassVar[str] = "scale_nonlinearity"
    order: ClassVar[int] = 6
    where: ClassVar[str] = "a channel's own vertical positions (TP5+TP6 for x) differ from its horizontal pairs"
    k2_v_per_g2: Vec3 = (30e-6, -20e-6, 25e-6)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        return np.asarray(ctx.a_g) ** 2 * np.asarray(self.k2_v_per_g2)

    @classmethod
    def fit_columns(cls, ctx, value):
        return vector_columns(cls, "k2_v_per_g2", "k2", ctx)

    @classmethod
    def fit_parameters(cls, coef, value, labels):
        return vector_parameters("k2_v_per_g2", coef)

    @classmethod
    def implausible(cls, p):
        return too_big(p, "k2_v_per_g2", 5e-3, "V/g^2")

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        return (
            f"The scale factors have a second-order part K2 = {shown.vector(p['k2_v_per_g2'], '/g^2')}: a "
            f"channel reads that much more when its own axis is vertical than the linear model says (up to "
            f"{shown.amount(shown.peak)} in single positions), which also biases the VP gravity module."
        )
