"""``thermocal export UNIT [V] --format px4|ardupilot|csv``: a passport in a format flight software or a
spreadsheet loads; ``--compare PARAMS_FILE``: a vehicle's existing temperature calibration against the passport."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from pipeline.errors import ThermocalError
from pipeline.io.files import write_text_whole

from .app import (
    REGISTRY_HELP,
    UNIT_OR_FILE_HELP,
    JsonFlag,
    UnverifiedFlag,
    app,
    emit,
    passport_in_use,
    refuse_out_over_inputs,
    warn,
)


def _device_id(text: str | None) -> int | None:
    """``--px4-device-id``: decimal or 0x-hexadecimal."""
    if text is None:
        return None
    try:
        return int(text.strip(), 0)
    except ValueError:
        raise ThermocalError(
            f"{text!r} is not a device id (a number, decimal or 0x hexadecimal)", where="--px4-device-id"
        ) from None


@app.command()
def export(
    unit: str = typer.Argument(..., metavar="UNIT|FILE", help=UNIT_OR_FILE_HELP),
    version: int | None = typer.Argument(
        None,
        metavar="V",
        help="version number (default: the unit's current passport: its newest approved version, else its newest "
        "that did not fail)",
    ),
    registry: Path | None = typer.Option(None, "--registry", help=REGISTRY_HELP),
    fmt: str | None = typer.Option(
        None,
        "--format",
        help="px4 (TC_A<K>_* parameters, a QGroundControl file) | ardupilot (INS_TCAL<K>_* parameters) | csv (every "
        "constant and coefficient); with --compare, the firmware is read from the file",
    ),
    out: Path | None = typer.Option(None, "--out", help="write the file here (default: print it)"),
    px4_device_id: str | None = typer.Option(
        None,
        "--px4-device-id",
        metavar="N",
        help="PX4: the device id of the accelerometer to correct (its CAL_ACC<n>_ID, or device_id in 'listener "
        "sensor_accel'), decimal or 0x hexadecimal; written as TC_A<K>_ID with TC_A_ENABLE 1. Default: the id the "
        "run metadata recorded (px4_accel_device_id), else 0, and the file corrects nothing",
    ),
    instance: int | None = typer.Option(
        None,
        "--instance",
        metavar="K",
        help="PX4: the parameter slot TC_A<K>_* (0..3, default 0); ArduPilot: the IMU INS_TCAL<K>_* (1..3, or 4, 5 "
        "for INS4_/INS5_TCAL_*; default 1)",
    ),
    set_caltemp: bool = typer.Option(
        False,
        "--set-caltemp",
        help="ArduPilot: also write INS_ACC<K>_CALTEMP = the passport's T0 (it belongs to the vehicle's own "
        "accelerometer calibration, which writes it: only when the vehicle's accelerometer offsets and scales are "
        "this passport's T0 constants)",
    ),
    qgc: bool = typer.Option(
        False,
        "--qgc",
        help="ArduPilot: write QGroundControl's tab-separated parameter file (it loads no other form) instead of "
        "NAME VALUE lines (MAVProxy, Mission Planner)",
    ),
    rotation: str | None = typer.Option(
        None,
        "--rotation",
        metavar="R",
        help="the unit's axes in the firmware's accelerometer frame: a rotation name of the firmware (e.g. "
        "ROTATION_ROLL_180, ROTATION_YAW_90) or its number, or nine numbers 'r11,r12,...,r33' (the matrix taking "
        "the unit's x, y, z into the IMU's axes, row by row); default: they are the same",
    ),
    compare: Path | None = typer.Option(
        None,
        "--compare",
        metavar="PARAMS_FILE",
        help="evaluate a vehicle's existing PX4 or ArduPilot temperature calibration (a parameter file as "
        "QGroundControl or MAVProxy saves it) against the passport over its valid range: the largest difference "
        "per axis, micro-g; writes nothing",
    ),
    unverified: UnverifiedFlag = False,
    as_json: JsonFlag = False,
):
    """The passport in a format flight software or a spreadsheet loads, with the steps left to you on the vehicle,
    what the format cannot hold and the error that leaves over the passport's valid temperature range."""
    from pipeline.passport.export import ExportOptions, compare_params, compare_text, export_passport
    from pipeline.passport.firmware import read_params_file

    if compare is None and fmt is None:
        raise ThermocalError("give --format px4|ardupilot|csv (or --compare PARAMS_FILE)", where="--format")
    if compare is not None and out is not None:
        raise ThermocalError("--compare writes nothing: leave out --out", where="--compare")
    options = ExportOptions(_device_id(px4_device_id), instance, set_caltemp, rotation, qgc)
    if out is not None:  # never over the passport read or a registry's records
        refuse_out_over_inputs(out, [Path(unit)] if registry is None else [], registry)
    doc, state = passport_in_use(unit, version, registry, unverified)  # verified, or refused in one line
    if compare is not None:
        params = read_params_file(compare)
        result = compare_params(doc, params, fmt=fmt, options=options, path=str(compare))
        if state.warning():
            warn(f"comparison with {state.warning()}")
        emit({**result, "passport_used": state.as_dict()}, as_json, compare_text(result, str(compare), state.text()))
        return
    assert fmt is not None
    exp = export_passport(doc, fmt, state=state, options=options)
    if out is not None:  # before the warnings: a file that cannot be written is the one line on stderr
        write_text_whole(out, exp.text, "export", make_folder=False)  # whole or not at all
    if state.warning():
        warn(f"export of {state.warning()}")
    for line in exp.warnings:
        warn(line)
    if exp.order:
        print(f"thermocal: {exp.order}", file=sys.stderr)
    if as_json:
        emit(
            {
                **exp.summary(),
                "passport_used": state.as_dict(),
                "out": str(out) if out else None,
                "text": None if out else exp.text,
            },
            True,
        )
    elif out is None:
        sys.stdout.write(exp.text)
        sys.stdout.flush()
    else:
        emit(None, False, exp.summary_text(str(out), state.text()))
