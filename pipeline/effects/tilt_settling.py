"""``tilt_settling``: anelastic creep after each move, U += -f (U_new - U_old) exp(-(t - t_arrive)/tau_s) after the
arrival.

Shows at the start of every static position, decaying. A sample's contribution depends on the last move (not
local).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.effects.base import Effect, Shown, SignalContext, log_grid


@dataclass(frozen=True)
class TiltSettling(Effect):
    """Anelastic creep after each move: U += -f (U_new - U_old) exp(-(t - t_arrive)/tau) after the arrival."""

    id: ClassVar[str] = "tilt_settling"
    order: ClassVar[int] = 8
    where: ClassVar[str] = "start of every static position, decaying"
    local: ClassVar[bool] = False
    needs_fixture: ClassVar[str | None] = "the fixture's moves (when each turn started and ended)"
    nonlinear: ClassVar[str | None] = "tau_s"
    grid: ClassVar[tuple[float, ...]] = log_grid(1.0, 900.0, 18)
    f: float = 2e-4
    tau_s: float = 30.0

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        t = np.asarray(ctx.t_s, dtype=float)
        out = np.zeros((t.size, 3))
        arrive = np.asarray(ctx.arrive_s, dtype=float)
        if arrive.size == 0 or t.size == 0:
            return out
        k, _ = ctx.k_u0
        i_old = np.clip(np.searchsorted(t, ctx.move_start_s, side="left") - 1, 0, t.size - 1)
        i_new = np.clip(np.searchsorted(t, arrive, side="left"), 0, t.size - 1)
        jump_v = np.einsum("mij,mj->mi", k[i_new], ctx.a_g[i_new] - ctx.a_g[i_old])  # U_new - U_old per move
        j = np.searchsorted(arrive, t, side="right") - 1
        after = j >= 0
        jj = j[after]
        out[after] = -self.f * jump_v[jj] * np.exp(-(t[after] - arrive[jj]) / self.tau_s)[:, None]
        return out

    @classmethod
    def fit_columns(cls, ctx, value):
        return ["f"], [cls.make({"f": 1.0, "tau_s": value}).delta_u_v(ctx)]

    @classmethod
    def fit_parameters(cls, coef, value, labels):
        return {"f": float(coef[0]), "tau_s": float(value)}

    @classmethod
    def implausible(cls, p):
        if p["f"] <= 0:
            return f"f = {p['f']:.3g} < 0: the reading overshoots instead of creeping"
        return "f beyond 1 %" if p["f"] > 0.01 else None

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        return (
            f"After every move the reading creeps to its final value: {p['f'] * 1e6:.0f} ppm of the step, "
            f"decaying with a time constant of about {p['tau_s']:.0f} s (up to {shown.amount(shown.peak)} at the "
            "start of each static position)."
        )
