"""The extended model ``diagnose`` writes into a passport (read by the passport layer and ``apply``, fitted by
``pipeline.diagnose``): the refit base thermal model plus fitted catalogue effects.

Stored in the passport as ``extended_model``::

    {"schema": "thermocal.extended_model/1", "normal_temp_c": 20.0,
     "base": {"coefficients": {"K": [[...]], "U0": [...]}, "thermal_model": <polynomial, contract form>},
     "effects": [{"effect": "<catalogue id>", "parameters": {...}}, ...],      # pipeline.effects parameter names
     "source": {...}}

The forward model is the simulator's: ``U = K(T*) a + U0(T*) + sum of delta_u_v`` over the effects, with
``T* = T_e`` (the lagged element temperature) when ``thermal_lag`` is among them and T otherwise.
:func:`pipeline.passport.document.compensate_extended` inverts it for the specific force: it needs the signal
context of the samples (times, temperature, ramp direction, moves), because several effects depend on the history
of the run, not only on the current sample. The face error is not compensated: the rotated vector is the true
specific force.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pipeline.effects.base import Effect, SignalContext
from pipeline.effects.catalogue import make_effect
from pipeline.model import output_v, specific_force_g
from pipeline.thermal import PolynomialModel

SCHEMA_ID = "thermocal.extended_model/1"


@dataclass
class ExtendedModel:
    """A polynomial base thermal model and catalogue effects with fitted parameters."""

    base: PolynomialModel
    effects: list[Effect]
    source: dict | None = None

    @property
    def _lag(self) -> Effect | None:
        """The effect that moves the temperature the constants are evaluated at (thermal lag), if any."""
        return next((e for e in self.effects if e.acts_on == "temperature"), None)

    @property
    def lag_tau_s(self) -> float | None:
        lag = self._lag
        return None if lag is None else lag.nonlinear_value()

    def element_temperature_c(self, ctx: SignalContext, element_temp_c: np.ndarray | None = None) -> np.ndarray:
        """T* of the samples: the lagged element temperature with thermal lag (``element_temp_c`` when given,
        e.g. computed on a continuous thermosensor series; else the lag of ``ctx.temp_c``), else ``ctx.temp_c``."""
        lag = self._lag
        if lag is None:
            return np.asarray(ctx.temp_c, float)
        return lag.element_temperature_c(ctx) if element_temp_c is None else np.asarray(element_temp_c, float)

    def _output_terms_v(self, ctx: SignalContext, with_face: bool) -> np.ndarray:
        out = np.zeros((len(ctx.t_s), 3))
        for e in self.effects:
            if e.acts_on == "temperature" or (e.acts_on == "specific_force" and not with_face):
                continue
            out += e.delta_u_v(ctx)
        return out

    def output_v(self, ctx: SignalContext, element_temp_c: np.ndarray | None = None) -> np.ndarray:
        """Predicted outputs (n, 3) V for the context's nominal specific force ``ctx.a_g``."""
        c = replace(ctx, constants=self.base)
        k, u0 = self.base.constants_at(self.element_temperature_c(c, element_temp_c))
        return output_v(k, u0, c.a_g) + self._output_terms_v(c, with_face=True)

    def specific_force_g(
        self, u_v: np.ndarray, ctx: SignalContext, element_temp_c: np.ndarray | None = None, iterations: int = 3
    ) -> np.ndarray:
        """Specific force (n, 3) g from outputs ``u_v`` (n, 3) V: the base inverted at T*, the output effects
        subtracted, iterated because some effects depend on the specific force (ctx.a_g is not used)."""
        u_v = np.asarray(u_v, dtype=float)
        k, u0 = self.base.constants_at(self.element_temperature_c(ctx, element_temp_c))
        a = specific_force_g(k, u0, u_v)
        if not any(e.acts_on == "output" for e in self.effects):
            return a
        for _ in range(iterations):
            c = replace(ctx, a_g=a, constants=self.base)
            a = specific_force_g(k, u0, u_v - self._output_terms_v(c, with_face=False))
        return a

    def to_dict(self) -> dict[str, Any]:
        doc = {
            "schema": SCHEMA_ID,
            "normal_temp_c": float(self.base.normal_temp_c),
            "base": {
                "coefficients": {"K": np.asarray(self.base.K0).tolist(), "U0": np.asarray(self.base.U00).tolist()},
                "thermal_model": self.base.to_dict(),
            },
            "effects": [{"effect": e.id, "parameters": e.stored_params()} for e in self.effects],
        }
        if self.source:
            doc["source"] = self.source
        return doc

    @classmethod
    def from_dict(cls, d: dict) -> ExtendedModel:
        if d.get("schema") != SCHEMA_ID:
            raise ValueError(f"not a {SCHEMA_ID} document")
        t0 = float(d["normal_temp_c"])
        c = d["base"]["coefficients"]
        base = PolynomialModel.from_dict(
            d["base"]["thermal_model"], np.asarray(c["K"], float), np.asarray(c["U0"], float), t0
        )
        return cls(base, [make_effect(e["effect"], e["parameters"]) for e in d["effects"]], d.get("source"))


__all__ = ["ExtendedModel", "SCHEMA_ID"]
