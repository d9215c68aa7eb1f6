"""What flight software does with an accelerometer temperature calibration (``thermocal export``, ``--compare``).

Facts read from the firmwares' sources and parameter definitions, written here in thermocal's own terms:

- **PX4** (``temperature_compensation`` module). ``TC_A_ENABLE`` must be 1, read at boot. Four parameter slots
  ``TC_A0_*`` .. ``TC_A3_*``; an accelerometer is corrected by the first slot whose ``TC_A<k>_ID`` equals its device
  id (compared as unsigned 32-bit; the parameter is a signed int32), none when no slot matches (an id of 0 matches
  nothing). In float32: ``dT = clamp(T, TMIN, TMAX) - TREF`` (a temperature above TMAX gives ``TMAX - TREF``, below
  TMIN ``TMIN - TREF``), ``offset_i = X0_i + X1_i dT + X2_i dT^2 + X3_i dT^3`` (``dT^2 = dT dT``, ``dT^3 = dT^2 dT``),
  subtracted from the reading before the vehicle's own offset and scale (``CAL_ACCn_*``) and before the board
  rotation. New offsets are published only when the temperature has moved by more than 1 C since the last
  publication (the first reading always publishes), so the offset in use lags the temperature by up to 1 C.
- **ArduPilot** (``AP_InertialSensor_tempcal``). ``INS_TCALn_ENABLE`` must be 1 (it needs a reboot; while it is 0
  the group's other parameters are hidden, so a file setting them is refused until the vehicle rebooted with it
  1). IMUs 1..3 are ``INS_TCAL<n>_*`` with ``INS_ACC<n>_CALTEMP``; IMUs 4 and 5 are ``INS<n>_TCAL_*`` with
  ``INS<n>_ACC_CALTEMP``. In float32: ``p(x) = ((c1 + (c2 + c3 x) x) x) 1e-6`` per axis (``c_k`` =
  ``ACC<k>_X/Y/Z``), and the reading becomes ``v - p(T - 35) + p(Tcal - 35)``, both T and Tcal (the temperature of the
  vehicle's own accelerometer calibration, ``CALTEMP``, written by that calibration; default -300) clamped to
  [TMIN, TMAX], which also clamp the gyroscope's correction (``GYR<k>_*``) of the same group. Applied after the IMU's
  sensor rotation and before the vehicle's offsets, scales and board rotation (``AHRS_ORIENTATION``); not while
  the vehicle calibrates its accelerometers.
- **Rotations**: both firmwares name sensor rotations ``ROTATION_*`` with an enum number, each a roll, pitch and
  yaw in degrees whose matrix is ``Rz(yaw) Ry(pitch) Rx(roll)``, taking a vector from the sensor's axes into the
  rotated ones (``v' = R v``). The first 41 names are common (number 38 differs in its angles).
- **Parameter files**: QGroundControl writes ``SYS COMP NAME VALUE TYPE`` (tab separated, type 2 = int8, 6 =
  int32, 9 = float; it loads only that form, and a parameter only with the vehicle's type); MAVProxy ``NAME
  VALUE`` and Mission Planner ``NAME,VALUE``; ``#`` starts a comment line.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ThermocalError

FIRMWARES = ("px4", "ardupilot")
PX4_SLOTS = 4  # TC_A0_* .. TC_A3_* (the module's ACCEL_COUNT_MAX)
PX4_UPDATE_STEP_C = 1.0  # offsets are recomputed when the temperature moved by more than this
PX4_DEFAULTS = {"TREF": 25.0, "TMIN": 0.0, "TMAX": 100.0}  # a slot's defaults (parameter definitions)
ARDUPILOT_IMUS = 5  # INS_TCAL1..3 and INS4_/INS5_
ARDUPILOT_TREF_C = 35.0  # fixed reference temperature of ArduPilot's tempcal (not a parameter)
ARDUPILOT_SCALE = 1.0e6  # ArduPilot stores the coefficients times 1e6
ARDUPILOT_TEMP_RANGE_C = (-70.0, 80.0)  # the range INS_TCALn_TMIN/TMAX accept
ARDUPILOT_DEFAULTS = {"TMIN": 0.0, "TMAX": 70.0, "CALTEMP": -300.0}
#: What a vehicle's own accelerometer calibration makes 1 g read, m/s^2 (PX4's CONSTANTS_ONE_G, ArduPilot's
#: GRAVITY_MSS): the firmwares' offsets are in these units whatever the gravity where the unit was calibrated
FIRMWARE_G_MPS2 = 9.80665
QGC_INT8, QGC_INT32, QGC_FLOAT = 2, 6, 9  # MAV_PARAM_TYPE of a QGroundControl parameter file's last column
AXES = "xyz"


@dataclass(frozen=True)
class Px4Slot:
    """The parameter names of PX4's accelerometer slot ``k`` (``TC_A<k>_*``); ``coef[n][i]`` is ``X<n>_<i>``."""

    slot: int
    enable: str
    id: str
    tref: str
    tmin: str
    tmax: str
    coef: tuple[tuple[str, ...], ...]


def px4_slot(k: int) -> Px4Slot:
    if not 0 <= k < PX4_SLOTS:
        raise ThermocalError(f"PX4 has accelerometer slots 0..{PX4_SLOTS - 1} (TC_A0_* .. TC_A3_*), not {k}")
    p = f"TC_A{k}_"
    coef = tuple(tuple(f"{p}X{n}_{i}" for i in range(3)) for n in range(4))
    return Px4Slot(k, "TC_A_ENABLE", p + "ID", p + "TREF", p + "TMIN", p + "TMAX", coef)


@dataclass(frozen=True)
class ArduPilotImu:
    """The parameter names of ArduPilot's IMU ``n`` (1-based); ``acc[k-1][i]`` is ``ACC<k>_<X|Y|Z>``."""

    imu: int
    enable: str
    tmin: str
    tmax: str
    acc: tuple[tuple[str, ...], ...]
    gyr: tuple[tuple[str, ...], ...]
    caltemp: str

    @property
    def group(self) -> str:
        return self.enable[: -len("ENABLE")] + "*"


def ardupilot_imu(n: int) -> ArduPilotImu:
    if not 1 <= n <= ARDUPILOT_IMUS:
        raise ThermocalError(
            f"ArduPilot has IMUs 1..{ARDUPILOT_IMUS} (INS_TCAL1_* .. INS_TCAL3_*, INS4_TCAL_*, INS5_TCAL_*), not {n}"
        )
    p, cal = (f"INS_TCAL{n}_", f"INS_ACC{n}_CALTEMP") if n <= 3 else (f"INS{n}_TCAL_", f"INS{n}_ACC_CALTEMP")
    acc = tuple(tuple(f"{p}ACC{k}_{ax}" for ax in "XYZ") for k in (1, 2, 3))
    gyr = tuple(tuple(f"{p}GYR{k}_{ax}" for ax in "XYZ") for k in (1, 2, 3))
    return ArduPilotImu(n, p + "ENABLE", p + "TMIN", p + "TMAX", acc, gyr, cal)


# --- rotations ------------------------------------------------------------------------------------------------

_COMMON_ROTATIONS: list[tuple[str, float, float, float]] = [
    ("NONE", 0, 0, 0),
    ("YAW_45", 0, 0, 45),
    ("YAW_90", 0, 0, 90),
    ("YAW_135", 0, 0, 135),
    ("YAW_180", 0, 0, 180),
    ("YAW_225", 0, 0, 225),
    ("YAW_270", 0, 0, 270),
    ("YAW_315", 0, 0, 315),
    ("ROLL_180", 180, 0, 0),
    ("ROLL_180_YAW_45", 180, 0, 45),
    ("ROLL_180_YAW_90", 180, 0, 90),
    ("ROLL_180_YAW_135", 180, 0, 135),
    ("PITCH_180", 0, 180, 0),
    ("ROLL_180_YAW_225", 180, 0, 225),
    ("ROLL_180_YAW_270", 180, 0, 270),
    ("ROLL_180_YAW_315", 180, 0, 315),
    ("ROLL_90", 90, 0, 0),
    ("ROLL_90_YAW_45", 90, 0, 45),
    ("ROLL_90_YAW_90", 90, 0, 90),
    ("ROLL_90_YAW_135", 90, 0, 135),
    ("ROLL_270", 270, 0, 0),
    ("ROLL_270_YAW_45", 270, 0, 45),
    ("ROLL_270_YAW_90", 270, 0, 90),
    ("ROLL_270_YAW_135", 270, 0, 135),
    ("PITCH_90", 0, 90, 0),
    ("PITCH_270", 0, 270, 0),
    ("PITCH_180_YAW_90", 0, 180, 90),
    ("PITCH_180_YAW_270", 0, 180, 270),
    ("ROLL_90_PITCH_90", 90, 90, 0),
    ("ROLL_180_PITCH_90", 180, 90, 0),
    ("ROLL_270_PITCH_90", 270, 90, 0),
    ("ROLL_90_PITCH_180", 90, 180, 0),
    ("ROLL_270_PITCH_180", 270, 180, 0),
    ("ROLL_90_PITCH_270", 90, 270, 0),
    ("ROLL_180_PITCH_270", 180, 270, 0),
    ("ROLL_270_PITCH_270", 270, 270, 0),
    ("ROLL_90_PITCH_180_YAW_90", 90, 180, 90),
    ("ROLL_90_YAW_270", 90, 0, 270),
    ("ROLL_90_PITCH_68_YAW_293", 90, 68, 293),  # ArduPilot: 68.8 and 293.3 (below)
    ("PITCH_315", 0, 315, 0),
    ("ROLL_90_PITCH_315", 90, 315, 0),
]
_MORE_ROTATIONS: dict[str, list[tuple[str, float, float, float]]] = {
    "px4": [
        ("ROLL_270_YAW_180", 270, 0, 180),
        ("ROLL_270_YAW_270", 270, 0, 270),
        ("PITCH_90_YAW_180", 0, 90, 180),
        ("PITCH_9_YAW_180", 0, 9, 180),
        ("PITCH_45", 0, 45, 0),
        ("ROLL_270_YAW_225", 270, 0, 225),
        ("ROLL_270_YAW_315", 270, 0, 315),
    ],
    "ardupilot": [("PITCH_7", 0, 7, 0), ("ROLL_45", 45, 0, 0), ("ROLL_315", 315, 0, 0)],
}


def rotations(firmware: str) -> dict[str, tuple[int, tuple[float, float, float]]]:
    """The firmware's rotation names: ``ROTATION_*`` -> (enum number, (roll, pitch, yaw) degrees)."""
    table = list(_COMMON_ROTATIONS) + _MORE_ROTATIONS[firmware]
    if firmware == "ardupilot":
        table[38] = ("ROLL_90_PITCH_68_YAW_293", 90, 68.8, 293.3)
    return {f"ROTATION_{name}": (k, (r, p, y)) for k, (name, r, p, y) in enumerate(table)}


def euler_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)``: the matrix both firmwares build from a rotation's angles."""
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    m = rz @ ry @ rx
    return np.where(np.abs(m) < 1e-15, 0.0, m)


def rotation_matrix(spec: str | None, firmware: str) -> tuple[np.ndarray, str]:
    """``--rotation``: the matrix R taking the unit's x, y, z into the axes the firmware corrects (``v_fw = R
    v_unit``) and how to say it. ``spec``: a rotation name of the firmware (``ROTATION_ROLL_180``, or without the
    prefix), its enum number, or nine numbers (the matrix row by row, separated by commas or spaces), which must be
    orthonormal. None: the identity (the unit's axes are the IMU's)."""
    if spec is None or not spec.strip():
        return np.eye(3), "the unit's x, y, z"
    text = spec.strip()
    table = rotations(firmware)
    by_number = {k: name for name, (k, _) in table.items()}
    name = text.upper() if text.upper().startswith("ROTATION_") else f"ROTATION_{text.upper()}"
    if text.isdigit() and int(text) in by_number:
        name = by_number[int(text)]
    if name in table:
        k, angles = table[name]
        m = euler_matrix(*angles)
        return m, f"the unit's x, y, z rotated by {name} ({firmware} rotation {k}: {_matrix_text(m)})"
    parts = text.replace(",", " ").replace(";", " ").split()
    if len(parts) != 9:
        raise ThermocalError(
            f"unknown rotation {spec!r}: give one of {firmware}'s rotation names (e.g. ROTATION_ROLL_180, "
            "ROTATION_YAW_90) or its number, or nine numbers (the matrix taking the unit's axes into the IMU's, "
            "row by row)",
            where="--rotation",
        )
    try:
        m = np.array([float(p) for p in parts]).reshape(3, 3)
    except ValueError:
        raise ThermocalError(
            f"the rotation matrix {spec!r} holds a value that is not a number", where="--rotation"
        ) from None
    if not np.all(np.isfinite(m)) or np.abs(m @ m.T - np.eye(3)).max() > 1e-6:
        raise ThermocalError(
            f"the rotation matrix {spec!r} is not orthonormal (its rows must be unit vectors at right angles)",
            where="--rotation",
        )
    kind = "a reflection, det -1" if np.linalg.det(m) < 0 else "matrix"
    return m, f"the unit's x, y, z mapped by the {kind} {_matrix_text(m)}"


def _matrix_text(m: np.ndarray) -> str:
    return "[" + "; ".join(" ".join(f"{v:.6g}" for v in row) for row in m) + "]"


# --- the firmwares' arithmetic (float32), for --compare -------------------------------------------------------


def as_uint32(value: float) -> int:
    """A device id as the firmware compares it: the int32 parameter read as unsigned 32-bit."""
    return int(value) & 0xFFFFFFFF


def px4_int32(device_id: int) -> int:
    """A device id (0 < id < 2**32) as PX4's int32 parameter ``TC_A<k>_ID`` holds it."""
    return device_id - (1 << 32) if device_id >= 1 << 31 else device_id


def px4_matching_slot(params: Mapping[str, float], device_id: int) -> int | None:
    """The slot PX4 uses for an accelerometer with ``device_id``: the first whose ``TC_A<k>_ID`` equals it."""
    for k in range(PX4_SLOTS):
        if as_uint32(params.get(px4_slot(k).id, 0)) == as_uint32(device_id):
            return k
    return None


def px4_offsets(params: Mapping[str, float], slot: int, temps_c: np.ndarray) -> np.ndarray:
    """PX4's offsets (n, 3) m/s^2 of slot ``slot`` at ``temps_c``, float32 as PX4 computes them (subtracted from
    the reading). Parameters absent from ``params`` take PX4's defaults."""
    s = px4_slot(slot)
    f = np.float32
    tref = f(params.get(s.tref, PX4_DEFAULTS["TREF"]))
    tmin = f(params.get(s.tmin, PX4_DEFAULTS["TMIN"]))
    tmax = f(params.get(s.tmax, PX4_DEFAULTS["TMAX"]))
    t = np.asarray(temps_c, dtype=np.float32)
    dt = np.where(t > tmax, tmax - tref, np.where(t < tmin, tmin - tref, t - tref)).astype(np.float32)
    dt2 = dt * dt
    dt3 = dt2 * dt
    x = np.array([[params.get(name, 0.0) for name in row] for row in s.coef], dtype=np.float32)  # (4, 3)
    return ((x[0] + x[1] * dt[:, None]) + x[2] * dt2[:, None]) + x[3] * dt3[:, None]


def ardupilot_poly(params: Mapping[str, float], imu: int, x: np.ndarray) -> np.ndarray:
    """ArduPilot's ``p(x)`` (n, 3) m/s^2 of IMU ``imu``, float32."""
    names = ardupilot_imu(imu)
    c = np.array([[params.get(name, 0.0) for name in row] for row in names.acc], dtype=np.float32)  # (3, 3)
    xf = np.asarray(x, dtype=np.float32)[:, None]
    return (c[0] + (c[1] + c[2] * xf) * xf) * xf * np.float32(1.0 / ARDUPILOT_SCALE)


def ardupilot_correction(params: Mapping[str, float], imu: int, temps_c: np.ndarray, cal_temp_c: float) -> np.ndarray:
    """What ArduPilot subtracts (n, 3) m/s^2 from IMU ``imu``'s reading at ``temps_c``: ``p(T - 35) - p(Tcal -
    35)``, T and Tcal clamped to [TMIN, TMAX], float32; zero unless ``ENABLE`` is 1."""
    names = ardupilot_imu(imu)
    t = np.asarray(temps_c, dtype=np.float32)
    if int(params.get(names.enable, 0)) != 1:
        return np.zeros((len(t), 3), dtype=np.float32)
    tmin = np.float32(params.get(names.tmin, ARDUPILOT_DEFAULTS["TMIN"]))
    tmax = np.float32(params.get(names.tmax, ARDUPILOT_DEFAULTS["TMAX"]))
    tc = np.clip(np.array([cal_temp_c], dtype=np.float32), tmin, tmax)
    ref = np.float32(ARDUPILOT_TREF_C)
    return ardupilot_poly(params, imu, np.clip(t, tmin, tmax) - ref) - ardupilot_poly(params, imu, tc - ref)


# --- parameter files ------------------------------------------------------------------------------------------


def read_params_file(path: Path) -> dict[str, float]:
    """A vehicle's parameters as QGroundControl (``SYS COMP NAME VALUE TYPE``, tab separated), MAVProxy (``NAME
    VALUE``) or Mission Planner (``NAME,VALUE``) save them; ``#`` lines are comments; a later line for the same
    name wins. A line of none of these forms is an error naming the file and the line."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ThermocalError("not a text parameter file (not UTF-8)", path=str(path)) from None
    except OSError as e:
        raise ThermocalError(f"cannot read the parameter file ({e.strerror})", path=str(path)) from None
    out: dict[str, float] = {}
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = raw.rstrip("\r\n").split("\t")
        if len(fields) == 5:
            name, value = fields[2].strip(), fields[3].strip()
        else:
            parts = line.replace(",", " ").split()
            if len(parts) != 2:
                raise ThermocalError(
                    "not a parameter line (QGroundControl: 5 tab-separated fields; MAVProxy/ArduPilot: NAME VALUE)",
                    path=str(path),
                    where=f"line {n}",
                )
            name, value = parts
        try:
            number = float(int(value[2:], 16)) if value.lower().startswith("0x") else float(value)
        except ValueError:
            raise ThermocalError(
                f"parameter {name} has the value {value!r}, not a number", path=str(path), where=f"line {n}"
            ) from None
        if not math.isfinite(number):
            raise ThermocalError(f"parameter {name} is {value}", path=str(path), where=f"line {n}")
        out[name] = number
    return out


def detect_firmware(params: Mapping[str, float], path: str | None = None) -> str:
    """``px4`` when the parameters hold PX4's accelerometer tempcal (``TC_A*``), ``ardupilot`` for ArduPilot's
    (``INS_TCAL*``, ``INS<n>_TCAL_*``); an error when they hold neither or both."""
    px4 = any(k.startswith("TC_A") for k in params)
    ap = any(k.startswith("INS_TCAL") or (k.startswith("INS") and "_TCAL_" in k) for k in params)
    if px4 == ap:
        what = "both PX4 (TC_A*) and ArduPilot (INS_TCAL*)" if px4 else "no PX4 (TC_A*) or ArduPilot (INS_TCAL*)"
        raise ThermocalError(f"the parameter file holds {what} temperature calibration parameters", path=path)
    return "px4" if px4 else "ardupilot"
