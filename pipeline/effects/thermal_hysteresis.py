"""``thermal_hysteresis``: the constants depend on the direction the temperature came from: U0 += s h, with s = +1
after a heating ramp, -1 after a cooling ramp, 0 before the first ramp (h: V per axis).

Shows where one temperature is revisited from above and from below, even soaked.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.effects.base import Effect, Shown, SignalContext, Vec3, too_big, vector_columns, vector_parameters


@dataclass(frozen=True)
class ThermalHysteresis(Effect):
    """U0 += s h, s = +1 after a heating ramp, -1 after a cooling ramp, 0 before the first ramp."""

    id: ClassVar[str] = "thermal_hysteresis"
    order: ClassVar[int] = 2
    where: ClassVar[str] = "one temperature revisited from above and from below disagrees by 2 h, even soaked"
    h_v: Vec3 = (50e-6, -40e-6, 30e-6)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        s = np.zeros(len(ctx.t_s)) if ctx.ramp_sign is None else np.asarray(ctx.ramp_sign, dtype=float)
        return s[:, None] * np.asarray(self.h_v)

    @classmethod
    def fit_columns(cls, ctx, value):
        return vector_columns(cls, "h_v", "h", ctx)

    @classmethod
    def fit_parameters(cls, coef, value, labels):
        return vector_parameters("h_v", coef)

    @classmethod
    def implausible(cls, p):
        return too_big(p, "h_v", 5e-3, "V")

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        return (
            f"The zero offsets depend on the direction the temperature came from: after heating they sit "
            f"2h = {shown.vector(2 * np.asarray(p['h_v']))} above their values after cooling, so the same "
            f"temperature revisited from above and from below disagrees{shown.temps}, even soaked."
        )
