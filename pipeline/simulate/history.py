"""A fleet's calibration history made directly: passports of simulated units at successive recalibrations, written
into a registry through its one writing path (:meth:`pipeline.passport.registry.Registry.publish`: signed,
hash-chained), without simulating and calibrating a chamber run for each (``thermocal trends`` is tested and
benchmarked on registries of hundreds to thousands of units).

A passport of :func:`simulated_passport` holds what a calibration of the unit would measure: its constants at T0
(docs/physics.md), its constants per plateau at -40, +20 and +70 C and its polynomial thermal model of order 2, each
the unit's truth plus a normal error of the passport's own standard uncertainty (:class:`PassportNoise`, the
magnitudes of a short-program calibration at 2 Hz: about 0.12 uV on U0 and 0.2 uV/g on K), which its ``uncertainty``
block states; verification rows at -10, +20 and +45 C within a few micro-g, timed in a recording that starts at
the calibration's date.

A :class:`Plant` says what happens to a unit over time: offsets or gains drifting at a constant rate (which may
reverse), or a unit that differs from its type from the start (an offset, a gain, a temperature coefficient).
:func:`write_fleet` writes ``versions`` passports of each of ``units`` random units of seed 000's type
(:func:`pipeline.simulate.unit.random_unit`), ``interval_days`` apart.
"""

from __future__ import annotations

import hashlib
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from pipeline.positions import AXES
from pipeline.simulate.unit import UnitTruth, random_unit

Vec3 = tuple[float, float, float]
_ZERO: Vec3 = (0.0, 0.0, 0.0)
#: calibration temperatures of the simulated passports (C) and their verification temperatures
PLATEAU_TEMPS_C = (-40.0, 20.0, 70.0)
VERIFY_TEMPS_C = (-10.0, 20.0, 45.0)
DAYS_PER_YEAR = 365.25


@dataclass(frozen=True)
class PassportNoise:
    """Standard uncertainties of a simulated passport (1 sigma): ``u0_v`` of each U0 (V), ``k_v_per_g`` of each K
    (V/g); a thermal coefficient of power n has ``sigma / (base * span_c**n)`` (alpha: base 1 V, beta and gamma:
    the constant they are relative to), as a fit over a ``span_c`` (C) wide band gives. ``dg_g``: spread of the
    verification rows' |dg| after compensation (g)."""

    u0_v: float = 1.2e-7
    k_v_per_g: float = 2.0e-7
    span_c: float = 45.0
    dg_g: float = 5e-6


@dataclass(frozen=True)
class Plant:
    """What is planted in one unit's history (all zero: a unit like the rest of its type, whose constants hold).

    Drifts, from the unit's first calibration on: ``u0_rate_v_per_year`` (V/year per axis),
    ``gain_rate_rel_per_year`` (relative change of Kii per year); with ``reverse_after_days`` the drift runs the
    other way from that day on (the constant comes back). Differences from the type, at every calibration:
    ``u0_offset_v`` (V), ``gain_offset_rel`` (relative, on Kii), ``alpha_offset_v_per_c`` (V/C, on the first-order
    offset temperature coefficient), ``beta_offset_per_c`` (1/C, on the first-order gain temperature coefficient).
    """

    u0_rate_v_per_year: Vec3 = _ZERO
    gain_rate_rel_per_year: Vec3 = _ZERO
    reverse_after_days: float | None = None
    u0_offset_v: Vec3 = _ZERO
    gain_offset_rel: Vec3 = _ZERO
    alpha_offset_v_per_c: Vec3 = _ZERO
    beta_offset_per_c: Vec3 = _ZERO

    def elapsed_years(self, days: float) -> float:
        """The drift's effective time (years) ``days`` after the first calibration: the days themselves, or, after
        a reversal, back down from the reversal day."""
        if self.reverse_after_days is not None and days > self.reverse_after_days:
            days = 2.0 * self.reverse_after_days - days
        return days / DAYS_PER_YEAR


def truth_at(base: UnitTruth, plant: Plant, days: float) -> UnitTruth:
    """The unit ``base`` as it is ``days`` after its first calibration, with ``plant`` applied (see :class:`Plant`):
    offsets and gains moved at T0 (their temperature dependence kept: a gain change scales every K_ii coefficient),
    the first-order coefficients of an outlier type added."""
    years = plant.elapsed_years(days)
    k = base.k_coef.copy()
    u = base.u0_coef.copy()
    scale = 1.0 + np.asarray(plant.gain_offset_rel) + np.asarray(plant.gain_rate_rel_per_year) * years
    idx = np.arange(3)
    k[:, idx, idx] *= scale
    u[0] += np.asarray(plant.u0_offset_v) + np.asarray(plant.u0_rate_v_per_year) * years
    if u.shape[0] > 1:
        u[1] += np.asarray(plant.alpha_offset_v_per_c)
        k[1, idx, idx] += np.asarray(plant.beta_offset_per_c) * k[0, idx, idx]
    return UnitTruth(base.normal_temp_c, k, u, label=base.label)


def simulated_passport(
    truth: UnitTruth,
    unit: str,
    recorded: datetime,
    rng: np.random.Generator,
    *,
    noise: PassportNoise = PassportNoise(),
    tolerances_g: tuple[float, float] = (3e-4, 1e-3),
) -> dict:
    """The passport content (before the registry adds version, parent, creation time and provenance) that a
    calibration of ``truth`` recorded from ``recorded`` (UTC) would give: measured values the truth plus normal
    errors of ``noise``, which its ``uncertainty`` states. ``tolerances_g``: the verification limits at T0 and over
    the range (g)."""
    t0 = truth.normal_temp_c
    k_truth, u_truth = truth.constants_at(np.array([t0, *PLATEAU_TEMPS_C]))
    k0 = k_truth[0] + rng.normal(0.0, noise.k_v_per_g, (3, 3))
    u0 = u_truth[0] + rng.normal(0.0, noise.u0_v, 3)
    rel = truth.relative_coefficients()
    order = int(rel["order"])
    base_k = np.abs(truth.k_coef[0])
    thermal: dict = {"kind": "polynomial", "order": order}
    thermal_sigma: dict = {"kind": "polynomial", "order": order}
    for group in ("alpha", "beta", "gamma"):
        thermal[group], thermal_sigma[group] = {}, {}
        for key, coefs in rel[group].items():
            if group == "alpha":
                base, sigma0 = 1.0, noise.u0_v
            else:
                i, j = AXES.index(key[0]), AXES.index(key[1])
                base, sigma0 = float(base_k[i, j]), noise.k_v_per_g
            sig = [sigma0 / (base * noise.span_c ** (n + 1)) for n in range(order)]
            thermal_sigma[group][key] = sig
            thermal[group][key] = [float(c + rng.normal(0.0, s)) for c, s in zip(coefs, sig)]
    per_plateau, plateau_sigma = [], []
    for p, temp in enumerate(PLATEAU_TEMPS_C):
        s_k, s_u = np.sqrt(3.0) * noise.k_v_per_g, np.sqrt(3.0) * noise.u0_v  # one plateau of three
        per_plateau.append(
            {
                "temp_c": temp,
                "run_id": f"sim-{unit}",
                "plateau": p,
                "K": (k_truth[p + 1] + rng.normal(0.0, s_k, (3, 3))).tolist(),
                "U0": (u_truth[p + 1] + rng.normal(0.0, s_u, 3)).tolist(),
                "positions": ["TP1", "TP2", "TP3", "TP4", "TP5", "TP6"],
                "method": "closed_form",
                "residual_rms_v": None,
            }
        )
        plateau_sigma.append(
            {
                "temp_c": temp,
                "run_id": f"sim-{unit}",
                "plateau": p,
                "K": np.full((3, 3), s_k).tolist(),
                "U0": [s_u] * 3,
            }
        )
    start_ns = int(recorded.timestamp() * 1e9)
    rows = []
    for v, temp in enumerate(VERIFY_TEMPS_C):
        limit = tolerances_g[0] if abs(temp - t0) <= 3.0 else tolerances_g[1]
        for k in range(6):
            t_ns = start_ns + int((3 + v * 4 + k * 0.1) * 3600e9)
            dg = float(rng.normal(0.0, noise.dg_g))
            rows.append(
                {
                    "temp_c": temp,
                    "position": f"VP{k + 1}",
                    "run_id": f"sim-{unit}",
                    "t_start_ns": t_ns,
                    "t_end_ns": t_ns + 300_000_000_000,
                    "dg_uncompensated_g": float(rng.normal(0.0, 2e-3)) if temp != t0 else dg,
                    "dg_method1_g": dg,
                    "dg_method2_g": dg + float(rng.normal(0.0, noise.dg_g)),
                    "dg_method2_simplified_g": dg + float(rng.normal(0.0, 10 * noise.dg_g)),
                    "tolerance_g": limit,
                    "passed": abs(dg) <= limit,
                    "plateau": 3 + v,
                }
            )
    return {
        "schema": "thermocal.passport/1",
        "unit": unit,
        "version": None,
        "parent_sha256": None,
        "created_utc": None,
        "normal_temp_c": float(t0),
        "g_local_mps2": 9.80665,
        "output_unit": "V",
        "method": "tilt_six_position",
        "coefficients": {"K": k0.tolist(), "U0": u0.tolist()},
        "per_plateau": per_plateau,
        "thermal_model": thermal,
        "plateaus": [
            {"temp_c": t, "positions": p["positions"], "run_id": f"sim-{unit}"}
            for t, p in zip(PLATEAU_TEMPS_C, per_plateau)
        ],
        "verification": rows,
        "status": "pass" if all(r["passed"] for r in rows) else "fail",
        "notes": [],
        "valid_temp_c": [PLATEAU_TEMPS_C[0], PLATEAU_TEMPS_C[-1]],
        "uncertainty": {
            "coefficients": {"K": np.full((3, 3), noise.k_v_per_g).tolist(), "U0": [noise.u0_v] * 3},
            "per_plateau": plateau_sigma,
            "thermal_model": thermal_sigma,
            "basis": {"level": "standard uncertainty (1 sigma)", "simulated": "pipeline.simulate.history"},
        },
    }


@dataclass(frozen=True)
class FleetSpec:
    """A simulated fleet history: ``units`` units (serials ``serial_format.format(k)`` for k = 1..units, unit
    seeds ``unit_seed0 + k``), each calibrated ``versions`` times ``interval_days`` apart from ``first_utc`` (each
    unit starts ``stagger_days * (k - 1)`` later, so the fleet's calibrations spread over the calendar); ``seed``
    drives the measurement errors; ``plants`` by serial."""

    units: int = 20
    versions: int = 4
    interval_days: float = 120.0
    first_utc: str = "2025-01-06T08:00:00Z"
    stagger_days: float = 1.0
    seed: int = 0
    unit_seed0: int = 5000
    serial_format: str = "AU-{:04d}"
    plants: Mapping[str, Plant] = field(default_factory=dict)
    noise: PassportNoise = PassportNoise()

    def serials(self) -> list[str]:
        return [self.serial_format.format(k) for k in range(1, self.units + 1)]


def fleet_passports(spec: FleetSpec, only: Collection[str] | None = None) -> Iterable[tuple[str, int, dict]]:
    """(serial, k-th calibration from 0, passport content) of every calibration of ``spec`` (of the serials in
    ``only``), unit by unit, oldest first."""
    start = datetime.fromisoformat(spec.first_utc.replace("Z", "+00:00"))
    for k, serial in enumerate(spec.serials(), start=1):
        if only is not None and serial not in only:
            continue
        base = random_unit(spec.unit_seed0 + k)
        plant = spec.plants.get(serial, Plant())
        rng = np.random.default_rng([spec.seed, k])
        first = start + timedelta(days=spec.stagger_days * (k - 1))
        for n in range(spec.versions):
            days = n * spec.interval_days
            truth = truth_at(base, plant, days)
            yield serial, n, simulated_passport(truth, serial, first + timedelta(days=days), rng, noise=spec.noise)


def write_fleet(registry_root: str | Path, spec: FleetSpec, only: Collection[str] | None = None) -> dict[str, int]:
    """Publish every passport of :func:`fleet_passports` (of the serials in ``only``) into the registry at
    ``registry_root`` (signed with the station's key, as a calibration would be). Returns the number of versions
    per serial."""
    from pipeline.passport.registry import Registry

    registry = Registry(registry_root)
    written: dict[str, int] = {}
    for serial, n, doc in fleet_passports(spec, only):
        day = datetime.fromtimestamp(doc["verification"][0]["t_start_ns"] / 1e9, UTC).strftime("%Y-%m-%d")
        digest = hashlib.sha256(f"{spec.seed}:{serial}:{n}:{day}".encode()).hexdigest()
        registry.publish(
            doc,
            inputs=[{"path": f"simulated/{serial}/{day}.mcap", "sha256": digest}],
            settings={"simulated": "pipeline.simulate.history"},
            code_version="simulated",
        )
        written[serial] = written.get(serial, 0) + 1
    return written
