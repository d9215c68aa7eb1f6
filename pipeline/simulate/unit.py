"""The simulated accelerometer unit: its 12 constants as smooth functions of temperature (docs/physics.md).

A :class:`UnitTruth` holds, for each of the 12 constants (K 3x3 in V/g, U0 in V), polynomial coefficients in
``dT = T - T0`` (absolute: ``K(T) = sum_n K_coef[n] dT^n``, units V/g/C^n and V/C^n). It implements
:class:`pipeline.model.ConstantsModel`, so the simulator, tests and the diagnosis can evaluate it like a passport.

- :func:`seed000_unit`: the real unit of seed 000 (Tables 1-2), quadratic through its three temperatures.
- :func:`random_unit`: another unit of the same type, reproducible from a seed.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.positions import AXES

SEED000_TABLES = Path(__file__).resolve().parent / "data" / "seed000_tables.json"

#: Calibration temperatures of the seed 000 tables (C).
SEED000_TEMPS_C = (20.0, -40.0, 70.0)


@dataclass(frozen=True, eq=False)
class UnitTruth:
    """A unit's constants as polynomials in ``dT = T - normal_temp_c``.

    ``k_coef`` has shape (order+1, 3, 3) in V/g/C^n, ``u0_coef`` shape (order+1, 3) in V/C^n; row 0 is the value
    at T0. ``label`` says where the unit came from (``seed000``, ``random:7``).
    """

    normal_temp_c: float
    k_coef: np.ndarray
    u0_coef: np.ndarray
    label: str = ""

    def __post_init__(self):
        k = np.asarray(self.k_coef, dtype=float)
        u = np.asarray(self.u0_coef, dtype=float)
        if k.ndim != 3 or k.shape[1:] != (3, 3) or u.shape != (k.shape[0], 3) or not 1 <= k.shape[0] <= 4:
            raise ValueError(
                f"UnitTruth needs K coefficients (m,3,3) and U0 coefficients (m,3) with m in 1..4, "
                f"got {k.shape} and {u.shape}"
            )
        object.__setattr__(self, "k_coef", k)
        object.__setattr__(self, "u0_coef", u)

    @property
    def order(self) -> int:
        return self.k_coef.shape[0] - 1

    def constants_at(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """K (n, 3, 3) in V/g and U0 (n, 3) in V at temperatures ``temp_c`` (n,) in C."""
        dt_c = np.atleast_1d(np.asarray(temp_c, dtype=float)).reshape(-1) - self.normal_temp_c
        powers = np.vander(dt_c, self.order + 1, increasing=True)
        return (powers @ self.k_coef.reshape(-1, 9)).reshape(-1, 3, 3), powers @ self.u0_coef

    def relative_coefficients(self) -> dict[str, Any]:
        """The same model in the relative form of docs/physics.md / the passport (polynomial of ``order``).

        alpha_n (V/C^n) = U0 coefficient n; beta_n = Kii coefficient n / Kii(T0); gamma_n = Kij coefficient n / Kij(T0).
        """
        k0 = self.k_coef[0]
        rel = self.k_coef[1:] / k0
        return {
            "kind": "polynomial",
            "order": self.order,
            "alpha": {a: self.u0_coef[1:, i].tolist() for i, a in enumerate(AXES)},
            "beta": {a + a: rel[:, i, i].tolist() for i, a in enumerate(AXES)},
            "gamma": {a + b: rel[:, i, j].tolist() for i, a in enumerate(AXES) for j, b in enumerate(AXES) if i != j},
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form; :meth:`from_dict` reads it back exactly (floats round-trip through JSON)."""
        return {
            "kind": "polynomial_in_dT",
            "label": self.label,
            "normal_temp_c": float(self.normal_temp_c),
            "order": self.order,
            "units": {"K_coef": "V/g/C^n", "U0_coef": "V/C^n"},
            "K_coef": self.k_coef.tolist(),
            "U0_coef": self.u0_coef.tolist(),
            "thermal_model": self.relative_coefficients(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> UnitTruth:
        if d.get("kind") != "polynomial_in_dT":
            raise ValueError(f"not a UnitTruth document (kind={d.get('kind')!r})")
        return cls(
            normal_temp_c=float(d["normal_temp_c"]),
            k_coef=np.array(d["K_coef"], dtype=float),
            u0_coef=np.array(d["U0_coef"], dtype=float),
            label=str(d.get("label", "")),
        )


def unit_through_tables(temps_c, k_v_per_g, u0_v, normal_temp_c: float = 20.0, label: str = "") -> UnitTruth:
    """The polynomial of order len(temps_c)-1 in dT passing exactly through the given constants.

    ``k_v_per_g`` (s, 3, 3) and ``u0_v`` (s, 3) are the constants at the ``s`` temperatures ``temps_c``.
    """
    dt_c = np.asarray(temps_c, dtype=float) - normal_temp_c
    s = dt_c.size
    vander = np.vander(dt_c, s, increasing=True)
    values = np.concatenate([np.asarray(k_v_per_g, float).reshape(s, 9), np.asarray(u0_v, float).reshape(s, 3)], axis=1)
    coef = np.linalg.solve(vander, values)
    return UnitTruth(normal_temp_c=normal_temp_c, k_coef=coef[:, :9].reshape(s, 3, 3), u0_coef=coef[:, 9:], label=label)


def seed000_tables() -> list[dict[str, Any]]:
    """Tables 1-2 of seed 000: ``[{"temp_c", "K", "U0"}, ...]`` at +20, -40, +70 C."""
    return json.loads(SEED000_TABLES.read_text())["table_1_2_constants"]


def seed000_unit(normal_temp_c: float = 20.0) -> UnitTruth:
    """The real unit of seed 000: quadratic in T through its constants at +20, -40 and +70 C."""
    tables = seed000_tables()
    return unit_through_tables(
        [t["temp_c"] for t in tables],
        [t["K"] for t in tables],
        [t["U0"] for t in tables],
        normal_temp_c=normal_temp_c,
        label="seed000",
    )


def _signed_loguniform(rng: np.random.Generator, lo: float, hi: float, size) -> np.ndarray:
    mag = np.exp(rng.uniform(np.log(lo), np.log(hi), size))
    return mag * rng.choice([-1.0, 1.0], size)


@dataclass(frozen=True)
class _Magnitudes:
    """How a unit type's units are drawn at T0 = +20 C: gain ``gain_v_per_g`` +- ``gain_rel`` (uniform), cross-axis
    sensitivities of random sign log-uniform in ``cas_v_per_g``, zero-g offsets of random sign log-uniform in
    ``u0_v``; per sub-band (-40..+20, +20..+70 C) chord slopes: beta uniform in ``beta_per_c`` of random sign,
    gamma log-uniform in ``gamma_per_c``, alpha log-uniform in ``alpha_v_per_c``, both of random sign."""

    gain_v_per_g: float
    gain_rel: float
    cas_v_per_g: tuple[float, float]
    u0_v: tuple[float, float]
    beta_per_c: tuple[float, float]
    gamma_per_c: tuple[float, float]
    alpha_v_per_c: tuple[float, float]


def _drawn_unit(unit_seed: int, normal_temp_c: float, m: _Magnitudes, label: str) -> UnitTruth:
    """A unit drawn from ``unit_seed`` with the magnitudes ``m``: quadratic in T through +20, -40 and +70 C."""
    rng = np.random.default_rng(unit_seed)
    k0 = _signed_loguniform(rng, *m.cas_v_per_g, (3, 3))
    k0[np.diag_indices(3)] = m.gain_v_per_g * (1.0 + rng.uniform(-m.gain_rel, m.gain_rel, 3))
    u0 = _signed_loguniform(rng, *m.u0_v, 3)
    diag = np.eye(3, dtype=bool)
    temps_c = [20.0, -40.0, 70.0]
    ks, us = [k0], [u0]
    for t in temps_c[1:]:
        rel = np.where(
            diag,
            rng.uniform(*m.beta_per_c, (3, 3)) * rng.choice([-1.0, 1.0], (3, 3)),
            _signed_loguniform(rng, *m.gamma_per_c, (3, 3)),
        )
        alpha = _signed_loguniform(rng, *m.alpha_v_per_c, 3)
        ks.append(k0 * (1.0 + rel * (t - 20.0)))
        us.append(u0 + alpha * (t - 20.0))
    return unit_through_tables(temps_c, ks, us, normal_temp_c=normal_temp_c, label=label)


#: seed 000's unit type (docs/physics.md "Typical magnitudes")
_NAVIGATION = _Magnitudes(-0.55, 0.01, (3e-4, 0.016), (1e-3, 5e-3), (1e-5, 5e-5), (1e-4, 6e-3), (1.5e-5, 1.5e-4))
#: a consumer MEMS part behind the same voltmeter (an analogue ratiometric triad): +0.3 V/g +-5 %, zero-g offsets
#: 10-50 mg, cross-axis 0.1-2 % of the gain, offset drift 0.1-1 mg/C, scale drift 0.01-0.05 %/C
_CONSUMER = _Magnitudes(0.30, 0.05, (3e-4, 6e-3), (3e-3, 1.5e-2), (1e-4, 5e-4), (1e-4, 6e-3), (3e-5, 3e-4))


def random_unit(unit_seed: int, normal_temp_c: float = 20.0) -> UnitTruth:
    """Another unit of seed 000's type, reproducible from ``unit_seed``; quadratic in T.

    Drawn at T0 = +20 C: gains -0.55 V/g +-1 %, CAS of random sign with magnitudes log-uniform in 3e-4..0.016 V/g,
    U0 of random sign 1..5 mV. Then for each of the sub-bands -40..+20 and +20..+70 C an independent chord slope
    (docs/physics.md "Typical magnitudes"): alpha log-uniform 1.5e-5..1.5e-4 V/C, beta 1e-5..5e-5 /C, gamma log-uniform
    1e-4..6e-3 /C, each of random sign; the unit is the quadratic through the three temperatures.
    """
    return _drawn_unit(unit_seed, normal_temp_c, _NAVIGATION, f"random:{unit_seed}")


def consumer_unit(unit_seed: int, normal_temp_c: float = 20.0) -> UnitTruth:
    """A consumer MEMS unit (:data:`_CONSUMER`), reproducible from ``unit_seed``; quadratic in T as
    :func:`random_unit`."""
    return _drawn_unit(unit_seed, normal_temp_c, _CONSUMER, f"consumer:{unit_seed}")


@dataclass(frozen=True)
class UnitType:
    """A kind of unit the simulator makes (``simulate --unit-type``): the grade its runs say (``unit_grade``; the
    navigation type's runs name none, the default grade), its nominal gain (V/g, signed), its typical voltmeter
    noise per sample (V), the reference unit (``unit_seed`` None) and the units drawn from a seed."""

    name: str
    grade: str
    nominal_gain_v_per_g: float
    noise_v: float
    reference: Callable[[float], UnitTruth]
    draw: Callable[[int, float], UnitTruth]

    def unit(self, unit_seed: int | None, normal_temp_c: float) -> UnitTruth:
        return self.reference(normal_temp_c) if unit_seed is None else self.draw(unit_seed, normal_temp_c)


#: the unit types by name: seed 000's (navigation grade) and a consumer MEMS part (its reference unit: seed 0)
UNIT_TYPES: dict[str, UnitType] = {
    "navigation": UnitType("navigation", "navigation", -0.55, 5e-6, seed000_unit, random_unit),
    "consumer": UnitType("consumer", "consumer", 0.30, 5e-4, lambda t0: consumer_unit(0, t0), consumer_unit),
}


def unit_type(name: str) -> UnitType:
    """The unit type called ``name`` (:data:`UNIT_TYPES`); ValueError naming them otherwise."""
    try:
        return UNIT_TYPES[name]
    except KeyError:
        raise ValueError(f"unknown unit type {name!r} ({', '.join(UNIT_TYPES)})") from None
