"""The catalogue of left-out physics (physics.md "the effect catalogue"), as signal contributions.

Each effect is a small dataclass of named parameters (units in the names) with defaults at a size an engineer cares
about: clearly above the 5 uV per-sample noise once a soaked plateau is averaged, but not huge. Every effect has

- ``delta_u_v(ctx) -> (n, 3)``: the change of the output U in V, a pure function of a :class:`SignalContext`
  (times, temperature, specific force, positions, moves, the constants model). The simulator adds these to
  ``K(T) a + U0(T)``; the diagnosis can evaluate and fit the same functions on residuals.
- ``params() -> dict``: all parameters, JSON-able (3-vectors as lists x, y, z).

Two effects change an input of the model rather than U; they also carry a hook for that:

- ``thermal_lag``: :meth:`ThermalLag.element_temperature_c` is the lagged sensing-element temperature T_e;
  ``delta_u_v`` is U evaluated at T_e minus U at T.
- ``fixture_face_error``: :meth:`FixtureFaceError.rotation_vectors_rad` gives delta_P of every position and
  :meth:`FixtureFaceError.position_vectors_g` the true specific force R(delta_P) a_P (the simulator builds its
  orientations from these, so it does not add ``delta_u_v`` again); ``delta_u_v`` is ``K(T) (R_P a - a)`` on the
  static samples, for a context whose ``a_g`` is nominal.

Effects are made by id with :func:`make_effect` or from the CLI syntax ``ID[:k=v,...]`` with
:func:`parse_effect_spec`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar

import numpy as np
from scipy.signal import lfilter, lfiltic
from scipy.spatial.transform import Rotation

from pipeline.model import ConstantsModel, output_v
from pipeline.positions import ALL_POSITIONS, AXES, POSITION_NAMES

Vec3 = tuple[float, float, float]


# ----------------------------------------------------------------------------------------------------------------
# Shared numerics


def first_order_lag(t_s: np.ndarray, x: np.ndarray, tau_s: float, y0: float | None = None) -> np.ndarray:
    """Response y of ``tau dy/dt = x - y`` to ``x`` sampled at ``t_s``, starting from ``y0`` (default x[0]).

    Exact for x linear between samples (first-order-hold discretisation, one ``lfilter`` pass). A non-uniform grid
    is resampled to its median step and back.
    """
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(x, dtype=float)
    y_start = float(x[0]) if (y0 is None and x.size) else y0
    if tau_s <= 0 or x.size < 2:
        return x.copy() if tau_s <= 0 else np.full_like(x, y_start)
    dt = np.diff(t)
    h = float(np.median(dt))
    if not np.allclose(dt, h, rtol=1e-6, atol=1e-9):
        grid = t[0] + h * np.arange(int(np.ceil((t[-1] - t[0]) / h)) + 1)
        return np.interp(t, grid, first_order_lag(grid, np.interp(grid, t, x), tau_s, y_start))
    a = np.exp(-h / tau_s)
    c = tau_s / h * (1.0 - a)
    b = [1.0 - c, c - a]
    den = [1.0, -a]
    rest, _ = lfilter(b, den, x[1:], zi=lfiltic(b, den, [y_start], [x[0]]))
    return np.concatenate([[y_start], rest])


def ramp_sign_from_temperature(t_s: np.ndarray, temp_c: np.ndarray, threshold_c_per_min: float = 0.2,
                               window_s: float = 120.0) -> np.ndarray:
    """The direction the temperature last came from, per sample: +1 after heating, -1 after cooling, 0 before the
    first ramp (for :class:`SignalContext` ``ramp_sign`` built from a recording).

    The rate is the difference over ``window_s``; a ramp is where its magnitude exceeds ``threshold_c_per_min``.
    """
    t = np.asarray(t_s, dtype=float)
    temp = np.asarray(temp_c, dtype=float)
    rate_c_per_min = (np.interp(t + window_s / 2, t, temp) - np.interp(t - window_s / 2, t, temp)) / window_s * 60
    ramping = np.abs(rate_c_per_min) > threshold_c_per_min
    last = np.maximum.accumulate(np.where(ramping, np.arange(t.size), -1))
    return np.where(last >= 0, np.sign(rate_c_per_min[np.maximum(last, 0)]), 0.0)


# ----------------------------------------------------------------------------------------------------------------
# The context every effect reads


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


# ----------------------------------------------------------------------------------------------------------------
# The effects


class Effect:
    """Base of the catalogue entries: ``id``, ``acts_on`` ("output", "temperature" or "specific_force")."""

    id: ClassVar[str] = ""
    acts_on: ClassVar[str] = "output"
    where: ClassVar[str] = ""

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:  # pragma: no cover - every effect overrides it
        raise NotImplementedError

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


@dataclass(frozen=True)
class ThermalLag(Effect):
    """The sensing element's temperature T_e lags the thermosensor: tau dT_e/dt = T - T_e; the constants are
    evaluated at T_e."""

    id: ClassVar[str] = "thermal_lag"
    acts_on: ClassVar[str] = "temperature"
    where: ClassVar[str] = "during ramps and early in soaks, sign set by dT/dt; gone on soaked plateaus"
    tau_s: float = 120.0

    def element_temperature_c(self, ctx: SignalContext) -> np.ndarray:
        """Hook: the lagged element temperature T_e (n,), C."""
        return first_order_lag(ctx.t_s, ctx.temp_c, self.tau_s)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        k_e, u0_e = ctx.constants.constants_at(self.element_temperature_c(ctx))
        return output_v(k_e, u0_e, ctx.a_g) - ctx.model_output_v()


@dataclass(frozen=True)
class ThermalHysteresis(Effect):
    """U0 += s h, s = +1 after a heating ramp, -1 after a cooling ramp, 0 before the first ramp."""

    id: ClassVar[str] = "thermal_hysteresis"
    where: ClassVar[str] = "one temperature revisited from above and from below disagrees by 2 h, even soaked"
    h_v: Vec3 = (50e-6, -40e-6, 30e-6)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        s = np.zeros(len(ctx.t_s)) if ctx.ramp_sign is None else np.asarray(ctx.ramp_sign, dtype=float)
        return s[:, None] * np.asarray(self.h_v)


@dataclass(frozen=True)
class TimeDrift(Effect):
    """Bias ageing: U0 += r (t - t_start)."""

    id: ClassVar[str] = "time_drift"
    where: ClassVar[str] = "revisits of one temperature drift monotonically with time"
    r_v_per_h: Vec3 = (3e-6, -2e-6, 4e-6)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        return (np.asarray(ctx.t_s, dtype=float) / 3600.0)[:, None] * np.asarray(self.r_v_per_h)


@dataclass(frozen=True)
class WarmupTransient(Effect):
    """Bias settling after power-on (the recording start): U0 += A exp(-(t - t_start)/tau)."""

    id: ClassVar[str] = "warmup_transient"
    where: ClassVar[str] = "early part of the first plateau only"
    a_v: Vec3 = (300e-6, -200e-6, 150e-6)
    tau_s: float = 900.0

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        return np.exp(-np.asarray(ctx.t_s, dtype=float) / self.tau_s)[:, None] * np.asarray(self.a_v)


@dataclass(frozen=True)
class TemperatureCurvature(Effect):
    """A cubic part of the temperature dependence: U0_i += c_i dT^3 and Kii *= (1 + c_rel_i dT^3)."""

    id: ClassVar[str] = "temperature_curvature"
    where: ClassVar[str] = "between calibration temperatures (ramps, VP plateaus at -10 and +45 C)"
    c_v_per_c3: Vec3 = (1.5e-9, -1.0e-9, 1.0e-9)
    c_rel_per_c3: Vec3 = (1.0e-9, 1.5e-9, -1.0e-9)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        k, _ = ctx.k_u0
        kii = np.diagonal(k, axis1=1, axis2=2)
        dt3 = (ctx.dt_c ** 3)[:, None]
        return dt3 * (np.asarray(self.c_v_per_c3) + kii * np.asarray(self.c_rel_per_c3) * ctx.a_g)


@dataclass(frozen=True)
class ScaleNonlinearity(Effect):
    """Second-order scale factor (IEEE 1293 K2): U_i += k2_i a_i^2."""

    id: ClassVar[str] = "scale_nonlinearity"
    where: ClassVar[str] = "a channel's own vertical positions (TP5+TP6 for x) differ from its horizontal pairs"
    k2_v_per_g2: Vec3 = (30e-6, -20e-6, 25e-6)

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        return np.asarray(ctx.a_g) ** 2 * np.asarray(self.k2_v_per_g2)


@dataclass(frozen=True)
class FixtureFaceError(Effect):
    """Each tilt face has its own small angular error: in position P the true a is R(delta_P) a_nominal.

    ``delta_rad`` gives the rotation vectors per position explicitly (positions not named have none); when it is
    None they are drawn from N(0, sigma_deg) per component with ``seed``.
    """

    id: ClassVar[str] = "fixture_face_error"
    acts_on: ClassVar[str] = "specific_force"
    where: ClassVar[str] = "horizontal channels of single positions, VP errors; constant in temperature"
    sigma_deg: float = 0.01
    seed: int = 1
    delta_rad: dict[str, Vec3] | None = None

    def rotation_vectors_rad(self) -> dict[str, np.ndarray]:
        """delta_P (3,) in rad for every position."""
        if self.delta_rad is not None:
            unknown = set(self.delta_rad) - set(ALL_POSITIONS)
            if unknown:
                raise ValueError(f"fixture_face_error: unknown positions {sorted(unknown)}")
            return {p: np.asarray(self.delta_rad.get(p, (0.0, 0.0, 0.0)), dtype=float) for p in POSITION_NAMES}
        draws = np.random.default_rng(self.seed).normal(0.0, np.radians(self.sigma_deg), (len(POSITION_NAMES), 3))
        return dict(zip(POSITION_NAMES, draws))

    def position_vectors_g(self) -> dict[str, np.ndarray]:
        """Hook: the true specific force (g) of every position, R(delta_P) a_nominal."""
        return {p: Rotation.from_rotvec(d).apply(np.asarray(ALL_POSITIONS[p], dtype=float))
                for p, d in self.rotation_vectors_rad().items()}

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        rot = self.rotation_vectors_rad()
        table = np.array([rot[p] for p in POSITION_NAMES] + [np.zeros(3)])  # last row: moving / unknown
        idx = np.where(np.asarray(ctx.position_idx) >= 0, ctx.position_idx, len(POSITION_NAMES))
        a = np.asarray(ctx.a_g, dtype=float)
        k, _ = ctx.k_u0
        return np.einsum("nij,nj->ni", k, Rotation.from_rotvec(table[idx]).apply(a) - a)

    def params(self) -> dict[str, Any]:
        out = super().params()
        out["delta_rad"] = {p: v.tolist() for p, v in self.rotation_vectors_rad().items()}
        return out


@dataclass(frozen=True)
class TiltSettling(Effect):
    """Anelastic creep after each move: U += -f (U_new - U_old) exp(-(t - t_arrive)/tau) after the arrival."""

    id: ClassVar[str] = "tilt_settling"
    where: ClassVar[str] = "start of every static position, decaying"
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


EFFECTS: dict[str, type[Effect]] = {cls.id: cls for cls in (
    ThermalLag, ThermalHysteresis, TimeDrift, WarmupTransient, TemperatureCurvature, ScaleNonlinearity,
    FixtureFaceError, TiltSettling)}


# ----------------------------------------------------------------------------------------------------------------
# Construction by id and from the CLI syntax


def make_effect(effect_id: str, params: dict[str, Any] | None = None) -> Effect:
    """The effect ``effect_id`` with ``params`` over its defaults.

    A 3-vector parameter takes 3 values or one scalar for all axes; ``name_x`` / ``name_y`` / ``name_z`` set one
    axis. Unknown ids or parameters and bad values raise ValueError naming them.
    """
    try:
        cls = EFFECTS[effect_id]
    except KeyError:
        raise ValueError(f"unknown effect {effect_id!r}; expected one of {', '.join(EFFECTS)}") from None
    defaults = cls()
    fields = {f.name: getattr(defaults, f.name) for f in dataclasses.fields(cls)}
    values = dict(fields)
    for key, raw in (params or {}).items():
        name, axis = key, None
        if key not in fields and key[-2:] in ("_x", "_y", "_z") and isinstance(fields.get(key[:-2]), tuple):
            name, axis = key[:-2], AXES.index(key[-1])
        if name not in fields:
            raise ValueError(f"effect {effect_id!r} has no parameter {key!r}; parameters: "
                             f"{', '.join(_describe_params(fields))}")
        default = fields[name]
        try:
            if isinstance(default, tuple):
                if axis is not None:
                    vec = list(values[name])
                    vec[axis] = _finite(raw)
                    values[name] = tuple(vec)
                elif np.ndim(raw) == 0:
                    values[name] = (_finite(raw),) * 3
                else:
                    vec = [_finite(v) for v in raw]
                    if len(vec) != 3:
                        raise ValueError("needs 3 values (x, y, z)")
                    values[name] = tuple(vec)
            elif isinstance(default, bool):
                raise ValueError("boolean parameters are not supported")
            elif isinstance(default, int):
                x = _finite(raw)
                if x != int(x):
                    raise ValueError("needs an integer")
                values[name] = int(x)
            elif name == "delta_rad":
                values[name] = None if raw is None else {str(p): tuple(_finite(v) for v in d) for p, d in raw.items()}
            else:
                values[name] = _finite(raw)
        except (TypeError, ValueError, AttributeError) as e:
            raise ValueError(f"effect {effect_id!r}: bad value {raw!r} for {key!r}: {e}") from None
    effect = cls(**values)
    _validate(effect)
    return effect


def _finite(v: Any) -> float:
    x = float(v)
    if not np.isfinite(x):
        raise ValueError("not a finite number")
    return x


def _describe_params(fields: dict[str, Any]) -> list[str]:
    return [f"{n} (3-vector, or {n}_x/_y/_z)" if isinstance(v, tuple) else n for n, v in fields.items()]


def _validate(effect: Effect) -> None:
    for name in ("tau_s", "sigma_deg"):
        v = getattr(effect, name, None)
        if v is not None and v < 0:
            raise ValueError(f"effect {effect.id!r}: {name} must not be negative, got {v}")
    if getattr(effect, "tau_s", 1.0) == 0 and not isinstance(effect, ThermalLag):
        raise ValueError(f"effect {effect.id!r}: tau_s must be positive")
    if isinstance(effect, FixtureFaceError):
        effect.rotation_vectors_rad()


def parse_effect_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Parse the CLI syntax ``ID[:k=v,...]`` into (id, all parameters with defaults filled in).

    ``thermal_hysteresis:h_v=2e-5`` sets all three axes, ``thermal_hysteresis:h_v_y=2e-5`` only y.
    """
    text = spec.strip()
    effect_id, colon, rest = text.partition(":")
    effect_id = effect_id.strip()
    overrides: dict[str, Any] = {}
    if rest.strip():
        for item in rest.split(","):
            key, eq, value = item.partition("=")
            if not eq or not key.strip() or not value.strip():
                raise ValueError(f"bad effect parameter {item.strip()!r} in {spec!r}: expected name=value")
            try:
                overrides[key.strip()] = float(value)
            except ValueError:
                raise ValueError(f"effect {effect_id!r}: {key.strip()!r} is not a number: {value.strip()!r}") \
                    from None
    elif colon:
        raise ValueError(f"effect spec {spec!r} has ':' but no parameters")
    effect = make_effect(effect_id, overrides)
    return effect.id, effect.params()
