"""``time_drift``: bias ageing over the run, U0 += r (t - t_start), r in V/h per axis.

Shows where one temperature is revisited: the revisits drift monotonically with time. Most of its own term is
absorbed by the base model at the calibration points, so a diagnosis shows it by refitting without it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.effects.base import Effect, Shown, SignalContext, Vec3, too_big, vector_columns, vector_parameters


@dataclass(frozen=True)
class TimeDrift(Effect):
    """Bias ageing: U0 += r (t - t_start)."""

    id: ClassVar[str] = "time_drift"
    order: ClassVar[int] = 3
    where: ClassVar[str] = "revisits of one temperature drift monotonically with time"
    shown_by_refit: ClassVar[bool] = True
    offset_rate_param: ClassVar[str | None] = "r_v_per_h"
    r_v_per_h: Vec3 = (3e-6, -2e-6, 4e-6)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        return (np.asarray(ctx.t_s, dtype=float) / 3600.0)[:, None] * np.asarray(self.r_v_per_h)

    @classmethod
    def fit_columns(cls, ctx, value):
        return vector_columns(cls, "r_v_per_h", "r", ctx)

    @classmethod
    def fit_parameters(cls, coef, value, labels):
        return vector_parameters("r_v_per_h", coef)

    @classmethod
    def implausible(cls, p):
        return too_big(p, "r_v_per_h", 1e-3, "V/h")

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        r = np.asarray(p["r_v_per_h"])
        return (
            f"The zero offsets age at {shown.vector(r, '/h')}, {shown.vector(r * shown.duration_h)} over the "
            f"{shown.duration_h:.1f} h run: revisits of one temperature{shown.temps} drift monotonically with "
            "time."
        )
