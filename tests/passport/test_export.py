"""thermocal export (pipeline/passport/export.py, pipeline/passport/firmware.py): the PX4 and ArduPilot parameter
files, read back by evaluators written here from each firmware's documented behaviour (independent of the code
under test), correct the right accelerometer of a vehicle and leave its own settings alone; every option; the
stated residual; ``--compare``; the CSV.

The vehicle's reading before the temperature correction: its own accelerometer calibration (an offset and a gain per
axis, no cross-axis terms) made at a calibration temperature Tc, in the firmware's axes (``--rotation R``:
``v_fw = R v_unit``): ``r_i = g (u_i - U0_i(Tc)) / K0_ii`` with u, U0, K0 the passport's, rotated.

- PX4 (``TemperatureCompensation``): only with ``TC_A_ENABLE`` 1; the slot k of 0..3 whose ``TC_A<k>_ID`` (an int32
  parameter, compared as unsigned 32-bit) equals the accelerometer's device id, none for no match; float32
  ``dT = clamp(T, TMIN, TMAX) - TREF``, ``offset = X0 + X1 dT + X2 dT^2 + X3 dT^3`` (summed in that order,
  ``dT^2 = dT dT``, ``dT^3 = dT^2 dT``), subtracted; new offsets published only when T moved more than 1 C since the
  last publication (the first reading publishes).
- ArduPilot (``AP_InertialSensor_tempcal``): only with ``INS_TCAL<n>_ENABLE`` 1; float32 ``p(x) = (c1 + (c2 + c3 x)
  x) x 1e-6`` (``c_k = ACC<k>_*``); ``v - p(T' - 35) + p(Tc' - 35)``, T' and Tc' (``INS_ACC<n>_CALTEMP``) clamped
  to [TMIN, TMAX]; IMUs 4 and 5 named ``INS<n>_TCAL_*``, ``INS<n>_ACC_CALTEMP``.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate import tilt
from pipeline.calibrate.publish import publish
from pipeline.errors import RunFormatError, ThermocalError
from pipeline.io.runs import read_run, write_run
from pipeline.passport.document import build_passport, load_model
from pipeline.passport.export import ExportOptions, compare_params, export_passport, max_change
from pipeline.passport.firmware import read_params_file
from pipeline.passport.registry import Registry
from pipeline.positions import TEST_POSITIONS, VERIFICATION_POSITIONS, gravity_vector_g
from pipeline.run import RunMeta
from pipeline.simulate.chamber import SimConfig, simulate
from tests.conftest import run_main

F32 = np.float32
G_FW = 9.80665  # what 1 g reads on a vehicle after its own accelerometer calibration (CONSTANTS_ONE_G, GRAVITY_MSS)
UG = 1e6 / G_FW  # micro-g per m/s^2 of the vehicle
DEVICE = 3_000_000_000  # above 2^31: PX4's int32 parameter holds it negative
TEMPS = np.linspace(-40.0, 70.0, 221)


@pytest.fixture(scope="module")
def sim_run():
    return simulate(SimConfig(seed=11, program="short", rate_hz=1.0)).run


@pytest.fixture(scope="module")
def passports(sim_run):
    obs, _ = tilt.observe_run(sim_run)
    out = {}
    for kind in ("auto", "piecewise"):
        fit = tilt.fit_unit("AU-0001", obs, tilt.CalibrationSettings(thermal_model=kind), 20.0)
        doc = build_passport(fit, [], "unverified", g_local_mps2=9.80665, plateaus=[])
        out[kind] = json.loads(json.dumps(doc))
    return out


# --- the vehicle and the firmwares, written here -------------------------------------------------------------


def _rot(R=None):
    return np.eye(3) if R is None else np.asarray(R, dtype=float)


def vehicle_reading(doc: dict, temps, a_g, cal_temp_c: float, R=None) -> np.ndarray:
    """What the firmware corrects (n, 3) m/s^2: the unit's output at specific force ``a_g`` (g, firmware axes)
    through a per-axis accelerometer calibration made at ``cal_temp_c`` (which scales 1 g to G_FW, whatever the
    local gravity), in the axes ``R`` takes the unit's into."""
    model = load_model(doc)
    R = _rot(R)
    K, U0 = model.constants_at(np.atleast_1d(np.asarray(temps, dtype=float)))
    K0 = R @ np.asarray(model.K0) @ R.T
    _, U0c = model.constants_at(np.array([cal_temp_c]))
    u = np.einsum("ij,njk,lk,l->ni", R, K, R, np.asarray(a_g, dtype=float)) + U0 @ R.T
    return G_FW * (u - U0c @ R.T) / np.diag(K0)


def bias(doc, temps, cal_temp_c, R=None):
    """The reading at a = 0: the temperature bias relative to the calibration temperature (n, 3) m/s^2."""
    return vehicle_reading(doc, temps, np.zeros(3), cal_temp_c, R)


def qgc_params(text: str) -> dict[str, float]:
    """A QGroundControl parameter file: ``SYS COMP NAME VALUE TYPE`` tab separated, type 6 int32, 9 float."""
    rows = [line.split("\t") for line in text.splitlines() if line and not line.startswith("#")]
    assert all(len(r) == 5 and r[0] == "1" and r[1] == "1" and r[4] in ("6", "9") for r in rows)
    assert all(r[4] == "6" and r[3].lstrip("-").isdigit() for r in rows if r[2] in ("TC_A_ENABLE",) or "_ID" in r[2])
    return {r[2]: float(r[3]) for r in rows}


def mavproxy_params(text: str) -> dict[str, float]:
    return {k: float(v) for k, v in (line.split() for line in text.splitlines() if line and line[0] != "#")}


def px4_offsets(params: dict, device_id: int, temps, *, step_c: float | None = None) -> np.ndarray:
    """PX4's offsets (n, 3) for the accelerometer ``device_id`` along the temperature history ``temps``; with
    ``step_c`` the offsets are recomputed only when T moved more than that since the last recomputation."""
    temps = np.asarray(temps, dtype=float)
    zero = np.zeros((len(temps), 3))
    if int(params.get("TC_A_ENABLE", 0)) != 1:
        return zero
    slots = [k for k in range(4) if int(params.get(f"TC_A{k}_ID", 0)) % 2**32 == device_id]
    if not slots:
        return zero
    p = {k[len(f"TC_A{slots[0]}_") :]: v for k, v in params.items() if k.startswith(f"TC_A{slots[0]}_")}
    tref, tmin, tmax = F32(p.get("TREF", 25.0)), F32(p.get("TMIN", 0.0)), F32(p.get("TMAX", 100.0))

    def at(t):
        t = F32(t)
        dt = (tmax - tref) if t > tmax else (tmin - tref) if t < tmin else (t - tref)
        dt2 = dt * dt
        dt3 = dt2 * dt
        return [F32(p.get(f"X0_{i}", 0)) + F32(p.get(f"X1_{i}", 0)) * dt + F32(p.get(f"X2_{i}", 0)) * dt2
                + F32(p.get(f"X3_{i}", 0)) * dt3 for i in range(3)]  # fmt: skip

    out, last_t, last = [], None, None
    for t in temps:
        if step_c is None or last_t is None or abs(F32(t) - F32(last_t)) > step_c:
            last_t, last = t, at(t)
        out.append(last)
    return np.array(out, dtype=np.float64)


def ardupilot_correction(params: dict, imu: int, temps, cal_temp_c: float | None) -> np.ndarray:
    """What ArduPilot subtracts (n, 3) from IMU ``imu``'s reading; ``cal_temp_c`` None: the vehicle's
    ``CALTEMP`` from ``params`` (default -300, never recorded)."""
    pre, cal_name = (
        (f"INS_TCAL{imu}_", f"INS_ACC{imu}_CALTEMP") if imu <= 3 else (f"INS{imu}_TCAL_", f"INS{imu}_ACC_CALTEMP")
    )
    temps = np.asarray(temps, dtype=float)
    if int(params.get(pre + "ENABLE", 0)) != 1:
        return np.zeros((len(temps), 3))
    tmin, tmax = F32(params.get(pre + "TMIN", 0.0)), F32(params.get(pre + "TMAX", 70.0))
    c = [[F32(params.get(f"{pre}ACC{k}_{ax}", 0.0)) for ax in "XYZ"] for k in (1, 2, 3)]
    tc = F32(params.get(cal_name, -300.0) if cal_temp_c is None else cal_temp_c)

    def p(x):
        return [(c[0][i] + (c[1][i] + c[2][i] * x) * x) * x * F32(1e-6) for i in range(3)]

    tc = min(max(tc, tmin), tmax)
    out = []
    for t in temps:
        tt = min(max(F32(t), tmin), tmax)
        out.append([a - b for a, b in zip(p(tt - F32(35)), p(tc - F32(35)), strict=True)])
    return np.array(out, dtype=np.float64)


# --- PX4 -------------------------------------------------------------------------------------------------------


def test_px4_with_device_id_corrects_that_accelerometer_only(passports):
    doc = passports["auto"]
    exp = export_passport(doc, "px4", options=ExportOptions(px4_device_id=DEVICE))
    p = qgc_params(exp.text)
    assert p["TC_A_ENABLE"] == 1 and p["TC_A0_ID"] == DEVICE - 2**32  # int32 as PX4 stores it
    assert (p["TC_A0_TREF"], p["TC_A0_TMIN"], p["TC_A0_TMAX"]) == (20.0, -40.0, 70.0) and exp.warnings == []
    want = bias(doc, TEMPS, 20.0)
    assert np.abs(want).max() * UG > 5000  # a real thermal bias
    got = px4_offsets(p, DEVICE, TEMPS)
    err_ug = np.abs(got - want).max() * UG
    assert err_ug < 0.005, err_ug  # float32 parameters and arithmetic, a poly2 model: measured 0.002
    # another accelerometer, or the enable flag off: nothing corrected
    assert not px4_offsets(p, DEVICE + 1, TEMPS).any()
    assert not px4_offsets({**p, "TC_A_ENABLE": 0}, DEVICE, TEMPS).any()
    # outside TMIN..TMAX PX4 clamps: the offset stays at the end values
    ends = px4_offsets(p, DEVICE, np.array([-60.0, -40.0, 70.0, 90.0]))
    assert np.array_equal(ends[0], ends[1]) and np.array_equal(ends[2], ends[3])


def test_px4_instance_writes_that_slot_and_it_is_the_one_matched(passports):
    doc = passports["auto"]
    base = qgc_params(export_passport(doc, "px4", options=ExportOptions(px4_device_id=1234)).text)
    p = qgc_params(export_passport(doc, "px4", options=ExportOptions(px4_device_id=1234, instance=2)).text)
    assert sorted(p) == sorted(k.replace("TC_A0_", "TC_A2_") for k in base) and p["TC_A2_ID"] == 1234
    assert all(p[k.replace("TC_A0_", "TC_A2_")] == v for k, v in base.items())
    # loaded onto a vehicle whose slot 0 holds another accelerometer's calibration: slot 2 corrects this one
    vehicle = {**p, "TC_A0_ID": 99, "TC_A0_X0_0": 5.0, "TC_A0_X0_1": 5.0, "TC_A0_X0_2": 5.0}
    assert np.array_equal(px4_offsets(vehicle, 1234, TEMPS), px4_offsets(base, 1234, TEMPS))
    # the file says it replaces its slot (another accelerometer's calibration there is lost) and how to avoid it
    steps = export_passport(doc, "px4", options=ExportOptions(px4_device_id=1234, instance=2)).steps
    assert "it replaces the vehicle's TC_A2_* slot: when its TC_A2_ID is another accelerometer's" in steps[0]
    assert "--instance K of a slot whose TC_A<K>_ID is 0" in steps[0] and "enables every TC_A<K>_*" in steps[1]
    with pytest.raises(ThermocalError, match="slots 0..3"):
        export_passport(doc, "px4", options=ExportOptions(instance=4))


def test_px4_without_device_id_warns_that_nothing_is_corrected(passports):
    exp = export_passport(passports["auto"], "px4")
    p = qgc_params(exp.text)
    assert p["TC_A0_ID"] == 0 and p["TC_A_ENABLE"] == 1
    assert not any(px4_offsets(p, d, TEMPS).any() for d in (1, 0x8A0028, DEVICE))  # a real id is never 0
    assert len(exp.warnings) == 1 and "will not be applied" in exp.warnings[0]
    assert "--px4-device-id" in exp.warnings[0] and "\n" not in exp.warnings[0]
    assert exp.steps[0].startswith("set TC_A0_ID") and "# steps left to you on the vehicle:" in exp.text
    # QGroundControl refuses a file saved from another system id: the first column (1) is said
    assert (
        "MAV_SYS_ID" in exp.steps[1]
        and "set TC_A_ENABLE 1, reboot and load again" in exp.steps[1]
        and all(line.startswith("1\t1\t") for line in exp.text.splitlines()[-17:])
    )


def test_px4_update_step_is_in_the_stated_residual(passports):
    """PX4 along a slow ramp up and down (0.05 C steps), offsets recomputed only after a change of more than 1 C:
    the error this leaves is bounded by the residual's update step and close to it."""
    doc = passports["auto"]
    exp = export_passport(doc, "px4", options=ExportOptions(px4_device_id=7))
    p = qgc_params(exp.text)
    ramp = np.concatenate([np.arange(-40.0, 70.0, 0.05), np.arange(70.0, -40.0, -0.05)])
    lag = np.abs(px4_offsets(p, 7, ramp, step_c=1.0) - bias(doc, ramp, 20.0)).max(axis=0) * UG
    stated = np.array(exp.residual["update_step_max_ug"])
    assert np.all(lag <= stated * (1 + 1e-3) + 0.01) and np.all(lag > 0.9 * stated), (lag, stated)
    assert stated.max() > 100  # a real cost: hundreds of micro-g per 1 C on this unit
    assert exp.residual["temperature_cost_ug_per_c"] == exp.residual["update_step_max_ug"]


def test_px4_device_id_from_the_run_metadata(sim_run, tmp_path):
    """A run whose metadata records ``px4_accel_device_id``: calibrated and published, its provenance input keeps
    the id and the PX4 export writes it without --px4-device-id (which still wins); a bad id is refused on reading."""
    meta = dataclasses.replace(sim_run.meta, extra={**sim_run.meta.extra, "px4_accel_device_id": "0xB2D05E00"})
    path = write_run(dataclasses.replace(sim_run, meta=meta), tmp_path / "run.mcap")
    result = tilt.calibrate([read_run(path)], tilt.CalibrationSettings())
    out = publish(tmp_path / "reg", result, input_paths=[str(path)], settings=tilt.CalibrationSettings(), figure=False)
    doc = json.loads(Path(out["passport"]).read_text())
    assert doc["provenance"]["inputs"][0]["px4_accel_device_id"] == "0xB2D05E00"
    exp = export_passport(doc, "px4")
    p = qgc_params(exp.text)
    assert p["TC_A0_ID"] % 2**32 == DEVICE and exp.warnings == [] and not exp.steps[0].startswith("set TC_A0_ID")
    assert "from the run metadata (px4_accel_device_id)" in exp.notes["device"]
    assert qgc_params(export_passport(doc, "px4", options=ExportOptions(px4_device_id=77)).text)["TC_A0_ID"] == 77
    r = compare_params(doc, p)
    assert r["applied"] and r["device_id"] == DEVICE and max(r["max_diff_ug"]) < 0.01
    with pytest.raises(RunFormatError, match="px4_accel_device_id"):
        RunMeta.from_strings({**meta.to_strings(), "px4_accel_device_id": "accel0"}, path="x.mcap")


# --- ArduPilot -------------------------------------------------------------------------------------------------


def test_ardupilot_leaves_caltemp_to_the_vehicle(passports):
    """Without --set-caltemp the file holds no CALTEMP: on a vehicle that calibrated its accelerometers at 31.5 C
    (its offsets absorb the bias there, CALTEMP says 31.5) the correction removes the bias to float32 precision."""
    doc = passports["auto"]
    exp = export_passport(doc, "ardupilot")
    p = mavproxy_params(exp.text)
    assert not any("CALTEMP" in k for k in p) and all(k.startswith("INS_TCAL1_") for k in p)
    assert p["INS_TCAL1_ENABLE"] == 1 and (p["INS_TCAL1_TMIN"], p["INS_TCAL1_TMAX"]) == (-40.0, 70.0)
    for cal in (31.5, 20.0, -12.0):
        left = bias(doc, TEMPS, cal) - ardupilot_correction({**p, "INS_ACC1_CALTEMP": cal}, 1, TEMPS, None)
        assert np.abs(left).max() * UG < 0.01, (cal, np.abs(left).max() * UG)  # measured 0.004 micro-g
    # never recorded (-300): clamped to TMIN, the correction is off by the bias between TMIN and the calibration
    off = bias(doc, TEMPS, 31.5) - ardupilot_correction(p, 1, TEMPS, None)
    assert np.allclose(off, bias(doc, np.array([-40.0]), 31.5), atol=1e-7)
    # the enable flag off: nothing
    assert not ardupilot_correction({**p, "INS_TCAL1_ENABLE": 0}, 1, TEMPS, 31.5).any()


def test_ardupilot_set_caltemp_and_instances(passports):
    doc = passports["auto"]
    one = mavproxy_params(export_passport(doc, "ardupilot").text)
    p = mavproxy_params(export_passport(doc, "ardupilot", options=ExportOptions(set_caltemp=True)).text)
    assert p == {**one, "INS_ACC1_CALTEMP": 20.0}
    assert np.abs(bias(doc, TEMPS, 20.0) - ardupilot_correction(p, 1, TEMPS, None)).max() * UG < 0.01
    for n, prefix, cal in ((2, "INS_TCAL2_", "INS_ACC2_CALTEMP"), (4, "INS4_TCAL_", "INS4_ACC_CALTEMP")):
        q = mavproxy_params(export_passport(doc, "ardupilot", options=ExportOptions(instance=n, set_caltemp=True)).text)
        assert q[cal] == 20.0 and sorted(q) == sorted([cal, *(k.replace("INS_TCAL1_", prefix) for k in one)])
        assert np.array_equal(ardupilot_correction(q, n, TEMPS, None), ardupilot_correction(p, 1, TEMPS, None))
        assert not ardupilot_correction(q, 1, TEMPS, None).any()  # IMU 1 untouched
    with pytest.raises(ThermocalError, match="IMUs 1..5"):
        export_passport(doc, "ardupilot", options=ExportOptions(instance=6))
    with pytest.raises(ThermocalError, match="--set-caltemp goes with --format ardupilot"):
        export_passport(doc, "px4", options=ExportOptions(set_caltemp=True))


def test_ardupilot_states_loading_order_and_what_the_limits_clamp(passports):
    exp = export_passport(passports["auto"], "ardupilot", options=ExportOptions(instance=3))
    head = "\n".join(line for line in exp.text.splitlines() if line.startswith("#"))
    steps = [s.split(" ")[0] for s in exp.steps[:4]]
    assert steps == ["set", "reboot", "load", "reboot:"] and "INS_TCAL3_ENABLE to 1" in exp.steps[0]
    assert all(f"#   {k}. {s}" in head for k, s in enumerate(exp.steps, start=1))
    assert "INS_ACC3_CALTEMP" in exp.steps[4] and "redo the vehicle's accelerometer calibration" in exp.steps[4]
    assert "also clamp the gyroscope" in exp.notes["limits"] and "# limits: " in head
    assert exp.order.count("reboot") == 2 and "gyroscope" in exp.order and "\n" not in exp.order
    # TMIN/TMAX are limited to ArduPilot's -70..80 C; the part outside is said not held
    wide = export_passport(dict(passports["auto"], valid_temp_c=[-80.0, 85.0]), "ardupilot")
    p = mavproxy_params(wide.text)
    assert (p["INS_TCAL1_TMIN"], p["INS_TCAL1_TMAX"]) == (-70.0, 80.0) and any("-70..80" in t for t in wide.not_held)


# --- both: rotation, notes, residual ---------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["px4", "ardupilot"])
def test_rotation_by_name_number_or_matrix(passports, fmt):
    """ROTATION_YAW_90 (v' = Rz(90) v: x' = -y, y' = x): the same parameters by name, number and matrix; the
    firmware's correction equals the bias of the rotated unit; x's coefficients are minus the unrotated y's."""
    doc = passports["auto"]
    read = qgc_params if fmt == "px4" else mavproxy_params
    extra = {"px4_device_id": 5} if fmt == "px4" else {"set_caltemp": True}
    files = {
        spec: read(export_passport(doc, fmt, options=ExportOptions(rotation=spec, **extra)).text)
        for spec in ("ROTATION_YAW_90", "yaw_90", "2", "0,-1,0, 1,0,0, 0,0,1", None)
    }
    assert files["ROTATION_YAW_90"] == files["yaw_90"] == files["2"] == files["0,-1,0, 1,0,0, 0,0,1"]
    p, plain = files["ROTATION_YAW_90"], files[None]
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    got = px4_offsets(p, 5, TEMPS) if fmt == "px4" else ardupilot_correction(p, 1, TEMPS, None)
    assert np.abs(got - bias(doc, TEMPS, 20.0, R)).max() * UG < 0.01
    names = [k for k in p if k.endswith(("_0", "_X")) and ("ACC" in k or "_X" in k[-5:])]
    for k in names:
        ky = k[:-1] + ("1" if k.endswith("0") else "Y")
        assert p[k] == pytest.approx(-plain[ky], rel=1e-6, abs=1e-12), k
    exp = export_passport(doc, fmt, options=ExportOptions(rotation="ROTATION_ROLL_180", **extra))
    assert "ROTATION_ROLL_180" in exp.notes["axes"] and exp.rotation == [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
    for bad, says in (("ROTATION_SIDEWAYS", "unknown rotation"), ("1,0,0,0,1,0,0,0,2", "not orthonormal")):
        with pytest.raises(ThermocalError, match=says):
            export_passport(doc, fmt, options=ExportOptions(rotation=bad))


@pytest.mark.parametrize("fmt", ["px4", "ardupilot"])
def test_every_file_states_steps_temperature_axes_and_residual(passports, fmt):
    exp = export_passport(passports["auto"], fmt, options=ExportOptions(instance=1))
    head = [line for line in exp.text.splitlines() if line.startswith("#")]
    text = "\n".join(head)
    assert any("redo the vehicle's accelerometer calibration" in s and "20 C" in s for s in exp.steps)
    assert "thermosensor" in exp.notes["temperature"] and "die temperature" in exp.notes["temperature"]
    assert "costs up to" in exp.notes["temperature"] and "--rotation" in exp.notes["axes"]
    for v in exp.notes.values():
        assert any(v in line for line in head)
    assert "#   cross-axis terms at T0 (the vehicle's calibration is per axis): " in text
    assert ("#   PX4's 1 C update step: " in text) == (fmt == "px4")
    summary = exp.summary_text("x.params", "AU-0001 v1")
    assert "steps left to you on the vehicle:" in summary and "residual over -40..70 C" in summary
    assert all(s in summary for s in exp.steps) and all(v in summary for v in exp.notes.values())


def test_stated_residual_is_the_error_left_on_the_vehicle(passports):
    """Readings of the passport's full model (gains and cross-axis terms varying with T) through the vehicle's
    per-axis calibration at T0, corrected by PX4 along a ramp (1 C update step): the error left is bounded by the
    stated worst total and close to it; the bias part alone is exact."""
    doc = passports["auto"]
    exp = export_passport(doc, "px4", options=ExportOptions(px4_device_id=9))
    p = qgc_params(exp.text)
    ramp = np.concatenate([np.arange(-40.0, 70.0, 0.1), np.arange(70.0, -40.0, -0.1)])
    offsets = px4_offsets(p, 9, ramp, step_c=1.0)
    g = G_FW
    worst, thermal = 0.0, 0.0
    for pos in [*TEST_POSITIONS, *VERIFICATION_POSITIONS]:
        a = gravity_vector_g(pos)
        err = vehicle_reading(doc, ramp, a, 20.0) - offsets - g * a
        worst = max(worst, float(np.abs(err).max()))
        # less what the vehicle's reading at T0 already had at that orientation (the cross-axis terms at T0)
        at_t0 = vehicle_reading(doc, np.array([20.0]), a, 20.0) - g * a
        thermal = max(thermal, float(np.abs(err - at_t0).max()))
    stated = exp.residual["total_worst_mps2"]
    assert 0.3 * stated < worst <= stated * (1 + 1e-6), (worst, stated)
    stated_thermal = exp.residual["temperature_worst_ug"] / UG
    assert 0.3 * stated_thermal < thermal <= stated_thermal * (1 + 1e-6) < 0.2 * stated, (thermal, stated_thermal)
    assert max(exp.residual["bias_fit_max_ug"]) < 0.005 and any("beta" in t and "gamma" in t for t in exp.not_held)


def test_offsets_are_in_the_vehicles_g_not_the_local_gravity(passports):
    """A vehicle's accelerometer calibration scales 1 g to 9.80665 m/s^2 (PX4's CONSTANTS_ONE_G, ArduPilot's
    GRAVITY_MSS): a passport made where g is 9.7803 gives the same offsets (was scaled by 9.7803 / 9.80665: 0.27 %,
    36 micro-g of a 13 300 micro-g bias, against a stated fit error of 0.002 micro-g)."""
    doc = passports["auto"]
    equator = dict(doc, g_local_mps2=9.7803)
    for fmt, read in (("px4", qgc_params), ("ardupilot", mavproxy_params)):
        opts = ExportOptions(px4_device_id=9) if fmt == "px4" else None
        assert read(export_passport(equator, fmt, options=opts).text) == read(
            export_passport(doc, fmt, options=opts).text
        )
    p = qgc_params(export_passport(equator, "px4", options=ExportOptions(px4_device_id=9)).text)
    rel = px4_offsets(p, 9, TEMPS) - px4_offsets(p, 9, [20.0])
    assert np.abs(rel - bias(equator, TEMPS, 20.0)).max() * UG < 0.005


def test_piecewise_model_states_its_cubic_fit_error(passports):
    doc = passports["piecewise"]
    exp = export_passport(doc, "px4", options=ExportOptions(px4_device_id=1))
    temps = np.linspace(-40, 70, 1101)
    fit_err = np.abs(px4_offsets(qgc_params(exp.text), 1, temps) - bias(doc, temps, 20.0)).max(axis=0)
    assert np.all(fit_err > 1e-7)  # a cubic cannot follow the kinks
    assert np.allclose(fit_err, exp.residual["bias_fit_max_mps2"], rtol=1e-3, atol=1e-9)
    assert any("piecewise" in t for t in exp.not_held)


# --- --compare -------------------------------------------------------------------------------------------------


def test_compare_evaluates_a_vehicles_parameters_as_the_firmware_does(passports, tmp_path):
    doc, other = passports["auto"], passports["piecewise"]
    own = tmp_path / "own.params"
    own.write_text(export_passport(doc, "px4", options=ExportOptions(px4_device_id=DEVICE, instance=1)).text)
    r = compare_params(doc, read_params_file(own), options=ExportOptions(px4_device_id=DEVICE))
    assert r["firmware"] == "px4" and r["applied"] and r["instance"] == 1 and r["device_id"] == DEVICE
    assert max(r["max_diff_ug"]) < 0.01
    # another passport's file: the difference is what the evaluator written here finds
    theirs = tmp_path / "theirs.params"
    theirs.write_text(export_passport(other, "px4", options=ExportOptions(px4_device_id=DEVICE)).text)
    p = read_params_file(theirs)
    grid = np.linspace(-40, 70, 1101)
    held = px4_offsets(p, DEVICE, grid) - px4_offsets(p, DEVICE, np.array([20.0]))
    want = np.abs(held - bias(doc, grid, 20.0)).max(axis=0) * UG
    r = compare_params(doc, p, options=ExportOptions(px4_device_id=DEVICE))
    assert np.allclose(r["max_diff_ug"], want, rtol=1e-4, atol=0.01) and min(want) > 1
    # disabled, or an id of no accelerometer: not applied, the whole bias is the difference
    for change, says in (({"TC_A_ENABLE": 0}, "TC_A_ENABLE is 0"), ({"TC_A0_ID": 0}, "no TC_A<k>_ID equals")):
        r = compare_params(doc, {**p, **change}, options=ExportOptions(px4_device_id=DEVICE))
        assert not r["applied"] and says in r["why_not"]
        assert np.allclose(r["max_diff_ug"], np.abs(bias(doc, grid, 20.0)).max(axis=0) * UG, rtol=1e-6)
    # ArduPilot as MAVProxy saves it, with the vehicle's CALTEMP; as Mission Planner saves it (NAME,VALUE)
    ap = export_passport(doc, "ardupilot", options=ExportOptions(instance=2)).text + "INS_ACC2_CALTEMP 31.5\n"
    (tmp_path / "ap.parm").write_text(ap)
    (tmp_path / "mp.param").write_text(ap.replace(" ", ",").replace("#,", "# "))
    for name in ("ap.parm", "mp.param"):
        r = compare_params(doc, read_params_file(tmp_path / name), options=ExportOptions(instance=2))
        assert r["firmware"] == "ardupilot" and r["applied"] and r["calibration_temp_c"] == 31.5
        assert max(r["max_diff_ug"]) < 0.01, r["max_diff_ug"]
    # a vehicle as QGroundControl saves it, its accelerometer's slot not slot 0, no device id given: the slot whose
    # ID is one of the vehicle's accelerometers (CAL_ACC<n>_ID) is the one PX4 uses and the one compared
    qgc = "# Onboard parameters for Vehicle 1\n#\n# Stack: PX4 Pro\n# Vehicle-Id Component-Id Name Value Type\n"
    qgc += f"1\t1\tCAL_ACC0_ID\t{DEVICE - 2**32}\t6\n1\t1\tCAL_ACC1_ID\t1310996\t6\n1\t100\tCAM_X\t3.5\t9\n"
    body = export_passport(doc, "px4", options=ExportOptions(px4_device_id=DEVICE, instance=2)).text
    (tmp_path / "vehicle.params").write_text(qgc + body)
    vehicle = read_params_file(tmp_path / "vehicle.params")
    r = compare_params(doc, vehicle)
    assert r["applied"] and r["instance"] == 2 and r["device_id"] == DEVICE and max(r["max_diff_ug"]) < 0.01
    assert any(n.startswith("TC_A2_* compared: the first slot whose ID is one of the vehicle's") for n in r["notes"])
    # ... and a slot whose ID is none of the vehicle's accelerometers is not applied: the whole bias stays
    other = {**vehicle, "CAL_ACC0_ID": 1310988.0}
    r = compare_params(doc, other)
    assert not r["applied"] and r["instance"] == 0 and "TC_A0_ID is 0" in r["why_not"]
    assert np.allclose(r["max_diff_ug"], np.abs(bias(doc, grid, 20.0)).max(axis=0) * UG, rtol=1e-6)
    (tmp_path / "bad.parm").write_text("INS_TCAL1_ENABLE 1\nINS_TCAL1_TMIN 1 2\n")
    with pytest.raises(ThermocalError) as info:
        read_params_file(tmp_path / "bad.parm")
    assert "bad.parm" in str(info.value) and "line 2" in str(info.value)


# --- the command -----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def registry(passports, tmp_path_factory):
    reg = Registry(tmp_path_factory.mktemp("export") / "reg")
    reg.publish(passports["auto"], inputs=[{"path": "a", "sha256": "a" * 64}], settings={}, code_version="t")
    reg.publish(passports["piecewise"], inputs=[{"path": "b", "sha256": "b" * 64}], settings={}, code_version="t")
    reg.approve("AU-0001", 1, "A. Metrologist")
    failed = dict(passports["auto"], status="fail")
    reg.publish(
        {k: v for k, v in failed.items() if k not in ("signature", "content_sha256")},
        inputs=[{"path": "c", "sha256": "c" * 64}],
        settings={},
        code_version="t",
    )
    return reg


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("thermocal: ") and "signing key" not in line]


def test_cli_px4_device_id_instance_and_the_warning_without_id(monkeypatch, capsys, registry, tmp_path):
    out = tmp_path / "au1.params"
    reg = str(registry.root)
    code, stdout, err = run_main(
        monkeypatch, capsys, "export", "AU-0001", "--registry", reg, "--format", "px4",
        "--px4-device-id", "0xB2D05E00", "--instance", "1", "--out", str(out),
    )  # fmt: skip
    assert code == 0 and _warnings(err) == [
        "thermocal: PX4 uses this file only in this order: load it, reboot, redo the vehicle's accelerometer "
        "calibration with the IMU between -40 and 70 C (best near T0 = 20 C)"
    ], err  # what is left to do, on stderr too (contract.md: was in the file and stdout alone)
    p = qgc_params(out.read_text())
    assert p["TC_A_ENABLE"] == 1 and p["TC_A1_ID"] % 2**32 == DEVICE and "TC_A0_ID" not in p
    assert stdout.startswith(f"wrote {out} (px4, AU-0001 v1") and "steps left to you on the vehicle:" in stdout
    assert "redo the vehicle's accelerometer calibration" in stdout and "PX4's 1 C update step" in stdout
    code, stdout, err = run_main(monkeypatch, capsys, "export", "AU-0001", "--registry", reg, "--format", "px4")
    assert code == 0 and stdout.startswith("# PX4 thermal compensation (TC_A0_*)")
    line, order = _warnings(err)
    assert line.startswith("thermocal: warning: the PX4 file will not be applied: TC_A0_ID is 0")
    assert order.startswith("thermocal: PX4 uses this file only in this order: set TC_A0_ID to the accelerometer's")
    for bad, says in (
        (("--format", "px4", "--px4-device-id", "twelve"), "--px4-device-id"),
        (("--format", "csv", "--instance", "1"), "--instance goes with"),
        (("--format", "px4", "--rotation", "ROTATION_SIDEWAYS"), "unknown rotation"),
        ((), "give --format"),
        (("--format", "px4", "--instance", "4"), "--instance: PX4 has accelerometer slots 0..3"),
        (("--format", "ardupilot", "--instance", "0"), "--instance: ArduPilot has IMUs 1..5"),
        (("--format", "px4", "--out", str(tmp_path / "no" / "such" / "dir.params")), "cannot write the export"),
    ):
        code, stdout, err = run_main(monkeypatch, capsys, "export", "AU-0001", "--registry", reg, *bad)
        assert code == 2 and stdout == "" and len(_warnings(err)) == 1 and says in err, (bad, err)


def test_cli_ardupilot_order_on_stderr_and_json(monkeypatch, capsys, registry, tmp_path):
    out = tmp_path / "au1.parm"
    reg = str(registry.root)
    code, stdout, err = run_main(
        monkeypatch, capsys, "export", "AU-0001", "--registry", reg, "--format", "ardupilot", "--instance", "2",
        "--out", str(out), "--json",
    )  # fmt: skip
    assert code == 0
    (line,) = _warnings(err)
    assert line.startswith("thermocal: ArduPilot reads this file only in this order: set INS_TCAL2_ENABLE 1, reboot")
    assert line.endswith("then check INS_ACC2_CALTEMP: if it is -300 or outside -40 .. 70 C, redo the vehicle's "
                         "accelerometer calibration with the IMU in that range")  # fmt: skip
    summary = json.loads(stdout)
    assert summary["version"] == 1 and summary["passport_used"]["approved_by"] == ["A. Metrologist"]
    assert summary["loading_order"] in line and summary["params"]["INS_TCAL2_ENABLE"] == 1
    assert "INS_ACC2_CALTEMP" not in out.read_text().replace("# ", "#").split("\n#")[-1]
    assert "# status unverified; approved by A. Metrologist" in out.read_text()
    # a failed version: exported all the same, with a warning line and the status in the file
    code, stdout, err = run_main(monkeypatch, capsys, "export", "AU-0001", "3", "--registry", reg, "--format", "csv")
    (line,) = _warnings(err)
    assert code == 0 and line.startswith("thermocal: warning: export of AU-0001 v3 failed its verification")
    # --compare: the file just written against v2 (piecewise), JSON and text
    code, stdout, err = run_main(
        monkeypatch, capsys, "export", "AU-0001", "2", "--registry", reg, "--compare", str(out), "--instance", "2",
        "--json",
    )  # fmt: skip
    r = json.loads(stdout)
    assert code == 0 and r["firmware"] == "ardupilot" and r["applied"] and 1 < max(r["max_diff_ug"]) < 1e4
    assert r["passport_used"]["version"] == 2 and r["calibration_temp_c"] == 20.0
    code, stdout, err = run_main(monkeypatch, capsys, "export", "AU-0001", "--registry", reg, "--compare", str(out))
    assert code == 0 and "the vehicle's correction is NOT applied: INS_TCAL1_ENABLE is 0" in stdout
    code, stdout, err = run_main(
        monkeypatch, capsys, "export", "AU-0001", "--registry", reg, "--compare", str(out), "--format", "px4"
    )
    assert code == 2 and "ArduPilot parameters, not px4" in err and str(out) in err


def test_firmware_files_refuse_or_warn_what_the_firmware_cannot_take(passports):
    """A passport valid at one temperature (no temperature model) is refused for PX4 and ArduPilot (it wrote ENABLE
    1 with TMIN = TMAX, which clamps a vehicle's own ArduPilot gyroscope correction to that temperature), not for
    CSV; a valid range beyond ArduPilot's -70..80 C is clipped with a warning line (was the header alone), refused
    when nothing is left (was TMIN 85 > TMAX 80); the ArduPilot file is not one QGroundControl loads."""
    doc = passports["auto"]
    one = dict(doc, valid_temp_c=[20.0, 20.0])
    for fmt in ("px4", "ardupilot"):
        with pytest.raises(ThermocalError, match="valid at one temperature only"):
            export_passport(one, fmt)
    assert export_passport(one, "csv").text.startswith("quantity,")
    wide = export_passport(dict(doc, valid_temp_c=[-60.0, 100.0]), "ardupilot")
    p = mavproxy_params(wide.text)
    assert (p["INS_TCAL1_TMIN"], p["INS_TCAL1_TMAX"]) == (-60.0, 80.0)
    (w,) = wide.warnings
    assert w.startswith("INS_TCAL1_TMIN/INS_TCAL1_TMAX written as -60 .. 80 C, not the passport's valid -60 .. 100 C")
    with pytest.raises(ThermocalError, match="outside the -70 .. 80 C"):
        export_passport(dict(doc, valid_temp_c=[85.0, 120.0]), "ardupilot")
    assert "not QGroundControl" in wide.steps[2] and export_passport(doc, "ardupilot").warnings == []


def test_ardupilot_qgc_form_loads_in_qgroundcontrol(passports, tmp_path):
    """QGroundControl loads only ``SYS COMP NAME VALUE TYPE`` tab-separated lines and a parameter only with the
    vehicle's type (ArduPilot's ENABLE an int8, 2; the rest float, 9): ``--qgc`` writes that form, with the same
    values (float32) as the NAME VALUE form, and --compare reads it back; the NAME VALUE file sends QGroundControl
    users to --qgc."""
    doc = passports["auto"]
    plain = export_passport(doc, "ardupilot", options=ExportOptions(instance=2, set_caltemp=True))
    qgc = export_passport(doc, "ardupilot", options=ExportOptions(instance=2, set_caltemp=True, qgc=True))
    rows = [line.split("\t") for line in qgc.text.splitlines() if line and not line.startswith("#")]
    assert all(len(r) == 5 and r[:2] == ["1", "1"] and len(r[2]) <= 16 for r in rows)
    assert [r[2:] for r in rows if r[4] != "9"] == [["INS_TCAL2_ENABLE", "1", "2"]]
    mav = mavproxy_params(plain.text)
    assert {r[2]: F32(float(r[3])) for r in rows} == {k: F32(v) for k, v in mav.items()}
    assert "QGroundControl: Vehicle Setup" in qgc.steps[2] and "export with --qgc" in plain.steps[2]
    (tmp_path / "v.params").write_text(qgc.text)
    r = compare_params(doc, read_params_file(tmp_path / "v.params"), options=ExportOptions(instance=2))
    assert r["applied"] and max(r["max_diff_ug"]) < 0.01, r
    with pytest.raises(ThermocalError, match="--qgc goes with --format ardupilot"):
        export_passport(doc, "px4", options=ExportOptions(qgc=True))


def test_cli_out_never_replaces_the_passport_or_a_registry_record(monkeypatch, capsys, registry, tmp_path):
    """--out on the passport file read, or on a file of a registry's unit folder, is refused in one line and the
    registry still verifies (the passport was replaced by the parameter file, exit 0, before)."""
    reg = registry.root
    v1 = reg / "units" / "AU-0001" / "v0001.json"
    before = {p: p.read_bytes() for p in (reg / "units" / "AU-0001").iterdir()}
    for args in (
        (str(v1), "--format", "px4", "--out", str(v1)),
        ("AU-0001", "--registry", str(reg), "--format", "csv", "--out", str(v1.with_name("log.jsonl"))),
        ("AU-0001", "--registry", str(reg), "--format", "ardupilot", "--out", str(v1.with_name("AU-0001.parm"))),
    ):
        code, stdout, err = run_main(monkeypatch, capsys, "export", *args)
        assert code == 2 and stdout == "" and len(_warnings(err)) == 1 and "--out" in err, (args, err)
    assert {p: p.read_bytes() for p in (reg / "units" / "AU-0001").iterdir()} == before
    assert registry.verify().ok
    code, _, err = run_main(monkeypatch, capsys, "export", str(v1), "--format", "csv", "--out", str(tmp_path / "a"))
    assert code == 0 and (tmp_path / "a").read_text().startswith("quantity,"), err


def test_cli_a_failed_write_leaves_the_previous_file(monkeypatch, capsys, registry, tmp_path):
    """The disk filling up in the middle of writing --out: exit 2 in one line, the previous export there unchanged
    and no partial parameter file (was: the first half of the new file, which would load part of the parameters)."""
    out = tmp_path / "au1.params"
    args = ("export", "AU-0001", "--registry", str(registry.root), "--format", "px4", "--out", str(out))
    assert run_main(monkeypatch, capsys, *args, "--px4-device-id", "7")[0] == 0
    before = out.read_bytes()
    real = Path.write_text

    def half_then_full(self, data, *a, **k):
        real(self, data[: len(data) // 2], *a, **k)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", half_then_full)
    code, stdout, err = run_main(monkeypatch, capsys, *args, "--px4-device-id", "8")
    monkeypatch.undo()
    assert code == 2 and len(_warnings(err)) == 1 and "No space left on device" in err, err
    assert out.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["au1.params"]


# --- CSV -------------------------------------------------------------------------------------------------------


def test_failed_passport_states_its_status_in_every_format(passports):
    doc = dict(passports["auto"], status="fail")
    for fmt in ("px4", "ardupilot"):
        head = [line for line in export_passport(doc, fmt).text.splitlines() if line.startswith("#")]
        assert "# status fail; approval unknown (not read from a registry)" in head
        assert any(line.startswith("# WARNING: this passport failed its verification") for line in head)
    rows = {r["quantity"]: r for r in csv.DictReader(io.StringIO(export_passport(doc, "csv").text))}
    assert rows["status"]["value"] == "fail" and rows["approval"]["value"].startswith("approval unknown")


def test_csv_holds_every_number_with_its_uncertainty(passports):
    doc = passports["auto"]
    rows = list(csv.DictReader(io.StringIO(export_passport(doc, "csv").text)))
    by = {(r["quantity"], r["key"], r["order"]): r for r in rows}
    assert float(by[("K", "xy", "")]["value"]) == doc["coefficients"]["K"][0][1]
    assert float(by[("K", "xy", "")]["std_uncertainty"]) == doc["uncertainty"]["coefficients"]["K"][0][1]
    assert float(by[("U0", "z", "")]["value"]) == doc["coefficients"]["U0"][2]
    assert float(by[("alpha", "x", "2")]["value"]) == doc["thermal_model"]["alpha"]["x"][1]
    assert float(by[("gamma", "zy", "1")]["std_uncertainty"]) == doc["uncertainty"]["thermal_model"]["gamma"]["zy"][0]
    assert by[("valid_temp_c", "", "")]["t_lo_c"] == "-40.0"
    assert len([r for r in rows if r["quantity"] in ("alpha", "beta", "gamma")]) == 24
    pw = list(csv.DictReader(io.StringIO(export_passport(passports["piecewise"], "csv").text)))
    assert len([r for r in pw if r["quantity"] == "alpha"]) == 6 and all(
        r["t_lo_c"] for r in pw if r["quantity"] == "beta"
    )


def test_max_change_over_a_valid_range_of_one_temperature():
    """A passport valid at one temperature only (lo == hi: a grid of two equal points) changes by nothing over it
    (was a ZeroDivisionError, exit 3); on a 0.5 C grid the largest change within 1 C is two steps'."""
    assert max_change(np.ones((2, 3)), np.array([20.0, 20.0])).tolist() == [0.0, 0.0, 0.0]
    temps = np.arange(0.0, 3.01, 0.5)
    values = np.stack([temps, 2 * temps, temps**2], axis=1)
    np.testing.assert_allclose(max_change(values, temps, span_c=1.0), [1.0, 2.0, 9.0 - 4.0], rtol=0, atol=1e-12)
