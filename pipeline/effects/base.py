"""What every catalogue effect is made of: the signal context it reads and the :class:`Effect` base class.

An effect (one module of :mod:`pipeline.effects` each, docs/physics.md "the effect catalogue") is a small frozen
dataclass of named parameters (units in the names) with defaults at a size an engineer cares about. In one place it
holds everything the project knows about it:

- simulation: ``delta_u_v(ctx) -> (n, 3)``, the change of the output U in V, a pure function of a
  :class:`SignalContext`; ``acts_on`` says whether it changes the output, the temperature the constants are
  evaluated at (``"temperature"``: :meth:`Effect.element_temperature_c`) or the specific force
  (``"specific_force"``: :meth:`Effect.rotation_vectors_rad`); ``local`` whether a sample's contribution depends on
  that sample alone (a long run is then simulated in chunks);
- fit terms for ``diagnose``: :meth:`Effect.fit_columns` (linear columns built from ``delta_u_v`` with unit
  parameters), the grid of its nonlinear parameter (``nonlinear``, ``grid``: a time constant in s),
  :meth:`Effect.fit_parameters` (fitted coefficients back to the effect's parameters) and
  :meth:`Effect.implausible` (physical bounds);
- its explanation for a person (:meth:`Effect.explain`) and how it shows in a diagnosis: ``shown_by_refit`` (its
  own term is mostly absorbed by the base model at the calibration points, so it shows where the data depart from
  the model refitted without it) and ``in_base_from_order`` (a base thermal polynomial of that order contains it).

Effects are made by id with :func:`pipeline.effects.catalogue.make_effect`, which finds every module of the
package; adding an effect is one module plus its tests.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar

import numpy as np

from pipeline.model import ConstantsModel, output_v, small, small_unit
from pipeline.positions import AXES

Vec3 = tuple[float, float, float]


@dataclass(eq=False)
class SignalContext:
    """What the effects need to know about a run, per voltmeter sample (n samples, m moves).

    - ``t_s`` (n,): seconds since the run start (``start_ns``, ns since the epoch)
    - ``temp_c`` (n,): temperature of the AU at the samples, C (the simulator's true case temperature; for a
      recording the thermosensor interpolated to the voltmeter times)
    - ``a_g`` (n, 3): specific force along the AU axes, g
    - ``position_idx`` (n,): index into ``positions.POSITION_NAMES``, -1 while moving or unknown
    - ``move_start_s``, ``arrive_s`` (m,): start and end (arrival) of every move, s since start, in time order
    - ``constants``: the unit's K(T), U0(T) (any :class:`ConstantsModel`)
    - ``normal_temp_c``: T0
    - ``ramp_sign`` (n,): +1 after a heating ramp, -1 after a cooling ramp, 0 before the first ramp (None: all 0)
    """

    t_s: np.ndarray
    temp_c: np.ndarray
    a_g: np.ndarray
    position_idx: np.ndarray
    move_start_s: np.ndarray
    arrive_s: np.ndarray
    constants: ConstantsModel
    normal_temp_c: float = 20.0
    ramp_sign: np.ndarray | None = None
    start_ns: int = 0

    @cached_property
    def k_u0(self) -> tuple[np.ndarray, np.ndarray]:
        """K (n, 3, 3) and U0 (n, 3) at ``temp_c`` (computed once)."""
        return self.constants.constants_at(self.temp_c)

    @property
    def dt_c(self) -> np.ndarray:
        return np.asarray(self.temp_c, dtype=float) - self.normal_temp_c

    def model_output_v(self) -> np.ndarray:
        """U = K(T) a + U0(T), V, without any effect."""
        k, u0 = self.k_u0
        return output_v(k, u0, self.a_g)


@dataclass(frozen=True)
class Shown:
    """Where and how large a fitted effect shows in a diagnosis, for its explanation: the largest change of the
    model (in the output unit ``unit``: V, or m/s^2; printed by :func:`pipeline.model.small`), the axes ("x/z"), the
    temperatures in words (" at -40, +20 C and on the ramps"), the run's length (h)."""

    peak: float
    axes: str
    temps: str
    duration_h: float
    unit: str

    def amount(self, x: float, spec: str = ".1f", per: str = "") -> str:
        """``x`` (in the output unit) in words: :func:`pipeline.model.small` in this diagnosis' unit."""
        return small(x, spec, per, unit=self.unit)

    def vector(self, v, per: str = "") -> str:
        """A 3-vector (in the output unit) in words: :func:`vec_uv` in this diagnosis' unit."""
        return vec_uv(v, per, unit=self.unit)


@dataclass(frozen=True)
class Effect:
    """Base of the catalogue entries (see the module doc for the class attributes and methods)."""

    id: ClassVar[str] = ""
    #: row of docs/physics.md's catalogue table (the catalogue's order)
    order: ClassVar[int] = 99
    acts_on: ClassVar[str] = "output"
    where: ClassVar[str] = ""
    local: ClassVar[bool] = True
    shown_by_refit: ClassVar[bool] = False
    in_base_from_order: ClassVar[int | None] = None
    nonlinear: ClassVar[str | None] = None
    grid: ClassVar[tuple[float, ...]] = ()
    #: the parameter (V/h per axis) when the effect is exactly a drift of the offsets linear in time since the
    #: start of the recording (its forward model then also carries a drift of the constants a diagnosis finds)
    offset_rate_param: ClassVar[str | None] = None
    #: what of the fixture the effect reads besides time, temperature and specific force (e.g. its moves), in
    #: words; None: nothing, so it can be evaluated on any recording from its own columns (``thermocal apply``)
    needs_fixture: ClassVar[str | None] = None

    # ---- simulation
    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:  # pragma: no cover - every effect overrides it
        raise NotImplementedError

    def element_temperature_c(self, ctx: SignalContext) -> np.ndarray:
        """For ``acts_on == "temperature"``: the temperature (n,) C the constants are evaluated at."""
        return np.asarray(ctx.temp_c, dtype=float)

    def rotation_vectors_rad(self) -> dict[str, np.ndarray]:
        """For ``acts_on == "specific_force"``: the rotation (3,) rad of every position's true specific force."""
        return {}

    def nonlinear_value(self) -> float | None:
        """The value of the nonlinear parameter named by ``nonlinear`` (a time constant, s); None without one."""
        return None if self.nonlinear is None else float(getattr(self, self.nonlinear))

    def params(self) -> dict[str, Any]:
        """All parameters, JSON-able."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, tuple):
                v = [float(x) for x in v]
            elif isinstance(v, dict):
                v = {k: [float(x) for x in val] for k, val in v.items()}
            out[f.name] = v
        return out

    def stored_params(self) -> dict[str, Any]:
        """The parameters an extended model stores (all of them unless an effect says otherwise)."""
        return self.params()

    def validate(self) -> None:
        """Raise ValueError naming a parameter out of its domain."""
        for name in ("tau_s", "sigma_deg"):
            v = getattr(self, name, None)
            if v is not None and v < 0:
                raise ValueError(f"effect {self.id!r}: {name} must not be negative, got {v}")
        if getattr(self, "tau_s", 1.0) == 0:
            raise ValueError(f"effect {self.id!r}: tau_s must be positive")

    @classmethod
    def make(cls, params: dict[str, Any] | None = None) -> Effect:
        """The effect with ``params`` over its defaults.

        A 3-vector parameter takes 3 values or one scalar for all axes; ``name_x`` / ``name_y`` / ``name_z`` set one
        axis. Unknown parameters and bad values raise ValueError naming them.
        """
        defaults = cls()
        fields = {f.name: getattr(defaults, f.name) for f in dataclasses.fields(cls)}
        values = dict(fields)
        for key, raw in (params or {}).items():
            name, axis = key, None
            if key not in fields and key[-2:] in ("_x", "_y", "_z") and isinstance(fields.get(key[:-2]), tuple):
                name, axis = key[:-2], AXES.index(key[-1])
            if name not in fields:
                raise ValueError(
                    f"effect {cls.id!r} has no parameter {key!r}; parameters: {', '.join(_describe_params(fields))}"
                )
            try:
                values[name] = cls._convert(name, fields[name], values[name], axis, raw)
            except (TypeError, ValueError, AttributeError) as e:
                raise ValueError(f"effect {cls.id!r}: bad value {raw!r} for {key!r}: {e}") from None
        effect = cls(**values)
        effect.validate()
        return effect

    @classmethod
    def _convert(cls, name: str, default: Any, current: Any, axis: int | None, raw: Any) -> Any:
        """One parameter value from its raw form (the type of its default decides)."""
        if isinstance(default, tuple):
            if axis is not None:
                vec = list(current)
                vec[axis] = finite(raw)
                return tuple(vec)
            if np.ndim(raw) == 0:
                return (finite(raw),) * 3
            vec = [finite(v) for v in raw]
            if len(vec) != 3:
                raise ValueError("needs 3 values (x, y, z)")
            return tuple(vec)
        if isinstance(default, bool):
            raise ValueError("boolean parameters are not supported")
        if isinstance(default, int):
            x = finite(raw)
            if x != int(x):
                raise ValueError("needs an integer")
            return int(x)
        return finite(raw)

    # ---- fit terms (diagnose)
    @classmethod
    def fit_columns(cls, ctx: SignalContext, value: float | None) -> tuple[list[str], list[np.ndarray]]:
        """Labels and (n, 3) columns, one per linear parameter, at the nonlinear parameter ``value``."""
        return [], []

    @classmethod
    def fit_parameters(cls, coef: np.ndarray, value: float | None, labels: list[str]) -> dict[str, Any]:
        """The effect's parameters from fitted coefficients (so that :meth:`make` rebuilds the fitted effect)."""
        return {}

    @classmethod
    def implausible(cls, params: dict[str, Any]) -> str | None:
        """Why fitted parameters are physically implausible, or None."""
        return None

    # ---- explanation
    @classmethod
    def explain(cls, params: dict[str, Any], shown: Shown) -> str:
        """One or two plain sentences for a person: what, where, how big, with units."""
        return f"{cls.id}: up to {shown.amount(shown.peak)} on {shown.axes}."


# ----------------------------------------------------------------------------------------------------------------
# Helpers the effect modules share


def finite(v: Any) -> float:
    x = float(v)
    if not np.isfinite(x):
        raise ValueError("not a finite number")
    return x


def _describe_params(fields: dict[str, Any]) -> list[str]:
    return [f"{n} (3-vector, or {n}_x/_y/_z)" if isinstance(v, tuple) else n for n, v in fields.items()]


def log_grid(lo: float, hi: float, n: int) -> tuple[float, ...]:
    """``n`` values from ``lo`` to ``hi`` evenly spaced in log."""
    return tuple(float(x) for x in np.geomspace(lo, hi, n))


def axis_columns(cls: type[Effect], name: str, ctx: SignalContext, **fixed) -> list[np.ndarray]:
    """``delta_u_v`` of ``cls`` with its 3-vector parameter ``name`` set to each unit vector in turn."""
    return [cls.make({name: list(e), **fixed}).delta_u_v(ctx) for e in np.eye(3)]


def vector_columns(
    cls: type[Effect], name: str, prefix: str, ctx: SignalContext, **fixed
) -> tuple[list[str], list[np.ndarray]]:
    """Labels ``prefix_x/_y/_z`` and :func:`axis_columns`."""
    return [f"{prefix}_{a}" for a in AXES], axis_columns(cls, name, ctx, **fixed)


def vector_parameters(name: str, coef: np.ndarray, value: float | None = None) -> dict[str, Any]:
    """``{name: coef[:3]}``, with ``tau_s`` when there is a time constant."""
    out: dict[str, Any] = {name: [float(c) for c in coef[:3]]}
    if value is not None:
        out["tau_s"] = float(value)
    return out


def too_big(params: dict, name: str, limit: float, unit: str) -> str | None:
    """A reason when the largest magnitude of ``params[name]`` exceeds ``limit``."""
    v = np.max(np.abs(params[name]))
    return f"{name} {v:.3g} {unit} is beyond {limit:.3g} {unit}" if v > limit else None


def vec_uv(v, per: str = "", *, unit: str) -> str:
    """A 3-vector in the output unit ``unit`` as "x +1.25, y -2.00, z +0.50 uV" (in the small unit of
    :func:`pipeline.model.small_name`; ``per`` e.g. ``/h``): for volts in nV when every component is below 1 uV
    (``+0.0 uV/h`` says nothing), to three significant digits of the largest."""
    unit, scale = small_unit(unit)
    x = np.asarray(v, dtype=float) * scale
    finite = np.abs(x[np.isfinite(x)])
    big = float(finite.max()) if finite.size else 0.0
    if 0.0 < big < 1.0 and unit == "uV":
        x, big, unit = x * 1e3, big * 1e3, "nV"
    decimals = (
        0
        if big >= 100
        else 1
        if big >= 10
        else 2
        if big >= 1 or big == 0.0
        else min(6, 2 - int(np.floor(np.log10(big))))
    )
    return ", ".join(f"{a} {c:+.{decimals}f}" for a, c in zip(AXES, x)) + f" {unit}{per}"


__all__ = [
    "SignalContext",
    "Shown",
    "Effect",
    "Vec3",
    "finite",
    "log_grid",
    "axis_columns",
    "vector_columns",
    "vector_parameters",
    "too_big",
    "vec_uv",
]
