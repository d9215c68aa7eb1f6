"""``thermocal simulate``: one simulated run of a chamber program and its ground truth."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from pipeline.errors import ThermocalError

from .app import JsonFlag, app, emit


@app.command()
def simulate(
    out: Path = typer.Option(..., "--out", help="output .mcap file or Parquet directory"),
    fmt: str = typer.Option("mcap", "--format", help="file format: mcap (one file) | parquet (a folder)"),
    unit: str = typer.Option(
        "AU-0001", "--unit", help="unit serial number written into the run (with --units: the first unit's)"
    ),
    units: int | None = typer.Option(
        None,
        "--units",
        metavar="N",
        help="N units of one type on one fixture in one run (one file): serials counting up from --unit, the "
        "first unit as without --units, the others random units of the type, each its own noise and thermosensor",
    ),
    seed: int = typer.Option(0, "--seed", help="random seed of the measurement noise"),
    unit_seed: int | None = typer.Option(
        None,
        "--unit-seed",
        help="draw a different unit of the same type from this seed (default: the type's "
        "reference unit; the navigation type's has the published tables' constants)",
    ),
    effect: list[str] = typer.Option(
        [],
        "--effect",
        metavar="ID[:k=v,...]",
        help="add a physical effect from the catalogue, with its parameters by name; repeat for several",
    ),
    disturbance: list[str] = typer.Option(
        [],
        "--disturbance",
        metavar="ID[:k=v,...]",
        help="add a mismatch outside the catalogue (constants_shift, bias_step, bias_random_walk, "
        "periodic), with its parameters by name; repeat for several",
    ),
    program: str = typer.Option(
        "standard",
        "--program",
        help="chamber program: standard (full temperature steps), short (a few "
        "plateaus, for quick tries) | differential (six orientations "
        "through a temperature cycle) | handheld (36 hand-turned poses of "
        "3 s at 20 C; use ~100 Hz and --jitter-ms) | sweep (three "
        "orientations, the temperature drifting 5-25 C, no plateau) | fast (positions cycled on continuous "
        "ramps +20 -> +70 -> -40 -> +20 C, 3.4 h) | a stepped program SETPOINT@SOAK_MIN:POSITIONS; ... "
        "(e.g. '20@0:TP; -40@0:TP; -10@0:VP; 20@0:TP+VP; 45@0:VP; 70@0:TP; 20@0:TP+VP')",
    ),
    ramp_c_per_min: float | None = typer.Option(
        None,
        "--ramp-c-per-min",
        metavar="C_PER_MIN",
        help="ramp rate of the fast program (default 1.5) or a stepped program (default 1)",
    ),
    hold_s: float | None = typer.Option(
        None, "--hold-s", help="hold of each position, s: fast program (default 240), stepped program (default 300)"
    ),
    move_s: float | None = typer.Option(
        None, "--move-s", help="move between positions, s: fast program or stepped program (default 20)"
    ),
    soak_min: float | None = typer.Option(
        None,
        "--soak-min",
        metavar="MINUTES",
        help="make every soak of the program this many minutes (the standard program soaks 60 and 90 "
        "min); short soaks leave the unit still settling while the positions are held",
    ),
    drop: list[str] = typer.Option(
        [],
        "--drop",
        metavar="POS@TEMP[#K]",
        help="leave out the hold of a position at the stages of that setpoint, e.g. TP4@-40 (#2: only the "
        "second stage at that setpoint); repeat for several",
    ),
    rate_hz: float = typer.Option(10.0, "--rate-hz", help="voltmeter sampling rate, Hz"),
    noise_uv: float | None = typer.Option(
        None, "--noise-uv", help="voltmeter noise per sample, micro-volts (default: the unit type's, 5 for navigation)"
    ),
    case_lag_s: float | None = typer.Option(
        None,
        "--case-lag-s",
        help="time constant of the unit's case temperature behind the chamber air, s (default: the unit type's)",
    ),
    jitter_ms: float = typer.Option(
        0.0,
        "--jitter-ms",
        help="voltmeter timestamp jitter (standard deviation), ms: a wireless logger's irregular stamps",
    ),
    no_fixture_log: bool = typer.Option(False, "--no-fixture-log", help="leave out the fixture's position log"),
    unit_type: str = typer.Option(
        "navigation",
        "--unit-type",
        help="the kind of unit: navigation (the type of the published tables) | consumer (a MEMS part: 0.3 V/g, "
        "offsets of tens of mg, 0.5 mV of noise per sample)",
    ),
    grade: str | None = typer.Option(
        None, "--grade", help="the run's unit_grade metadata (default: the unit type's; none for navigation)"
    ),
    encoding: str = typer.Option("json", "--encoding", help="MCAP message encoding: json | protobuf"),
    truth: Path | None = typer.Option(
        None, "--truth", help="where to write the ground truth as JSON (default: beside the run, NAME.truth.json)"
    ),
    as_json: JsonFlag = False,
):
    """Write one simulated run of a chamber program, and its ground truth as JSON beside it."""
    from pipeline.effects.catalogue import parse_effect_spec
    from pipeline.io.runs import FORMATS, write_run
    from pipeline.simulate.chamber import SimConfig, write_truth
    from pipeline.simulate.disturbances import parse_disturbance_spec
    from pipeline.simulate.large import simulate_run
    from pipeline.simulate.program import parse_drop, program_from
    from pipeline.simulate.unit import UNIT_TYPES
    from pipeline.verify import GRADES

    for option, value, least in (
        ("--ramp-c-per-min", ramp_c_per_min, 0.0),
        ("--hold-s", hold_s, 0.0),
        ("--move-s", move_s, None),
    ):
        if value is not None and not (math.isfinite(value) and (value > least if least is not None else value >= 0)):
            bound = "a finite number above 0" if least is not None else "a finite number, 0 or more"
            raise ThermocalError(f"must be {bound}, got {value:g}", where=option)
    if soak_min is not None and not soak_min >= 0:
        raise ThermocalError(f"soak must be 0 minutes or more, got {soak_min:g}", where="--soak-min")
    for d in drop:
        try:
            parse_drop(d)
        except ValueError as e:
            raise ThermocalError(str(e), where="--drop") from None
    try:
        chosen = program_from(program, ramp_c_per_min, hold_s, move_s)
    except ValueError as e:
        raise ThermocalError(str(e), where="--program") from None
    if soak_min is not None or drop:
        try:
            chosen = program_from(
                program, ramp_c_per_min, hold_s, move_s, None if soak_min is None else soak_min * 60.0, tuple(drop)
            )
        except ValueError as e:
            raise ThermocalError(str(e), where="--drop") from None
    if fmt not in FORMATS:
        raise ThermocalError(f"unknown format {fmt!r} ({', '.join(FORMATS)})", where="--format")
    try:
        effects = [parse_effect_spec(e) for e in effect]
    except ValueError as e:
        raise ThermocalError(str(e), where="--effect") from None
    try:
        disturbances = [parse_disturbance_spec(d) for d in disturbance]
    except ValueError as e:
        raise ThermocalError(str(e), where="--disturbance") from None
    if unit_type not in UNIT_TYPES:
        raise ThermocalError(f"unknown unit type {unit_type!r} ({', '.join(UNIT_TYPES)})", where="--unit-type")
    if grade is not None and grade not in GRADES:
        raise ThermocalError(f"unknown unit grade {grade!r} ({', '.join(GRADES)})", where="--grade")
    cfg = SimConfig(
        unit_serial=unit,
        seed=seed,
        unit_seed=unit_seed,
        program=chosen,
        rate_hz=rate_hz,
        noise_v=UNIT_TYPES[unit_type].noise_v if noise_uv is None else noise_uv * 1e-6,
        unit_type=unit_type,
        unit_grade=grade,
        case_lag_s=case_lag_s,
        effects=effects,
        jitter_s=jitter_ms * 1e-3,
        disturbances=disturbances,
        with_fixture_log=not no_fixture_log,
    )
    opts = {"encoding": encoding} if fmt == "mcap" and encoding != "json" else {}
    if units is None:
        res = simulate_run(cfg)
        path = write_run(res.run, out, fmt, **opts)
        truth_doc, n, serials = res.truth, res.run.voltmeter.height, None
    else:
        from pipeline.simulate.units import simulate_units

        if units < 1:
            raise ThermocalError(f"--units must be at least 1, got {units}", where="--units")
        runs, truths = simulate_units(cfg, units)
        path = write_run(runs, out, fmt, **opts)
        truth_doc, serials = {"units": truths}, list(runs.units)
        n = sum(r.voltmeter.height for r in runs.units.values())
    truth_path = truth or _truth_path(path)
    try:
        write_truth(truth_doc, truth_path)
    except OSError as e:
        raise ThermocalError(f"cannot write the ground truth ({e.strerror or e})", path=str(truth_path)) from None
    doc = {"run": str(path), "truth": str(truth_path), "samples": n}
    doc.update({"unit": unit} if serials is None else {"units": serials})
    what = f"{n} voltmeter samples" if serials is None else f"{len(serials)} units, {n} voltmeter samples"
    emit(doc, as_json, f"wrote {path} ({what}) and {truth_path}")


def _truth_path(run_path: Path) -> Path:
    run_path = Path(run_path)
    return run_path.parent / f"{run_path.name.removesuffix('.mcap')}.truth.json"
