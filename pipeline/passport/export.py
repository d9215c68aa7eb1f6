"""A passport in the formats other software loads (``thermocal export``): PX4 and ArduPilot parameter files, CSV.

Flight software corrects its accelerometer for temperature with a bias-only cubic per axis, in m/s^2, along the
sensor's own axes (here the unit's axes x, y, z), evaluated at the clamped temperature:

- **PX4** (``TemperatureCompensation``, parameters ``TC_A0_*``): ``offset_i = X0_i + X1_i dT + X2_i dT^2 + X3_i
  dT^3`` with ``dT = clamp(T, TMIN, TMAX) - TREF``; the corrected reading is ``raw - offset - CAL_ACC0 offset``.
  Written as a QGroundControl parameter file (``vehicle component name value type``, tab separated).
- **ArduPilot** (``AP_InertialSensor_tempcal``, parameters ``INS_TCAL1_*``): a polynomial without constant term
  about the fixed reference 35 C, ``p(x) = (ACC1 x + ACC2 x^2 + ACC3 x^3) * 1e-6``, and the corrected reading
  ``v - p(T - 35) + p(T_cal - 35)``, T and T_cal (``INS_ACC1_CALTEMP``, the temperature of the vehicle's own
  accelerometer calibration) clamped to [TMIN, TMAX]. The raw reading assumed here is calibrated at the passport's
  T0, so ``INS_ACC1_CALTEMP`` is written as T0 (left at ArduPilot's default -300 C it would clamp to TMIN and
  shift every reading by the bias change between TMIN and T0); a new accelerometer calibration on the vehicle
  sets it again to its own temperature. Written as ``NAME VALUE`` lines (the form ArduPilot's own tempcal tool
  writes; ``#`` lines are comments).

What is exported: the reading those programs call raw is the unit's output with the passport's normal-temperature
constants applied, ``r = g K0^-1 (U - U0(T0))`` (m/s^2, the vehicle's own accelerometer calibration plays that part).
With ``U = K(T) a + U0(T)`` its error is ``g K0^-1 (U0(T) - U0(T0))`` (the bias, held by the format) plus
``g K0^-1 (K(T) - K0) a`` (the scale-factor and cross-axis temperature terms, which a bias-only format cannot hold:
they depend on the orientation). The residual error that leaves over the passport's ``valid_temp_c`` is computed on
a 0.1 C grid: the bias cubic's own fit error (zero for a polynomial model of order <= 3, non-zero for a piecewise
model), and the largest error of the unheld terms for |a| = 1 g (the spectral norm of ``K0^-1 dK(T)``, and per
axis the norm of its row).

CSV holds everything: the normal-temperature constants, the thermal model's coefficients and their standard
uncertainties, one row per number.

Every file states the passport's status and approval (``pipeline.passport.registry.VersionState``): in its
comment header (PX4, ArduPilot) or as rows ``status`` and ``approval`` (CSV).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import ThermocalError
from pipeline.passport.document import failed_verification, load_model
from pipeline.passport.significance import sigma_of
from pipeline.passport.text import output_unit_of, per

FORMATS = ("px4", "ardupilot", "csv")
ARDUPILOT_TREF_C = 35.0  # fixed reference temperature of ArduPilot's tempcal (not a parameter)
ARDUPILOT_SCALE = 1.0e6  # ArduPilot stores the coefficients times 1e6
ARDUPILOT_TEMP_RANGE_C = (-70.0, 80.0)  # the range INS_TCALn_TMIN/TMAX accept
GRID_STEP_C = 0.1
AXES = "xyz"


@dataclass
class Export:
    """One exported file and what it says about itself. ``text``: the file's content; ``not_held``: what of the
    passport the format cannot hold, one sentence each; ``residual``: the error that leaves over ``valid_temp_c``
    (micro-g and m/s^2); ``params``: the exported parameters by name (parameter formats)."""

    format: str
    unit: str
    version: int | None
    valid_temp_c: tuple[float, float]
    text: str
    not_held: list[str] = field(default_factory=list)
    residual: dict = field(default_factory=dict)
    params: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict:
        return {
            "format": self.format,
            "unit": self.unit,
            "version": self.version,
            "valid_temp_c": list(self.valid_temp_c),
            "not_held": self.not_held,
            "residual": self.residual,
            "params": self.params,
        }


def valid_range_c(passport: dict) -> tuple[float, float]:
    """The passport's ``valid_temp_c``; for an older passport without it, the span of its calibration plateaus."""
    v = passport.get("valid_temp_c")
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v):
        return float(v[0]), float(v[1])
    temps = [p.get("temp_c") for p in passport.get("per_plateau") or [] if isinstance(p.get("temp_c"), (int, float))]
    if temps:
        return float(min(temps)), float(max(temps))
    t0 = float(passport.get("normal_temp_c", 20.0))
    return t0, t0


def thermal_errors(passport: dict, temps_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At ``temps_c`` (n,): the bias ``g K0^-1 (U0(T) - U0(T0))`` (n, 3) in m/s^2 and the unheld relative part
    ``K0^-1 (K(T) - K0)`` (n, 3, 3) (dimensionless: error in g per g of specific force)."""
    model = load_model(passport)
    g = float(passport.get("g_local_mps2", 9.80665))
    dK, dU0 = model.deltas(np.asarray(temps_c, dtype=float))
    K0inv = np.linalg.inv(np.asarray(model.K0, dtype=float))
    bias = g * np.einsum("ij,nj->ni", K0inv, dU0)
    rel = np.einsum("ij,njk->nik", K0inv, dK)
    return bias, rel


def _grid(lo: float, hi: float) -> np.ndarray:
    n = max(2, int(round((hi - lo) / GRID_STEP_C)) + 1)
    return np.linspace(lo, hi, n)


def _cubic_fit(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least-squares cubic (coefficients of x^0..x^3, per column of y (n, 3)): (4, 3). Fewer distinct points than
    four give the lower-order fit (higher coefficients 0)."""
    deg = min(3, len(np.unique(np.round(x, 6))) - 1)
    A = x[:, None] ** np.arange(deg + 1)[None, :]
    coef = np.zeros((4, y.shape[1]))
    if deg >= 0:
        coef[: deg + 1], *_ = np.linalg.lstsq(A, y, rcond=None)
    return coef


def _poly(coef: np.ndarray, x: np.ndarray) -> np.ndarray:
    return (x[:, None] ** np.arange(len(coef))[None, :]) @ coef


def _residual(bias: np.ndarray, held: np.ndarray, rel: np.ndarray, g: float, temps: np.ndarray) -> dict:
    """The error left over the grid: bias fit error per axis, unheld scale/cross-axis error (worst orientation)."""
    fit_err = np.abs(held - bias)  # (n, 3) m/s^2
    row = np.linalg.norm(rel, axis=2)  # (n, 3): per axis, worst |a| = 1 g
    spec = np.linalg.norm(rel, ord=2, axis=(1, 2))  # (n,)
    worst_t = float(temps[int(np.argmax(spec))]) if len(temps) else None
    ug = 1e6 / g
    return {
        "bias_fit_max_mps2": fit_err.max(axis=0).tolist(),
        "bias_fit_max_ug": (fit_err.max(axis=0) * ug).tolist(),
        "unheld_scale_cross_max_ug": (row.max(axis=0) * 1e6).tolist(),
        "unheld_scale_cross_max_mps2": (row.max(axis=0) * g).tolist(),
        "total_worst_ug": float(((spec * g)[:, None] + fit_err).max() * ug),
        "total_worst_mps2": float(((spec * g)[:, None] + fit_err).max()),
        "worst_at_temp_c": worst_t,
        "bias_range_ug": (np.ptp(bias, axis=0) * ug).tolist(),
        "grid_step_c": GRID_STEP_C,
    }


def _not_held(passport: dict, extra: list[str]) -> list[str]:
    tm = passport.get("thermal_model") or {}
    out = [
        "the scale-factor temperature terms (beta) and the cross-axis temperature terms (gamma): a bias-only "
        "polynomial cannot hold terms that scale with the specific force (the error they leave is the residual's "
        "unheld scale/cross-axis part)",
        "the normal-temperature gains, cross-axis sensitivities and offsets (K, U0 at T0): the vehicle's own "
        "accelerometer calibration holds those",
        "the standard uncertainties of the constants",
    ]
    if tm.get("kind") == "piecewise_linear":
        out.append(
            "the piecewise-linear model itself: exported as the least-squares cubic through it over "
            "valid_temp_c (its fit error is in residual, bias_fit_max_ug)"
        )
    elif int(tm.get("order", 0) or 0) > 3:
        out.append("polynomial terms beyond the cubic")
    if passport.get("rate_terms"):
        out.append("the temperature-rate terms of the differential method")
    return out + extra


def export_px4(passport: dict, state=None) -> Export:
    """PX4 ``TC_A0_*`` parameters (accelerometer instance 0): TREF the passport's normal temperature, TMIN/TMAX its
    valid range, X0..X3 the offset cubic in m/s^2 per C^n. ``TC_A0_ID`` must be set to the accelerometer's device
    id on the vehicle (``CAL_ACC0_ID``); it is written as 0."""
    lo, hi = valid_range_c(passport)
    tref = float(passport.get("normal_temp_c", 20.0))
    temps = _grid(lo, hi)
    bias, rel = thermal_errors(passport, temps)
    coef = _cubic_fit(temps - tref, bias).astype(np.float32)  # PX4 parameters are float32
    held = _poly(coef.astype(np.float64), temps - tref)
    g = float(passport.get("g_local_mps2", 9.80665))
    params: dict[str, float] = {"TC_A_ENABLE": 1, "TC_A0_ID": 0, "TC_A0_TREF": tref, "TC_A0_TMIN": lo, "TC_A0_TMAX": hi}
    for n in range(4):
        for i in range(3):
            params[f"TC_A0_X{n}_{i}"] = float(coef[n, i])
    residual = _residual(bias, held, rel, g, temps)
    not_held = _not_held(
        passport,
        ["TC_A0_ID (the accelerometer's device id on the vehicle): written as 0, set it to CAL_ACC0_ID before use"],
    )
    ints = {"TC_A_ENABLE", "TC_A0_ID"}
    lines = _header(
        passport, "PX4 thermal compensation (TC_A0_*), QGroundControl parameter file", lo, hi, not_held, residual, state
    )
    lines += ["# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
    for name, value in params.items():
        lines.append(f"1\t1\t{name}\t{int(value) if name in ints else _f32(value)}\t{6 if name in ints else 9}")
    return Export(
        "px4",
        passport.get("unit", ""),
        passport.get("version"),
        (lo, hi),
        "\n".join(lines) + "\n",
        not_held,
        residual,
        params,
    )


def export_ardupilot(passport: dict, state=None) -> Export:
    """ArduPilot ``INS_TCAL1_*`` parameters (first IMU): TMIN/TMAX the valid range (clipped to -70..80 C),
    ACC1..ACC3 the cubic about 35 C without constant term, times 1e6, and ``INS_ACC1_CALTEMP`` = T0: the
    correction is relative to the temperature of the accelerometer calibration the raw reading carries, here the
    passport's normal-temperature constants."""
    lo, hi = valid_range_c(passport)
    extra = []
    a_lo, a_hi = max(lo, ARDUPILOT_TEMP_RANGE_C[0]), min(hi, ARDUPILOT_TEMP_RANGE_C[1])
    if (a_lo, a_hi) != (lo, hi):
        extra.append(
            f"the part of valid_temp_c outside ArduPilot's -70..80 C (TMIN/TMAX clipped to {a_lo:g}..{a_hi:g} C)"
        )
    temps = _grid(a_lo, a_hi)
    bias, rel = thermal_errors(passport, temps)
    q = _cubic_fit(temps - ARDUPILOT_TREF_C, bias)
    coef = np.round(q[1:] * ARDUPILOT_SCALE, 9)  # ACC1..ACC3 as written
    # the correction the vehicle applies: p(T-35) - p(T_cal-35); its bias part at the calibration temperature
    # cancels, so compare the changes of the bias
    p = np.vstack([np.zeros(3), coef / ARDUPILOT_SCALE])
    held = _poly(p, temps - ARDUPILOT_TREF_C)
    g = float(passport.get("g_local_mps2", 9.80665))
    t0 = float(passport.get("normal_temp_c", 20.0))
    b0, _ = thermal_errors(passport, np.array([min(max(t0, a_lo), a_hi)]))
    held0 = _poly(p, np.array([min(max(t0, a_lo), a_hi)]) - ARDUPILOT_TREF_C)
    residual = _residual(bias - b0, held - held0, rel, g, temps)
    params: dict[str, float] = {
        "INS_TCAL1_ENABLE": 1,
        "INS_TCAL1_TMIN": a_lo,
        "INS_TCAL1_TMAX": a_hi,
        "INS_ACC1_CALTEMP": t0,
    }
    for n in range(3):
        for i, ax in enumerate("XYZ"):
            params[f"INS_TCAL1_ACC{n + 1}_{ax}"] = float(coef[n, i])
    not_held = _not_held(
        passport,
        extra
        + ["gyroscope terms (INS_TCAL1_GYR*): the unit has no gyroscopes; not written, so a vehicle's own values stay"],
    )
    lines = _header(
        passport,
        "ArduPilot IMU temperature calibration (INS_TCAL1_*), parameter file",
        a_lo,
        a_hi,
        not_held,
        residual,
        state,
    )
    lines.append(
        f"# INS_ACC1_CALTEMP = T0 ({t0:g} C): the raw reading assumed carries the passport's "
        "normal-temperature constants; a new accelerometer calibration on the vehicle resets it"
    )
    lines += [f"{name} {int(value) if name == 'INS_TCAL1_ENABLE' else _num(value)}" for name, value in params.items()]
    return Export(
        "ardupilot",
        passport.get("unit", ""),
        passport.get("version"),
        (a_lo, a_hi),
        "\n".join(lines) + "\n",
        not_held,
        residual,
        params,
    )


def export_csv(passport: dict, state=None) -> Export:
    """Every number of the passport's model, one row each: ``quantity, key, order, t_lo_c, t_hi_c, value, unit,
    std_uncertainty`` (the uncertainty empty where the passport records none)."""
    lo, hi = valid_range_c(passport)
    rows = [
        ["quantity", "key", "order", "t_lo_c", "t_hi_c", "value", "unit", "std_uncertainty"],
        ["unit", passport.get("unit", ""), "", "", "", "", "", ""],
        ["version", "", "", "", "", passport.get("version", ""), "", ""],
        ["status", "", "", "", "", passport.get("status", ""), "", ""],
        ["approval", "", "", "", "", _approval(passport, state), "", ""],
        ["normal_temp_c", "", "", "", "", passport.get("normal_temp_c", ""), "C", ""],
        ["g_local_mps2", "", "", "", "", passport.get("g_local_mps2", ""), "m/s^2", ""],
        ["valid_temp_c", "", "", lo, hi, "", "C", ""],
    ]
    c = passport.get("coefficients") or {}
    u = output_unit_of(passport)
    for i in range(3):
        for j in range(3):
            key = AXES[i] + AXES[j]
            rows.append(["K", key, "", "", "", c["K"][i][j], per(u, "g"), sigma_of(passport, f"K.{key}")])
    for i in range(3):
        rows.append(["U0", AXES[i], "", "", "", c["U0"][i], u, sigma_of(passport, f"U0.{AXES[i]}")])
    tm = passport.get("thermal_model") or {}
    units = {"alpha": per(u, "C^{n}"), "beta": "1/C^{n}", "gamma": "1/C^{n}"}
    if tm.get("kind") == "polynomial":
        for group in ("alpha", "beta", "gamma"):
            for key, values in sorted((tm.get(group) or {}).items()):
                for n, v in enumerate(values, start=1):
                    rows.append(
                        [group, key, n, "", "", v, units[group].format(n=n), sigma_of(passport, f"{group}.{key}[{n}]")]
                    )
    else:
        for s, seg in enumerate(tm.get("segments") or []):
            for group in ("alpha", "beta", "gamma"):
                for key, v in sorted((seg.get(group) or {}).items()):
                    rows.append(
                        [
                            group,
                            key,
                            1,
                            seg["t_lo_c"],
                            seg["t_hi_c"],
                            v,
                            units[group].format(n=1),
                            sigma_of(passport, f"segments[{s}].{group}.{key}"),
                        ]
                    )
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows([["" if x is None else x for x in r] for r in rows])
    return Export("csv", passport.get("unit", ""), passport.get("version"), (lo, hi), buf.getvalue(), [], {}, {})


def export_passport(passport: dict, fmt: str, state=None) -> Export:
    """The passport in ``fmt``: ``px4``, ``ardupilot`` or ``csv``. ``state``: its
    :class:`pipeline.passport.registry.VersionState` when read from a registry (status and approval stated in the
    file)."""
    if fmt not in FORMATS:
        raise ThermocalError(f"unknown export format {fmt!r} ({', '.join(FORMATS)})", where="--format")
    try:
        return {"px4": export_px4, "ardupilot": export_ardupilot, "csv": export_csv}[fmt](passport, state)
    except (KeyError, TypeError, ValueError, np.linalg.LinAlgError) as e:
        raise ThermocalError(f"the passport cannot be exported as {fmt} ({type(e).__name__}: {e})") from None


def _f32(value: float) -> str:
    """A float32 parameter as text that reads back to the same float32."""
    return repr(float(np.float32(value)))


def _num(value: float) -> str:
    return f"{value:.9f}".rstrip("0").rstrip(".") if value != 0 else "0"


def _approval(passport: dict, state) -> str:
    """The approval as the file states it: from the registry's records, or unknown for a passport file alone."""
    return state.approval_text() if state is not None else "approval unknown (not read from a registry)"


def _header(
    passport: dict, what: str, lo: float, hi: float, not_held: list[str], residual: dict, state=None
) -> list[str]:
    unit, version = passport.get("unit", "?"), passport.get("version")
    lines = [
        f"# {what}",
        f"# thermocal export of {unit} passport v{version} (content_sha256 "
        f"{str(passport.get('content_sha256', ''))[:16]}), method {passport.get('method', 'tilt_six_position')}",
        f"# status {passport.get('status')}; {_approval(passport, state)}",
    ]
    if passport.get("status") == "fail":
        lines.append(f"# WARNING: {failed_verification('this passport')}; review before loading it")
    lines += [
        f"# valid temperature range {lo:g} .. {hi:g} C; accelerometer offsets in m/s^2 along the unit's x, y, z",
        "# raw reading assumed: the unit's output with the passport's normal-temperature constants applied",
        "# not held by this format:",
    ]
    lines += [f"#   - {t}" for t in not_held]
    if residual:
        lines.append("# residual error over the valid range (computed on a 0.1 C grid):")
        lines.append(
            "#   bias cubic fit error, max per axis x y z: "
            + " ".join(f"{v:.3g}" for v in residual["bias_fit_max_ug"])
            + " micro-g"
        )
        lines.append(
            "#   unheld scale/cross-axis terms, |a| = 1 g, max per axis x y z: "
            + " ".join(f"{v:.3g}" for v in residual["unheld_scale_cross_max_ug"])
            + " micro-g"
        )
        lines.append(
            f"#   worst total: {residual['total_worst_ug']:.3g} micro-g ({residual['total_worst_mps2']:.3g} m/s^2)"
        )
    return lines
