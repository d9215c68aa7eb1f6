"""``thermocal calibrate RUN...``: one unit's runs into a new passport version (the Prefect flow
:func:`flows.calibrate.calibrate_flow`, run by :func:`flows.calibrate.run_calibrate`); a run holding several units:
one passport per unit."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer

from pipeline.calibrate.methods import names as method_names
from pipeline.errors import ThermocalError

from .app import (
    REGISTRY_HELP,
    GradeOption,
    JsonFlag,
    app,
    calibration_settings,
    check_method,
    emit,
    needs_base,
)


@app.command()
def calibrate(
    runs: list[Path] = typer.Argument(
        ..., metavar="RUN", help="runs of one unit (.mcap files or Parquet run directories)"
    ),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    thermal_model: str = typer.Option(
        "auto",
        "--thermal-model",
        help="temperature model of the constants: poly1 | poly2 | poly3 "
        "(polynomial of that order) | piecewise (linear between "
        "plateaus); auto: the highest order the plateaus allow, at "
        "most 3",
    ),
    constants_method: str = typer.Option(
        "auto",
        "--constants-method",
        help="how the constants are solved per plateau: six_position "
        "(closed form from TP1..TP6) | least_squares (every "
        "position) | auto",
    ),
    grade: GradeOption = None,
    tol_normal_g: float | None = typer.Option(
        None,
        "--tol-normal-g",
        help="pass limit of the gravity-module error |dg| at the normal temperature, g (default: the grade's)",
    ),
    tol_range_g: float | None = typer.Option(
        None,
        "--tol-range-g",
        help="pass limit of |dg| over the rest of the temperature range, g (default: the grade's)",
    ),
    method: str = typer.Option(
        "auto",
        "--method",
        help="auto (default: the method the recording supports, as inspect "
        f"says, and the result says which) | {' | '.join(method_names())} "
        "(inspect RUN says what each needs and determines)",
    ),
    base_passport: Path | None = typer.Option(
        None,
        "--base-passport",
        help="differential: normal-temperature passport to start from "
        "(default: the unit's current passport in the registry: its "
        "newest approved version, else its newest that did not fail, not made by the "
        "differential method and not failed; without one, the constants "
        "the orientations determine by themselves)",
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="compute and print everything, write nothing to the registry"
    ),
    unit: list[str] = typer.Option(
        [],
        "--unit",
        metavar="SERIAL",
        help="of a run holding several units, calibrate only this unit (repeat for several; default: every unit)",
    ),
    as_json: JsonFlag = False,
):
    """Ingest, segment, average, fit, verify on the VP segments, write a new passport version (Prefect flow).

    A run holding several units gives one passport per unit: {"units": [...], "failed": [...]}.
    Exit status 1 (with the result printed) when the calibration's status is fail; with several units, the worst
    of the units' (2 when a unit's input was bad)."""
    settings = calibration_settings(thermal_model, constants_method, tol_normal_g, tol_range_g, grade)
    if method != "auto":
        check_method(method)
    for r in runs:
        if not r.exists():
            raise ThermocalError("no such file or directory", path=str(r))
    base = None  # the flow looks up the unit's current passport when the method needs one and none is named
    if base_passport is not None and (method == "auto" or needs_base(method)):
        from pipeline.passport.registry import load_passport_file

        base, _ = load_passport_file(base_passport)  # verified, or refused in one line
    from ..calibrate import run_calibrate

    result = run_calibrate([str(r) for r in runs], str(registry), settings, method, base, dry_run, unit or None)
    if "units" in result:
        _units_outcome(result, as_json)
        return
    emit(result, as_json, None if as_json else calibrate_text(result))
    if result.get("status") == "fail":
        print(f"thermocal: calibrate: {result['unit']}: status fail ({fail_reason(result)})", file=sys.stderr)
        raise typer.Exit(1)


def fail_reason(result: dict) -> str:
    """Why a calibration's status is fail, in a few words: its first plausibility finding (constants no unit of
    its type has: the status is fail whatever the VP verification said), else the verification."""
    implausible = [w.removeprefix("implausible: ") for w in result.get("warnings", []) if w.startswith("implausible: ")]
    if implausible:
        return f"implausible constants: {implausible[0]}"
    from pipeline.calibrate.tilt import stage_clauses
    from pipeline.verify import failed_outside

    doc = _passport_doc(result) or {}
    outside = failed_outside(doc.get("verification", []), doc.get("valid_temp_c"))
    lost = stage_clauses(result.get("warnings", []))
    if outside is None and not lost:
        return "the compensated gravity-module error exceeds its limit at a verification position"
    where = outside or "at a verification position"
    return "; ".join([f"the compensated gravity-module error exceeds its limit {where}", *lost])


def _units_outcome(result: dict, as_json: bool) -> None:
    """Print the result of a run with several units (contract.md) and exit with the worst of the units' statuses:
    2 when a unit's input was bad (one line each on stderr), 1 when a unit's calibration failed, else 0."""
    text = None
    if not as_json:
        parts = [calibrate_text(r) for r in result["units"]]
        parts += [f"{f['unit']}: not calibrated: {f['reason']}" for f in result["failed"]]
        parts += [f"warning: {w['run']}: {w['warning']}" for w in result.get("warnings", [])]
        text = "\n\n".join(parts)
    emit(result, as_json, text)
    from ..fleet import failure_line

    for f in result["failed"]:
        print(f"thermocal: calibrate: {failure_line(f)}", file=sys.stderr)
    failing = [r for r in result["units"] if r.get("status") == "fail"]
    if failing and not result["failed"]:
        said = "; ".join(f"{r['unit']}: status fail ({fail_reason(r)})" for r in failing)
        print(f"thermocal: calibrate: {said}", file=sys.stderr)
    if result["failed"]:
        raise typer.Exit(2)
    if failing:
        raise typer.Exit(1)


def _passport_doc(r: dict) -> dict | None:
    """The passport a calibration result wrote (or would write: a dry run's content), None when it cannot be read."""
    doc = r.get("passport_content") if r.get("dry_run") else None
    if doc is None and r.get("passport") and Path(r["passport"]).is_file():
        try:
            doc = json.loads(Path(r["passport"]).read_text())
        except (OSError, ValueError):
            doc = None
    return doc


def calibrate_text(r: dict) -> str:
    from pipeline.passport.text import calibrate_lines

    lines = calibrate_lines(r, _passport_doc(r))
    if r.get("base_passport_used"):
        lines.insert(1, r["base_passport_used"])
    return "\n".join(lines)
