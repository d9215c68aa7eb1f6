"""Mismatches outside the effect catalogue (docs/physics.md, last paragraph of "Real recordings"): what the simulator
can add to test that ``diagnose`` does not force a catalogue name onto them. They are not catalogue ids and ``diagnose``
never fits them by name: it must report ``constants_shift`` for the first and ``unexplained`` for the others.

- ``constants_shift``: the unit's constants moved since its passport was made, U += dK a + dU0 with
  dK = diag(Kii) dgain_rel (a relative gain change per axis) and dU0 in V at the start of the recording, and,
  gradually, on from there: dU0 += du0_rate_v_per_h (t - t_start) and dgain_rel += dgain_rate_rel_per_h (t - t_start)
  (rates per hour; ``diagnose`` given the passport reports both as ``constants_shift``);
- ``bias_step``: a step of the zero offsets at ``t_h`` hours into the run (a shock), U += step_v for t >= t_h;
- ``bias_random_walk``: the zero offsets wander, U += W(t) with W a random walk of ``sigma_v_per_sqrt_h``
  (V/sqrt(h)) per axis drawn on a ``step_s`` grid with ``seed`` and interpolated;
- ``periodic``: a periodic disturbance (the chamber's compressor cycling), U += amp_v sin(2 pi t / period_s + phase).

Each is an :class:`~pipeline.effects.base.Effect` (same parameters syntax ``ID[:k=v,...]``), kept out of
:mod:`pipeline.effects` so that the catalogue stays what docs/physics.md lists.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.effects.base import Effect, SignalContext, Vec3
from pipeline.effects.catalogue import parse_spec


@dataclass(frozen=True)
class ConstantsShift(Effect):
    """U += diag(Kii g(t)) a + u(t): the constants moved since the passport, with u(t) = du0_v + du0_rate_v_per_h
    t_h and g(t) = dgain_rel + dgain_rate_rel_per_h t_h (t_h: hours since the start of the recording)."""

    id: ClassVar[str] = "constants_shift"
    where: ClassVar[str] = "everywhere: the passport's constants no longer hold"
    du0_v: Vec3 = (200e-6, -150e-6, 100e-6)
    dgain_rel: Vec3 = (0.0, 0.0, 0.0)
    du0_rate_v_per_h: Vec3 = (0.0, 0.0, 0.0)
    dgain_rate_rel_per_h: Vec3 = (0.0, 0.0, 0.0)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        k, _ = ctx.k_u0
        kii = np.diagonal(k, axis1=1, axis2=2)
        t_h = (np.asarray(ctx.t_s, dtype=float) / 3600.0)[:, None]
        u = np.asarray(self.du0_v) + t_h * np.asarray(self.du0_rate_v_per_h)
        g = np.asarray(self.dgain_rel) + t_h * np.asarray(self.dgain_rate_rel_per_h)
        return u + kii * g * np.asarray(ctx.a_g)


@dataclass(frozen=True)
class BiasStep(Effect):
    """U += step_v for t >= t_h hours into the run."""

    id: ClassVar[str] = "bias_step"
    where: ClassVar[str] = "from t_h on"
    t_h: float = 8.0
    step_v: Vec3 = (60e-6, -40e-6, 0.0)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        on = (np.asarray(ctx.t_s, dtype=float) >= self.t_h * 3600.0).astype(float)
        return on[:, None] * np.asarray(self.step_v)


@dataclass(frozen=True)
class BiasRandomWalk(Effect):
    """U += W(t), a random walk of sigma_v_per_sqrt_h per axis (drawn on a step_s grid from t = 0, interpolated)."""

    id: ClassVar[str] = "bias_random_walk"
    where: ClassVar[str] = "everywhere, wandering"
    local: ClassVar[bool] = False
    sigma_v_per_sqrt_h: Vec3 = (10e-6, 10e-6, 10e-6)
    step_s: float = 60.0
    seed: int = 1

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        t = np.asarray(ctx.t_s, dtype=float)
        if t.size == 0:
            return np.zeros((0, 3))
        n = int(np.ceil(max(t.max(), 0.0) / self.step_s)) + 2
        steps = np.random.default_rng(self.seed).normal(0.0, 1.0, (n, 3)) * np.sqrt(self.step_s / 3600.0)
        walk = np.vstack([np.zeros(3), np.cumsum(steps[:-1], axis=0)]) * np.asarray(self.sigma_v_per_sqrt_h)
        grid = np.arange(n) * self.step_s
        return np.stack([np.interp(t, grid, walk[:, i]) for i in range(3)], axis=1)

    def validate(self) -> None:
        if not self.step_s > 0:
            raise ValueError(f"disturbance {self.id!r}: step_s must be positive, got {self.step_s}")


@dataclass(frozen=True)
class Periodic(Effect):
    """U += amp_v sin(2 pi t / period_s + phase_rad)."""

    id: ClassVar[str] = "periodic"
    where: ClassVar[str] = "everywhere, periodic"
    amp_v: Vec3 = (20e-6, 20e-6, 0.0)
    period_s: float = 1200.0
    phase_rad: float = 0.0

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        t = np.asarray(ctx.t_s, dtype=float)
        return np.sin(2 * np.pi * t / self.period_s + self.phase_rad)[:, None] * np.asarray(self.amp_v)

    def validate(self) -> None:
        if not self.period_s > 0:
            raise ValueError(f"disturbance {self.id!r}: period_s must be positive, got {self.period_s}")


#: id -> disturbance class (not catalogue effects)
DISTURBANCES: dict[str, type[Effect]] = {c.id: c for c in (ConstantsShift, BiasStep, BiasRandomWalk, Periodic)}


def make_disturbance(disturbance_id: str, params: dict[str, Any] | None = None) -> Effect:
    """The disturbance ``disturbance_id`` with ``params`` over its defaults."""
    try:
        cls = DISTURBANCES[disturbance_id]
    except KeyError:
        raise ValueError(f"unknown disturbance {disturbance_id!r}; expected one of {', '.join(DISTURBANCES)}") from None
    return cls.make(params)


def parse_disturbance_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """The CLI syntax ``ID[:k=v,...]`` into (id, all parameters with defaults filled in)."""
    did, overrides = parse_spec(spec)
    d = make_disturbance(did, overrides)
    return d.id, d.params()


__all__ = [
    "DISTURBANCES",
    "ConstantsShift",
    "BiasStep",
    "BiasRandomWalk",
    "Periodic",
    "make_disturbance",
    "parse_disturbance_spec",
]
