"""``thermal_lag``: the sensing element's temperature T_e lags the thermosensor (a thermal gradient; seed 003's rate
terms): tau dT_e/dt = T - T_e, and the constants are evaluated at T_e.

Shows during ramps and early in soaks, with the sign of dT/dt; gone on soaked plateaus. It has no linear fit term:
``diagnose`` evaluates the base model at the lagged temperature instead (``acts_on == "temperature"``). The lag
search runs from 0.02 s (far below what a 1 s micro-sample resolves: a lag there is no lag) to 4 h, so that a lag of
a fraction of a second is found inside the range, not at its edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.dynamics import first_order_lag
from pipeline.effects.base import Effect, Shown, SignalContext, log_grid
from pipeline.model import output_v


@dataclass(frozen=True)
class ThermalLag(Effect):
    """The sensing element's temperature T_e lags the thermosensor: tau dT_e/dt = T - T_e; the constants are
    evaluated at T_e."""

    id: ClassVar[str] = "thermal_lag"
    order: ClassVar[int] = 1
    acts_on: ClassVar[str] = "temperature"
    where: ClassVar[str] = "during ramps and early in soaks, sign set by dT/dt; gone on soaked plateaus"
    local: ClassVar[bool] = False
    nonlinear: ClassVar[str | None] = "tau_s"
    grid: ClassVar[tuple[float, ...]] = log_grid(0.02, 4 * 3600.0, 30)
    tau_s: float = 120.0

    def element_temperature_c(self, ctx: SignalContext) -> np.ndarray:
        """The lagged element temperature T_e (n,), C."""
        return first_order_lag(ctx.t_s, ctx.temp_c, self.tau_s)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        k_e, u0_e = ctx.constants.constants_at(self.element_temperature_c(ctx))
        return output_v(k_e, u0_e, ctx.a_g) - ctx.model_output_v()

    def validate(self) -> None:
        if self.tau_s < 0:
            raise ValueError(f"effect {self.id!r}: tau_s must not be negative, got {self.tau_s}")

    @classmethod
    def fit_parameters(cls, coef: np.ndarray, value: float | None, labels: list[str]) -> dict[str, Any]:
        if value is None:  # diagnose fits a nonlinear effect at a value of its grid
            raise ValueError(f"effect {cls.id!r}: fitted without a time constant")
        return {"tau_s": float(value)}

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        tau = p["tau_s"]
        size = f"{tau:.0f} s" if tau >= 10 else f"{tau:.2g} s"
        return (
            f"The sensing element lags the thermosensor by about {size} (a thermal gradient): during ramps and "
            f"early in soaks the {shown.axes} outputs depart from the passport by up to {shown.amount(shown.peak)}, "
            "with the sign of dT/dt, and agree again on soaked plateaus."
        )
