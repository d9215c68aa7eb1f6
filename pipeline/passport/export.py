"""A passport in the formats other software loads (``thermocal export``): PX4 and ArduPilot parameter files, CSV.

Flight software corrects its accelerometer for temperature with a bias-only cubic per axis, in m/s^2, evaluated at
the temperature the IMU reports and clamped to a range; :mod:`pipeline.passport.firmware` has each firmware's
arithmetic, parameter names, rotations and parameter-file forms. The files here are written for the vehicle as it
is: its own accelerometer calibration holds an offset and a gain per axis (no cross-axis terms), so the reading a
firmware corrects is, per axis i of the firmware's frame, ``r_i = g (U_i - U0_i(T0)) / K0_ii`` (m/s^2; g is the
firmwares' 9.80665, to which their accelerometer calibration scales 1 g, not the passport's local gravity), and its
temperature error is

- the bias ``b_i(T) = g (U0_i(T) - U0_i(T0)) / K0_ii``, held by the format (its cubic fit error is stated), plus
- ``g (K_i.(T) - K0_i.) a / K0_ii``, the scale-factor and cross-axis temperature terms (beta, gamma), which a
  bias-only format cannot hold (they depend on the orientation), plus
- ``g (K0_i. / K0_ii - e_i) a``, the cross-axis terms at T0, which the vehicle's per-axis calibration cannot hold.

With ``--rotation R`` (``v_fw = R v_unit``) the passport's constants are taken into the firmware's axes first
(``R K R^T``, ``R U0``). The residual stated over the passport's ``valid_temp_c`` (0.1 C grid, |a| = 1 g, per axis):
the bias fit error, the unheld temperature terms, the cross-axis terms at T0 and, for PX4, its 1 C update step (the
largest change of the offsets over 1 C, the lag PX4 allows before it recomputes them); the largest change over 1 C
is also the cost of each 1 C by which the IMU's die temperature, which the firmware reads, differs from the unit's
thermosensor, against which the model was fitted.

- **PX4** (``TC_A<k>_*``, a QGroundControl parameter file): TREF = T0, TMIN/TMAX = ``valid_temp_c``, X0..X3 the
  offset cubic in dT = T - TREF; ``TC_A_ENABLE`` 1 and ``TC_A<k>_ID`` the accelerometer's device id
  (``--px4-device-id``; without it 0, which matches no accelerometer: the command warns).
- **ArduPilot** (``INS_TCAL<n>_*``, ``NAME VALUE`` lines as ArduPilot's own tempcal tool writes them): the cubic
  about 35 C without constant term, times 1e6, TMIN/TMAX the valid range within -70..80 C. The correction is
  relative to ``INS_ACC<n>_CALTEMP``, which the vehicle's own accelerometer calibration writes: it is written (as
  T0) only with ``--set-caltemp``.

Every parameter file states in its comment header the passport's status and approval, the steps left to the user
(loading order, reboots, the device id, the vehicle's accelerometer calibration and at which temperature), the
temperature the model was fitted against and what the firmware reads, the axes and how to map them, what the format
cannot hold and the residual. CSV holds everything: the normal-temperature constants, the thermal model's
coefficients and their standard uncertainties, one row per number.

``--compare``: :func:`compare_params` evaluates a vehicle's existing PX4 or ArduPilot parameters (as saved by
QGroundControl or MAVProxy) the way the firmware does and states how far they are from the passport, per axis.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import ThermocalError
from pipeline.passport.document import failed_verification, load_model, load_passport, output_unit_of
from pipeline.passport.firmware import (
    ARDUPILOT_DEFAULTS,
    ARDUPILOT_SCALE,
    ARDUPILOT_TEMP_RANGE_C,
    ARDUPILOT_TREF_C,
    FIRMWARE_G_MPS2,
    PX4_SLOTS,
    PX4_UPDATE_STEP_C,
    QGC_FLOAT,
    QGC_INT8,
    QGC_INT32,
    ardupilot_correction,
    ardupilot_imu,
    as_uint32,
    detect_firmware,
    px4_int32,
    px4_matching_slot,
    px4_offsets,
    px4_slot,
    rotation_matrix,
)
from pipeline.passport.significance import sigma_of
from pipeline.passport.text import per
from pipeline.run import PX4_DEVICE_ID_KEY, px4_device_id

FORMATS = ("px4", "ardupilot", "csv")
GRID_STEP_C = 0.1
AXES = "xyz"
FIRMWARE_NAMES = {"px4": "PX4", "ardupilot": "ArduPilot"}
#: where each firmware applies its correction (the frame of the exported coefficients)
FIRMWARE_FRAME = {
    "px4": "after the driver's sensor rotation and before the board rotation (SENS_BOARD_ROT, or CAL_ACC<n>_ROT for "
    "an external sensor)",
    "ardupilot": "after the IMU's sensor rotation and before the board rotation (AHRS_ORIENTATION)",
}
FIRMWARE_TEMPERATURE = {
    "px4": "the temperature the accelerometer reports (its die temperature, sensor_accel.temperature)",
    "ardupilot": "the temperature the IMU reports (its die temperature)",
}


@dataclass
class ExportOptions:
    """What the user says about the vehicle. ``px4_device_id``: the accelerometer's device id (PX4,
    ``TC_A<k>_ID``); ``instance``: PX4's slot k of ``TC_A<k>_*`` (0..3, default 0) or ArduPilot's IMU n of
    ``INS_TCAL<n>_*`` (1..5, default 1); ``set_caltemp``: ArduPilot, write ``INS_ACC<n>_CALTEMP`` = T0;
    ``rotation``: ``--rotation`` (:func:`pipeline.passport.firmware.rotation_matrix`); ``qgc``: ArduPilot, write
    QGroundControl's tab-separated form (``SYS COMP NAME VALUE TYPE``) instead of ``NAME VALUE`` lines."""

    px4_device_id: int | None = None
    instance: int | None = None
    set_caltemp: bool = False
    rotation: str | None = None
    qgc: bool = False

    def check(self, fmt: str) -> None:
        """Options that do not go with ``fmt`` are a usage error."""
        wrong = [
            (self.px4_device_id is not None and fmt != "px4", "--px4-device-id goes with --format px4"),
            (self.set_caltemp and fmt != "ardupilot", "--set-caltemp goes with --format ardupilot"),
            (self.qgc and fmt != "ardupilot", "--qgc goes with --format ardupilot (a PX4 file is QGroundControl's)"),
            (self.instance is not None and fmt == "csv", "--instance goes with --format px4 or ardupilot"),
            (self.rotation is not None and fmt == "csv", "--rotation goes with --format px4 or ardupilot"),
        ]
        for bad, text in wrong:
            if bad:
                raise ThermocalError(text, where="--format")
        if self.instance is not None and fmt in FIRMWARE_NAMES:
            try:
                px4_slot(self.instance) if fmt == "px4" else ardupilot_imu(self.instance)
            except ThermocalError as e:
                raise ThermocalError(e.message, where="--instance") from None
        if self.px4_device_id is not None and not 0 < self.px4_device_id < 1 << 32:
            raise ThermocalError(
                f"a PX4 device id is a positive 32-bit number, not {self.px4_device_id}", where="--px4-device-id"
            )


@dataclass
class Export:
    """One exported file and what it says about itself. ``text``: the file's content; ``not_held``: what of the
    passport the format cannot hold, one sentence each; ``residual``: the error that leaves over ``valid_temp_c``
    (micro-g and m/s^2, per axis); ``params``: the exported parameters by name (parameter formats); ``steps``: what
    the user must still do on the vehicle, in order; ``notes``: the temperature and the axes, one sentence each;
    ``warnings``: one line each for stderr (e.g. a PX4 file without a device id); ``order``: one line for stderr,
    the loading order and the steps after it (the device id, reboots, the vehicle's accelerometer calibration)."""

    format: str
    unit: str
    version: int | None
    valid_temp_c: tuple[float, float]
    text: str
    not_held: list[str] = field(default_factory=list)
    residual: dict = field(default_factory=dict)
    params: dict[str, float] = field(default_factory=dict)
    steps: list[str] = field(default_factory=list)
    notes: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    order: str | None = None
    rotation: list[list[float]] | None = None

    def summary(self) -> dict:
        return {
            "format": self.format,
            "unit": self.unit,
            "version": self.version,
            "valid_temp_c": list(self.valid_temp_c),
            "not_held": self.not_held,
            "residual": self.residual,
            "params": self.params,
            "steps": self.steps,
            "notes": self.notes,
            "warnings": self.warnings,
            "rotation": self.rotation,
            "loading_order": self.order,
        }

    def summary_text(self, out: str, used: str) -> str:
        """The command's summary after writing the file to ``out``: what, the steps left, temperature, axes and
        the residual (``used``: which passport, e.g. ``AU-0001 v2 (status pass, approved by ...)``)."""
        lines = [f"wrote {out} ({self.format}, {used})"]
        if self.steps:
            lines.append("steps left to you on the vehicle:")
            lines += [f"  {k}. {s}" for k, s in enumerate(self.steps, start=1)]
        lines += [f"{k}: {v}" for k, v in self.notes.items()]
        if self.residual:
            lines.append(_residual_line(self.residual, self.valid_temp_c))
        return "\n".join(lines)


@dataclass
class VehicleModel:
    """The passport as the vehicle reads it, in the firmware's axes, on ``temps_c`` (n,): ``bias`` (n, 3) m/s^2
    (relative to T0), ``rel`` (n, 3, 3) the unheld temperature terms and ``cross0`` (3, 3) the cross-axis terms at T0
    (error in g per g of specific force, per axis of the reading), ``g`` the m/s^2 of 1 g on the vehicle
    (:data:`pipeline.passport.firmware.FIRMWARE_G_MPS2`)."""

    temps_c: np.ndarray
    bias: np.ndarray
    rel: np.ndarray
    cross0: np.ndarray
    g: float


def recorded_device_id(passport: dict) -> tuple[int | None, str | None]:
    """The PX4 device id the passport's input runs recorded (run metadata ``px4_accel_device_id``, kept in the
    provenance's inputs) and where it comes from; (None, None) when none did, (None, why) when they disagree."""
    inputs = (passport.get("provenance") or {}).get("inputs") or []
    found = [px4_device_id(i.get(PX4_DEVICE_ID_KEY)) for i in inputs if isinstance(i, dict)]
    ids = {d for d in found if d is not None}
    if not ids:
        return None, None
    if len(ids) > 1:
        return None, f"the input runs record different device ids ({', '.join(str(i) for i in sorted(ids))})"
    (device,) = ids
    return device, f"the run metadata ({PX4_DEVICE_ID_KEY})"


def device_id_for(passport: dict, options: ExportOptions) -> tuple[int | None, str]:
    """The PX4 device id an export or comparison uses: ``--px4-device-id``, else the one the input runs recorded;
    and where it came from (or why there is none)."""
    if options.px4_device_id is not None:
        return options.px4_device_id, "--px4-device-id"
    device, source = recorded_device_id(passport)
    return device, source or "none given (--px4-device-id) nor recorded in the run metadata"


def valid_range_c(passport: dict) -> tuple[float, float]:
    """The range the export covers: the passport's valid range (:attr:`Passport.valid_range_c`: ``valid_temp_c``,
    else its calibration plateaus' span), else T0 alone."""
    p = load_passport(passport)
    return p.valid_range_c or (p.normal_temp_c, p.normal_temp_c)


def vehicle_model(passport: dict, temps_c: np.ndarray, rotation: np.ndarray | None = None) -> VehicleModel:
    """The passport's temperature errors as a vehicle with a per-axis accelerometer calibration at T0 reads them,
    in the axes ``rotation`` takes the unit's into (identity: the unit's x, y, z); see the module's docstring."""
    model = load_model(passport)
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
    g = FIRMWARE_G_MPS2  # a bias of x g reads x * 9.80665 m/s^2 after the vehicle's calibration, not x * g_local
    temps = np.atleast_1d(np.asarray(temps_c, dtype=float))
    K, U0 = model.constants_at(temps)
    K0 = R @ np.asarray(model.K0, dtype=float) @ R.T
    Kf = np.einsum("ij,njk,lk->nil", R, K, R)
    d = np.diag(K0)
    bias = g * np.einsum("ij,nj->ni", R, U0 - np.asarray(model.U00, dtype=float)) / d
    rel = (Kf - K0) / d[None, :, None]
    cross0 = K0 / d[:, None] - np.eye(3)
    return VehicleModel(temps, bias, rel, cross0, g)


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


def max_change(values: np.ndarray, temps_c: np.ndarray, span_c: float = PX4_UPDATE_STEP_C) -> np.ndarray:
    """Per column of ``values`` (n, 3) on the ascending grid ``temps_c``: the largest change between two
    temperatures at most ``span_c`` apart (3,)."""
    out = np.zeros(values.shape[1])
    step = float(np.min(np.diff(temps_c))) if len(temps_c) > 1 else span_c
    if step <= 0:  # a valid range of one temperature (lo == hi): nothing changes over it
        return out
    for s in range(1, min(int(span_c / step + 1e-9), len(temps_c) - 1) + 1):
        out = np.maximum(out, np.abs(values[s:] - values[:-s]).max(axis=0))
    return out


def _residual(vm: VehicleModel, held: np.ndarray, change: np.ndarray, update_step: bool) -> dict:
    """The error left over the grid, per axis: the bias fit, the unheld temperature terms and the cross-axis terms
    at T0 (worst orientation, |a| = 1 g), PX4's update step when ``update_step``; ``change`` (3,) m/s^2 the held
    offsets' largest change over 1 C."""
    g, temps = vm.g, vm.temps_c
    ug = 1e6 / g
    fit_err = np.abs(held - vm.bias)  # (n, 3) m/s^2
    unheld = np.linalg.norm(vm.rel, axis=2)  # (n, 3) g per g
    cross = np.linalg.norm(vm.cross0, axis=1)  # (3,)
    scale = np.linalg.norm(vm.rel + vm.cross0[None], axis=2)  # both multiply a: their worst orientation together
    step = change if update_step else np.zeros(3)
    total = fit_err + g * scale + step  # (n, 3) m/s^2
    thermal = fit_err + g * unheld + step  # the same without the cross-axis terms at T0 (not a temperature effect)
    worst = np.unravel_index(int(np.argmax(total)), total.shape)
    return {
        "bias_fit_max_mps2": fit_err.max(axis=0).tolist(),
        "bias_fit_max_ug": (fit_err.max(axis=0) * ug).tolist(),
        "unheld_scale_cross_max_ug": (unheld.max(axis=0) * 1e6).tolist(),
        "unheld_scale_cross_max_mps2": (unheld.max(axis=0) * g).tolist(),
        "vehicle_cross_axis_max_ug": (cross * 1e6).tolist(),
        "update_step_max_ug": (step * ug).tolist() if update_step else None,
        "total_max_ug": (total.max(axis=0) * ug).tolist(),
        "total_worst_ug": float(total.max() * ug),
        "total_worst_mps2": float(total.max()),
        "temperature_max_ug": (thermal.max(axis=0) * ug).tolist(),
        "temperature_worst_ug": float(thermal.max() * ug),
        "worst_at_temp_c": float(temps[worst[0]]),
        "temperature_cost_ug_per_c": (change * ug).tolist(),
        "stale_calibration_max_ug": (np.abs(vm.bias).max(axis=0) * ug).tolist(),
        "bias_range_ug": (np.ptp(vm.bias, axis=0) * ug).tolist(),
        "grid_step_c": GRID_STEP_C,
    }


def _not_held(passport: dict, extra: list[str]) -> list[str]:
    tm = passport.get("thermal_model") or {}
    out = [
        "the scale-factor temperature terms (beta) and the cross-axis temperature terms (gamma): a bias-only "
        "polynomial cannot hold terms that scale with the specific force (the error they leave is the residual's "
        "unheld scale/cross-axis part)",
        "the normal-temperature constants (K, U0 at T0): the vehicle's own accelerometer calibration holds an "
        "offset and a gain per axis; the cross-axis sensitivities (K's off-diagonal terms) neither PX4 nor ArduPilot "
        "holds (the error they leave is the residual's cross-axis part)",
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


def _ug3(values) -> str:
    return " / ".join(f"{v:.3g}" for v in values) + " micro-g (x / y / z)"


def _notes(fw: str, frame: str, residual: dict) -> dict[str, str]:
    name = FIRMWARE_NAMES[fw]
    return {
        "temperature": "the model was fitted against the unit's own thermosensor (the recording's au_temperature "
        f"stream); {name} evaluates it at {FIRMWARE_TEMPERATURE[fw]}: each 1 C by which that reads differently "
        f"from the thermosensor costs up to {_ug3(residual['temperature_cost_ug_per_c'])}",
        "axes": f"offsets along {frame}; {name} applies them in the accelerometer's frame {FIRMWARE_FRAME[fw]}; "
        "when the unit's x, y, z are not that frame, export with --rotation NAME (the firmware's rotation names, "
        "e.g. ROTATION_ROLL_180) or --rotation 'r11,r12,r13,r21,r22,r23,r31,r32,r33' (the matrix taking the "
        "unit's axes into the accelerometer's)",
    }


def _residual_line(res: dict, valid: tuple[float, float]) -> str:
    parts = [
        f"bias fit {_ug3(res['bias_fit_max_ug'])}",
        f"unheld scale/cross-axis temperature terms {_ug3(res['unheld_scale_cross_max_ug'])}",
        f"cross-axis terms at T0 {_ug3(res['vehicle_cross_axis_max_ug'])}",
    ]
    if res.get("update_step_max_ug") is not None:
        parts.append(f"PX4's 1 C update step {_ug3(res['update_step_max_ug'])}")
    return (
        f"residual over {valid[0]:g}..{valid[1]:g} C at |a| = 1 g: " + "; ".join(parts) + f"; worst total "
        f"{res['total_worst_ug']:.3g} micro-g at {res['worst_at_temp_c']:g} C; without the cross-axis terms at T0 "
        f"(there with or without this file) {_ug3(res['temperature_max_ug'])}"
    )


def export_px4(passport: dict, state=None, options: ExportOptions | None = None) -> Export:
    """PX4 ``TC_A<k>_*`` parameters (slot k = ``--instance``, default 0): TREF the passport's normal temperature,
    TMIN/TMAX its valid range, X0..X3 the offset cubic in m/s^2 per C^n (float32, as PX4 stores them),
    ``TC_A_ENABLE`` 1 and ``TC_A<k>_ID`` the accelerometer's device id (0 without ``--px4-device-id``: PX4 then
    corrects nothing, which the file and a warning say)."""
    opts = options or ExportOptions()
    slot = px4_slot(0 if opts.instance is None else opts.instance)
    R, frame = rotation_matrix(opts.rotation, "px4")
    lo, hi = valid_range_c(passport)
    tref = float(passport.get("normal_temp_c", 20.0))
    temps = _grid(lo, hi)
    vm = vehicle_model(passport, temps, R)
    coef = _cubic_fit(temps - tref, vm.bias).astype(np.float32)  # PX4 parameters are float32
    device, device_source = device_id_for(passport, opts)
    params: dict[str, float] = {
        slot.enable: 1,
        slot.id: px4_int32(device) if device else 0,
        slot.tref: tref,
        slot.tmin: lo,
        slot.tmax: hi,
    }
    for n in range(4):
        for i in range(3):
            params[slot.coef[n][i]] = float(coef[n, i])
    held = px4_offsets(params, slot.slot, temps).astype(np.float64)  # what PX4 subtracts, as it computes it
    residual = _residual(vm, held, max_change(held, temps), update_step=True)
    warnings, steps = [], []
    if not device:
        why = "" if device_source.startswith("none") else f" ({device_source})"
        warnings.append(
            f"the PX4 file will not be applied: {slot.id} is 0{why}, which matches no accelerometer; export with "
            f"--px4-device-id N (the accelerometer's device id: the vehicle's CAL_ACC<n>_ID, or device_id in "
            f"'listener sensor_accel') or set {slot.id} before loading"
        )
        steps.append(
            f"set {slot.id} to the device id of the accelerometer to correct (the vehicle's CAL_ACC<n>_ID, or "
            "device_id in 'listener sensor_accel'), or export again with --px4-device-id N: while it is 0 the file "
            "corrects nothing"
        )
    steps += [
        "load this file (QGroundControl: Vehicle Setup > Parameters > Tools > Load from file; it refuses a file whose "
        "first column, the system id, is not the vehicle's MAV_SYS_ID: written here as 1, edit that column for "
        "another; if it reports TC_A* parameters the vehicle does not have, set TC_A_ENABLE 1, reboot and load again, "
        "as PX4's own offboard thermal calibration sets TC_A_ENABLE before loading its file); it replaces the "
        f"vehicle's {slot.id[:-2]}* slot: when its {slot.id} is another accelerometer's device id (not 0 nor this "
        "one's), export again with --instance K of a slot whose TC_A<K>_ID is 0",
        "reboot: PX4 reads TC_A_ENABLE at boot (it enables every TC_A<K>_* slot the vehicle holds, not only this one)",
        f"redo the vehicle's accelerometer calibration with the IMU between TMIN and TMAX ({lo:g} .. {hi:g} C), "
        f"best near T0 = {tref:g} C: PX4 computes it on thermally corrected readings, so one made before loading "
        f"leaves up to {_ug3(residual['stale_calibration_max_ug'])}",
    ]
    order = (
        "PX4 uses this file only in this order: "
        + ("" if device else f"set {slot.id} to the accelerometer's device id, ")
        + f"load it, reboot, redo the vehicle's accelerometer calibration with the IMU between {lo:g} and {hi:g} C "
        f"(best near T0 = {tref:g} C)"
    )
    notes = _notes("px4", frame, residual)
    if device:
        notes["device"] = (
            f"{slot.id} = {device} (0x{device:08X}), from {device_source}: PX4 corrects only the accelerometer "
            "with that device id"
        )
    not_held = _not_held(passport, [])
    text = _header(
        passport,
        f"PX4 thermal compensation ({slot.id[:-2]}*), QGroundControl parameter file",
        (lo, hi),
        steps,
        notes,
        not_held,
        residual,
        state,
    )
    text += ["# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
    ints = {slot.enable, slot.id}
    for name, value in params.items():
        text.append(
            f"1\t1\t{name}\t{int(value) if name in ints else _f32(value)}\t{QGC_INT32 if name in ints else QGC_FLOAT}"
        )
    return Export(
        "px4",
        passport.get("unit", ""),
        passport.get("version"),
        (lo, hi),
        "\n".join(text) + "\n",
        not_held,
        residual,
        params,
        steps,
        notes,
        warnings,
        order,
        R.tolist(),
    )


def export_ardupilot(passport: dict, state=None, options: ExportOptions | None = None) -> Export:
    """ArduPilot ``INS_TCAL<n>_*`` parameters (IMU n = ``--instance``, default 1): ENABLE 1, TMIN/TMAX the valid
    range (clipped to -70..80 C), ACC1..ACC3 the cubic about 35 C without constant term, times 1e6. The correction
    is relative to ``INS_ACC<n>_CALTEMP``, the temperature of the vehicle's own accelerometer calibration, which is
    written (as T0) only with ``--set-caltemp``: right only when the vehicle's accelerometer offsets and scales are
    the passport's T0 constants."""
    opts = options or ExportOptions()
    imu = ardupilot_imu(1 if opts.instance is None else opts.instance)
    R, frame = rotation_matrix(opts.rotation, "ardupilot")
    lo, hi = valid_range_c(passport)
    extra, warnings = [], []
    a_lo, a_hi = max(lo, ARDUPILOT_TEMP_RANGE_C[0]), min(hi, ARDUPILOT_TEMP_RANGE_C[1])
    if a_lo > a_hi or (a_lo == a_hi and hi > lo):
        raise ThermocalError(
            f"the passport is valid over {lo:g} .. {hi:g} C, outside the -70 .. 80 C ArduPilot's {imu.tmin}/"
            f"{imu.tmax} accept: nothing of it can be exported for ArduPilot",
            where="--format",
        )
    if (a_lo, a_hi) != (lo, hi):
        extra.append(
            f"the part of valid_temp_c outside ArduPilot's -70..80 C (TMIN/TMAX clipped to {a_lo:g}..{a_hi:g} C)"
        )
        warnings.append(
            f"{imu.tmin}/{imu.tmax} written as {a_lo:g} .. {a_hi:g} C, not the passport's valid {lo:g} .. {hi:g} C: "
            f"ArduPilot accepts -70 .. 80 C, and holds the correction at its value at the limit beyond it"
        )
    t0 = float(passport.get("normal_temp_c", 20.0))
    temps = _grid(a_lo, a_hi)
    vm = vehicle_model(passport, temps, R)
    q = _cubic_fit(temps - ARDUPILOT_TREF_C, vm.bias)
    coef = np.round(q[1:] * ARDUPILOT_SCALE, 9)  # ACC1..ACC3 as written
    params: dict[str, float] = {imu.enable: 1, imu.tmin: a_lo, imu.tmax: a_hi}
    for n in range(3):
        for i in range(3):
            params[imu.acc[n][i]] = float(coef[n, i])
    if opts.set_caltemp:
        params[imu.caltemp] = t0
    # what ArduPilot subtracts for a vehicle calibrated at T0 (clamped as ArduPilot clamps it): p(T-35) - p(T0-35)
    t0c = min(max(t0, a_lo), a_hi)
    held = ardupilot_correction(params, imu.imu, temps, t0c).astype(np.float64)
    vm.bias = vm.bias - vehicle_model(passport, np.array([t0c]), R).bias
    residual = _residual(vm, held, max_change(held, temps), update_step=False)
    group = imu.group
    steps = [
        f"set {imu.enable} to 1 (loading this file once does only that: while it is 0 ArduPilot hides the other "
        f"{group} parameters)",
        "reboot",
        (
            "load this file again (QGroundControl: Vehicle Setup > Parameters > Tools > Load from file; it refuses a "
            "file whose first column, the system id, is not the vehicle's SYSID_THISMAV: written here as 1, edit that "
            f"column for another): now every {group} parameter is there"
            if opts.qgc
            else "load this file again (MAVProxy: param load FILE; Mission Planner: Full Parameter List > Load from "
            "file; not QGroundControl, which reads only its own tab-separated files and skips every line of this "
            f"one: export with --qgc for it): now every {group} parameter is there"
        ),
        f"reboot: ArduPilot reads {group} at boot",
    ]
    if opts.set_caltemp:
        steps.append(
            f"this file sets {imu.caltemp} = T0 ({t0:g} C) (--set-caltemp): right only when the vehicle's "
            "accelerometer offsets and scales are this passport's T0 constants; a new accelerometer calibration on "
            "the vehicle writes it again"
        )
    else:
        steps.append(
            f"check {imu.caltemp} (this file leaves it alone: the vehicle's own accelerometer calibration wrote it "
            f"and the correction is relative to it): if it is -300 (never recorded) or outside TMIN..TMAX "
            f"({a_lo:g} .. {a_hi:g} C), redo the vehicle's accelerometer calibration with the IMU in that range, best "
            f"near T0 = {t0:g} C (otherwise up to {_ug3(residual['bias_range_ug'])} stays)"
        )
    gyro = (
        f"{imu.tmin}/{imu.tmax} also clamp the gyroscope's temperature correction ({group[:-1]}GYR1..3_*, not "
        f"written here, so a vehicle's own gyroscope coefficients stay, clamped to {a_lo:g} .. {a_hi:g} C), and "
        f"{imu.enable} enables both"
    )
    notes = {**_notes("ardupilot", frame, residual), "limits": gyro}
    order = (
        f"ArduPilot reads this file only in this order: set {imu.enable} 1, reboot, load the file, reboot; "
        f"{imu.tmin}/{imu.tmax} also clamp the gyroscope correction; then "
        + (
            f"{imu.caltemp} is T0 = {t0:g} C from this file (--set-caltemp)"
            if opts.set_caltemp
            else f"check {imu.caltemp}: if it is -300 or outside {a_lo:g} .. {a_hi:g} C, redo the vehicle's "
            "accelerometer calibration with the IMU in that range"
        )
    )
    not_held = _not_held(
        passport,
        extra
        + [
            f"gyroscope terms ({group[:-1]}GYR*): the unit has no gyroscopes; not written, so a vehicle's own "
            "values stay"
        ],
    )
    text = _header(
        passport,
        f"ArduPilot IMU temperature calibration ({group}), "
        + ("QGroundControl parameter file" if opts.qgc else "parameter file (MAVProxy, Mission Planner)"),
        (a_lo, a_hi),
        steps,
        notes,
        not_held,
        residual,
        state,
    )
    if opts.qgc:  # ENABLE is an int8 parameter, the rest float; a row of another type QGroundControl skips
        text += ["# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
        text += [
            f"1\t1\t{name}\t{int(value)}\t{QGC_INT8}"
            if name == imu.enable
            else f"1\t1\t{name}\t{_f32(value)}\t{QGC_FLOAT}"
            for name, value in params.items()
        ]
    else:
        text += [f"{name} {int(value) if name == imu.enable else _num(value)}" for name, value in params.items()]
    return Export(
        "ardupilot",
        passport.get("unit", ""),
        passport.get("version"),
        (a_lo, a_hi),
        "\n".join(text) + "\n",
        not_held,
        residual,
        params,
        steps,
        notes,
        warnings,
        order,
        R.tolist(),
    )


def compare_params(
    passport: dict,
    params: Mapping[str, float],
    *,
    fmt: str | None = None,
    options: ExportOptions | None = None,
    path: str | None = None,
) -> dict:
    """A vehicle's existing temperature calibration (``params``, e.g. from
    :func:`pipeline.passport.firmware.read_params_file`) against the passport over its valid range: the firmware's
    correction evaluated as the firmware does (enable flag, device id, clamping, float32) and the passport's bias
    in the same axes (``options.rotation``). The vehicle's own accelerometer calibration absorbs a constant, so the
    difference is taken relative to its value at the calibration temperature (ArduPilot: ``INS_ACC<n>_CALTEMP``
    when the file has a recorded one; else, and for PX4, T0). Returns ``max_diff_ug`` per axis with where, and
    whether and why the firmware applies the file at all."""
    opts = options or ExportOptions()
    fw = detect_firmware(params, path)
    if fmt not in (None, fw):
        raise ThermocalError(f"the parameter file holds {FIRMWARE_NAMES[fw]} parameters, not {fmt}", path=path)
    opts.check(fw)
    R, frame = rotation_matrix(opts.rotation, fw)
    lo, hi = valid_range_c(passport)
    t0 = float(passport.get("normal_temp_c", 20.0))
    temps = _grid(lo, hi)
    vm = vehicle_model(passport, temps, R)
    why_not: str | None = None
    notes: list[str] = []
    out: dict = {"firmware": fw}
    if fw == "px4":
        slot = 0 if opts.instance is None else opts.instance
        device, device_source = device_id_for(passport, opts)
        vehicle_ids = {as_uint32(v) for k, v in params.items() if k.startswith("CAL_ACC") and k.endswith("_ID")}
        vehicle_ids.discard(0)
        if device is not None:
            found = px4_matching_slot(params, device)
            if found is None:
                why_not = f"no TC_A<k>_ID equals the device id {device} (from {device_source})"
            slot = slot if found is None else found
        elif opts.instance is None:
            # no device id given or recorded: the first slot the vehicle uses (its ID one of the vehicle's
            # accelerometers, CAL_ACC<n>_ID, when the file has them; else the first slot with an ID)
            used = [
                k
                for k in range(PX4_SLOTS)
                if _slot_id(params, k) and (not vehicle_ids or _slot_id(params, k) in vehicle_ids)
            ]
            if used:
                slot = used[0]
                which = (
                    "whose ID is one of the vehicle's accelerometers (CAL_ACC<n>_ID)"
                    if vehicle_ids
                    else "with an ID (the file holds no CAL_ACC<n>_ID)"
                )
                notes.append(
                    f"TC_A{slot}_* compared: the first slot {which}; give --px4-device-id N or --instance K for another"
                )
        names = px4_slot(slot)
        dev = as_uint32(params.get(names.id, 0))
        if int(params.get(names.enable, 0)) != 1:
            why_not = f"{names.enable} is {params.get(names.enable, 0):g} (must be 1)"
        elif why_not is None and dev == 0:
            why_not = f"{names.id} is 0, which matches no accelerometer"
        elif why_not is None and vehicle_ids and dev not in vehicle_ids:
            why_not = f"{names.id} {dev} matches none of the vehicle's accelerometers ({sorted(vehicle_ids)})"
        cal_t = t0  # PX4's offsets are absolute: the calibration at cal_t absorbed their value there
        held = (px4_offsets(params, slot, temps) - px4_offsets(params, slot, np.array([cal_t]))).astype(np.float64)
        notes.append(f"relative to a vehicle accelerometer calibration at T0 = {t0:g} C (it absorbs a constant)")
        out |= {"instance": slot, "device_id": dev}
    else:
        imu = ardupilot_imu(1 if opts.instance is None else opts.instance)
        if int(params.get(imu.enable, 0)) != 1:
            why_not = f"{imu.enable} is {params.get(imu.enable, 0):g} (must be 1, and the vehicle rebooted)"
        cal = params.get(imu.caltemp)
        if cal is None or cal <= ARDUPILOT_DEFAULTS["CALTEMP"] + 1:
            cal_t = t0
            notes.append(
                f"{imu.caltemp} is "
                + ("not in the file" if cal is None else f"{cal:g} (never recorded)")
                + f": relative to a vehicle accelerometer calibration at T0 = {t0:g} C"
            )
        else:
            cal_t = float(cal)
            notes.append(f"relative to the vehicle's accelerometer calibration at {imu.caltemp} = {cal_t:g} C")
        held = ardupilot_correction(params, imu.imu, temps, cal_t).astype(np.float64)
        out |= {"instance": imu.imu}
    if why_not is not None:
        held = np.zeros_like(held)
    truth = vm.bias - vehicle_model(passport, np.array([cal_t]), R).bias
    diff = np.abs(held - truth)  # (n, 3) m/s^2
    ug = 1e6 / vm.g
    at = np.argmax(diff, axis=0)
    return out | {
        "applied": why_not is None,
        "why_not": why_not,
        "valid_temp_c": [lo, hi],
        "calibration_temp_c": cal_t,
        "max_diff_ug": (diff.max(axis=0) * ug).tolist(),
        "at_temp_c": [float(temps[k]) for k in at],
        "bias_range_ug": (np.ptp(truth, axis=0) * ug).tolist(),
        "axes": frame,
        "notes": notes,
        "grid_step_c": GRID_STEP_C,
    }


def _slot_id(params: Mapping[str, float], slot: int) -> int:
    """PX4 slot ``slot``'s ``TC_A<k>_ID`` as the firmware compares it (0: none)."""
    return as_uint32(params.get(px4_slot(slot).id, 0))


def compare_text(result: dict, path: str, used: str) -> str:
    """``export --compare`` as text."""
    fw = FIRMWARE_NAMES[result["firmware"]]
    inst = (
        f"TC_A{result['instance']}_*, device id {result['device_id']}"
        if result["firmware"] == "px4"
        else ardupilot_imu(result["instance"]).group
    )
    lo, hi = result["valid_temp_c"]
    head = f"{path}: {fw} ({inst}) against {used}"
    applied = "applied" if result["applied"] else f"NOT applied: {result['why_not']}"
    diff = " / ".join(f"{v:.3g} (at {t:g} C)" for v, t in zip(result["max_diff_ug"], result["at_temp_c"], strict=True))
    return "\n".join(
        [
            head,
            f"  the vehicle's correction is {applied}",
            f"  max difference over {lo:g}..{hi:g} C: {diff} micro-g (x / y / z)",
            *[f"  {n}" for n in result["notes"]],
            f"  axes: {result['axes']}",
        ]
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


def export_passport(passport: dict, fmt: str, state=None, options: ExportOptions | None = None) -> Export:
    """The passport in ``fmt``: ``px4``, ``ardupilot`` or ``csv``. ``state``: its
    :class:`pipeline.passport.registry.VersionState` when read from a registry (status and approval stated in the
    file); ``options``: what the user says about the vehicle (:class:`ExportOptions`)."""
    if fmt not in FORMATS:
        raise ThermocalError(f"unknown export format {fmt!r} ({', '.join(FORMATS)})", where="--format")
    opts = options or ExportOptions()
    opts.check(fmt)
    stated = load_passport(passport).valid_range_c  # None: states none (an old passport): T0 alone, as before
    if fmt in FIRMWARE_NAMES and stated is not None and stated[1] <= stated[0]:
        t = stated[0]
        raise ThermocalError(
            f"{passport.get('unit', 'the unit')} v{passport.get('version')} is valid at one temperature only "
            f"({t:g} C): it holds no temperature model, so a temperature calibration for {FIRMWARE_NAMES[fmt]} from "
            "it would correct nothing and only enable the firmware's correction clamped to that temperature; "
            "--format csv exports its constants",
            where="--format",
        )
    try:
        if fmt == "csv":
            return export_csv(passport, state)
        return {"px4": export_px4, "ardupilot": export_ardupilot}[fmt](passport, state, opts)
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
    passport: dict,
    what: str,
    valid: tuple[float, float],
    steps: list[str],
    notes: dict[str, str],
    not_held: list[str],
    residual: dict,
    state=None,
) -> list[str]:
    unit, version = passport.get("unit", "?"), passport.get("version")
    lo, hi = valid
    check = getattr(state, "verification", None)
    stored = "content_sha256 as stored, unverified" if check is not None and not check.verified else "content_sha256"
    lines = [
        f"# {what}",
        f"# thermocal export of {unit} passport v{version} ({stored} "
        f"{str(passport.get('content_sha256', ''))[:16]}), method {passport.get('method', 'tilt_six_position')}",
        f"# status {passport.get('status')}; {_approval(passport, state)}",
    ]
    if passport.get("status") == "fail":
        lines.append(f"# WARNING: {failed_verification('this passport')}; review before loading it")
    lines += [
        f"# valid temperature range {lo:g} .. {hi:g} C; accelerometer offsets in m/s^2",
        "# raw reading assumed: the unit's output with the vehicle's own accelerometer calibration at T0 (an offset "
        "and a gain per axis)",
        "# steps left to you on the vehicle:",
    ]
    lines += [f"#   {k}. {s}" for k, s in enumerate(steps, start=1)]
    lines += [f"# {k}: {v}" for k, v in notes.items()]
    lines += ["# not held by this format:"] + [f"#   - {t}" for t in not_held]
    if residual:
        lines += [
            "# residual error over the valid range (0.1 C grid, |a| = 1 g), max per axis x / y / z in micro-g:",
            "#   bias cubic fit error: " + _ug_list(residual["bias_fit_max_ug"]),
            "#   unheld scale/cross-axis temperature terms: " + _ug_list(residual["unheld_scale_cross_max_ug"]),
            "#   cross-axis terms at T0 (the vehicle's calibration is per axis): "
            + _ug_list(residual["vehicle_cross_axis_max_ug"]),
        ]
        if residual.get("update_step_max_ug") is not None:
            lines.append("#   PX4's 1 C update step: " + _ug_list(residual["update_step_max_ug"]))
        lines += [
            "#   total: " + _ug_list(residual["total_max_ug"]),
            "#   total without the cross-axis terms at T0 (there with or without this file): "
            + _ug_list(residual["temperature_max_ug"]),
            f"#   worst: {residual['total_worst_ug']:.3g} micro-g ({residual['total_worst_mps2']:.3g} m/s^2) at "
            f"{residual['worst_at_temp_c']:g} C",
        ]
    return lines


def _ug_list(values) -> str:
    return " / ".join(f"{v:.3g}" for v in values)
