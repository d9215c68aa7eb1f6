"""``warmup_transient``: bias settling after power-on (the recording start), U0 += A exp(-(t - t_start)/tau_w).

Shows in the early part of the first plateau. The time-constant search runs from 10 s to 24 h: a settling
over a large part of the run is found inside the range (beyond it, it is a drift).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.effects.base import (
    Effect,
    Shown,
    SignalContext,
    Vec3,
    log_grid,
    too_big,
    vector_columns,
    vector_parameters,
)


@dataclass(frozen=True)
class WarmupTransient(Effect):
    """Bias settling after power-on (the recording start): U0 += A exp(-(t - t_start)/tau)."""

    id: ClassVar[str] = "warmup_transient"
    order: ClassVar[int] = 4
    where: ClassVar[str] = "early part of the first plateau only"
    nonlinear: ClassVar[str | None] = "tau_s"
    grid: ClassVar[tuple[float, ...]] = log_grid(10.0, 24 * 3600.0, 26)
    a_v: Vec3 = (300e-6, -200e-6, 150e-6)
    tau_s: float = 900.0

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        return np.exp(-np.asarray(ctx.t_s, dtype=float) / self.tau_s)[:, None] * np.asarray(self.a_v)

    @classmethod
    def fit_columns(cls, ctx, value):
        return vector_columns(cls, "a_v", "a", ctx, tau_s=value)

    @classmethod
    def fit_parameters(cls, coef, value, labels):
        return vector_parameters("a_v", coef, value)

    @classmethod
    def implausible(cls, p):
        return too_big(p, "a_v", 0.02, "V")

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        return (
            f"After power-on the zero offsets settle by {shown.vector(p['a_v'])} with a time constant of about "
            f"{p['tau_s'] / 60:.1f} min: the early part of the first plateau{shown.temps} is off by up to "
            f"{shown.amount(shown.peak)}."
        )
