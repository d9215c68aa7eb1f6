"""The ``thermocal`` command line (contract.md). Commands that take ``--json`` print one JSON object on stdout;
logs and progress go to stderr; failures exit non-zero with a one-line reason on stderr.

Prefect is imported only by the commands that run a flow (``calibrate``, ``fleet``, ``serve``). Without
``PREFECT_API_URL``, ``calibrate`` and ``fleet`` run on the warm worker of thermocal's local Prefect server
(:mod:`flows.localserver`, started on first use; ``thermocal server ...``), which records their flow runs.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import typer

from pipeline.errors import ThermocalError
from pipeline.jsonable import json_default

app = typer.Typer(
    add_completion=False,
    pretty_exceptions_enable=False,
    help="thermocal: thermal-chamber calibration of accelerometer units.",
)
passport_app = typer.Typer(help="The passport audit trail: log, show, diff, approve, verify, head.")
app.add_typer(passport_app, name="passport")
server_app = typer.Typer(no_args_is_help=True, help="thermocal's local Prefect server: where flow runs are recorded.")
app.add_typer(server_app, name="server")

#: The help texts of options and arguments that several commands share.
JSON_HELP = "print one JSON object on stdout instead of text"
REGISTRY_HELP = "registry folder: every unit's passport versions"
UNIT_HELP = "the unit's serial number, e.g. AU-0001"


def _plain_type_words() -> None:
    """Help shows an option's value as a plain word (``PATH``, ``NUMBER``, ...) or its ``metavar``, and nothing for
    a flag or an argument (its name is shown), where typer's default shows Python type tags (``<bool>``,
    ``<list[Path]>``); arguments in the usage line as ``RUN`` and ``[V]``."""
    from typer import core

    words = {"float": "NUMBER", "int": "INTEGER", "str": "TEXT"}

    def display(self, ctx):
        if isinstance(self, core.TyperArgument) or getattr(self, "is_flag", False):
            return None
        if self.metavar is not None:
            return self.metavar
        desc = getattr(self, "type_descriptor", None)
        if desc is None:
            return None
        word = "PATH" if desc.is_path else words.get(self.bare_type().removeprefix("list[").removesuffix("]"), "VALUE")
        return word

    for cls in (getattr(core, "TyperArgument", None), getattr(core, "TyperOption", None)):
        if cls is not None and hasattr(cls, "display_type_rich"):
            cls.display_type_rich = display

    def usage_name(self) -> str:
        """``RUN`` (required), ``[V]`` (optional), ``RUN...`` in the usage line, where newer typer writes
        ``{RUN}``, which reads as a set of choices."""
        name = self.display_name_raw if self.required else f"[{self.display_name_raw}]"
        return name + ("..." if self.nargs != 1 else "")

    if hasattr(getattr(core, "TyperArgument", None), "_usage_display_name"):
        core.TyperArgument._usage_display_name = usage_name


_plain_type_words()


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("thermocal")
    except PackageNotFoundError:  # a source tree that was not installed
        return "unknown"


def _print_version(value: bool) -> None:
    if value:
        sys.stdout.write(f"thermocal {_version()}\n")
        raise typer.Exit(0)


@app.callback()
def _main_options(
    _version_flag: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="print the version of thermocal and exit"
    ),
):
    """thermocal: thermal-chamber calibration of accelerometer units."""


def _emit(obj, as_json: bool, text: str | None = None) -> None:
    if as_json:
        sys.stdout.write(json.dumps(obj, indent=2, default=json_default) + "\n")
    else:
        sys.stdout.write((text if text is not None else json.dumps(obj, indent=2, default=json_default)) + "\n")
    sys.stdout.flush()


# ---------------------------------------------------------------------------------------------------------- inspect
@app.command()
def inspect(
    run: Path = typer.Argument(..., metavar="RUN", help="an .mcap file or a Parquet run directory"),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """What a run holds: metadata, streams, rates, gaps, the plateaus and static positions found (no Prefect)."""
    from pipeline.inspect import format_summary, summarize_run
    from pipeline.io.runs import read_run

    summary = summarize_run(read_run(run))
    _emit(summary, as_json, None if as_json else format_summary(summary))


# --------------------------------------------------------------------------------------------------------- simulate
@app.command()
def simulate(
    out: Path = typer.Option(..., "--out", help="output .mcap file or Parquet directory"),
    fmt: str = typer.Option("mcap", "--format", help="file format: mcap (one file) | parquet (a folder)"),
    unit: str = typer.Option("AU-0001", "--unit", help="unit serial number written into the run"),
    seed: int = typer.Option(0, "--seed", help="random seed of the measurement noise"),
    unit_seed: int | None = typer.Option(
        None,
        "--unit-seed",
        help="draw a different unit of the same type from this seed (default: the "
        "reference unit, whose constants are the published tables)",
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
        "orientations, the temperature drifting 5-25 C, no plateau)",
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
    noise_uv: float = typer.Option(5.0, "--noise-uv", help="voltmeter noise per sample, micro-volts"),
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
    encoding: str = typer.Option("json", "--encoding", help="MCAP message encoding: json | protobuf"),
    truth: Path | None = typer.Option(
        None, "--truth", help="where to write the ground truth as JSON (default: beside the run, NAME.truth.json)"
    ),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """Write one simulated run of a chamber program, and its ground truth as JSON beside it."""
    from pipeline.effects.catalogue import parse_effect_spec
    from pipeline.io.runs import FORMATS, write_run
    from pipeline.simulate.chamber import SimConfig, write_truth
    from pipeline.simulate.disturbances import parse_disturbance_spec
    from pipeline.simulate.large import simulate_run
    from pipeline.simulate.program import PROGRAMS, get_program, parse_drop, variant

    if program not in PROGRAMS:
        raise ThermocalError(f"unknown chamber program {program!r} ({', '.join(PROGRAMS)})", where="--program")
    chosen = program
    if soak_min is not None or drop:
        if soak_min is not None and not soak_min >= 0:
            raise ThermocalError(f"soak must be 0 minutes or more, got {soak_min:g}", where="--soak-min")
        for d in drop:
            try:
                parse_drop(d)
            except ValueError as e:
                raise ThermocalError(str(e), where="--drop") from None
        try:
            chosen = variant(get_program(program), None if soak_min is None else soak_min * 60.0, tuple(drop))
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
    cfg = SimConfig(
        unit_serial=unit,
        seed=seed,
        unit_seed=unit_seed,
        program=chosen,
        rate_hz=rate_hz,
        noise_v=noise_uv * 1e-6,
        case_lag_s=case_lag_s,
        effects=effects,
        jitter_s=jitter_ms * 1e-3,
        disturbances=disturbances,
        with_fixture_log=not no_fixture_log,
    )
    res = simulate_run(cfg)
    opts = {"encoding": encoding} if fmt == "mcap" and encoding != "json" else {}
    path = write_run(res.run, out, fmt, **opts)
    truth_path = truth or _truth_path(path)
    try:
        write_truth(res.truth, truth_path)
    except OSError as e:
        raise ThermocalError(f"cannot write the ground truth ({e.strerror or e})", path=str(truth_path)) from None
    n = res.run.voltmeter.height
    _emit(
        {"run": str(path), "truth": str(truth_path), "samples": n, "unit": unit},
        as_json,
        f"wrote {path} ({n} voltmeter samples) and {truth_path}",
    )


def _truth_path(run_path: Path) -> Path:
    run_path = Path(run_path)
    return run_path.parent / f"{run_path.name.removesuffix('.mcap')}.truth.json"


# -------------------------------------------------------------------------------------------------------- calibrate
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
    tol_normal_g: float = typer.Option(
        3e-4, "--tol-normal-g", help="pass limit of the gravity-module error |dg| at the normal temperature, g"
    ),
    tol_range_g: float = typer.Option(
        1e-3, "--tol-range-g", help="pass limit of |dg| over the rest of the temperature range, g"
    ),
    method: str = typer.Option(
        "auto",
        "--method",
        help="auto (default: the method the recording supports, as inspect "
        "says, and the result says which) | tilt (known fixture positions) | "
        "scalar (the positions need not be known: only |a| = 1 g is used) | "
        "differential (fixed orientations through a temperature cycle or "
        "sweep)",
    ),
    base_passport: Path | None = typer.Option(
        None,
        "--base-passport",
        help="differential: normal-temperature passport to start from "
        "(default: the unit's current passport in the registry: its "
        "newest approved version, else its newest, not made by the "
        "differential method and not failed; without one, the constants "
        "the orientations determine by themselves)",
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="compute and print everything, write nothing to the registry"
    ),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """Ingest, segment, average, fit, verify on the VP segments, write a new passport version (Prefect flow).

    Exit status 1 (with the result printed) when the calibration's status is fail."""
    settings = _calibration_settings(thermal_model, constants_method, tol_normal_g, tol_range_g)
    if method != "auto":
        _check_method(method)
    for r in runs:
        if not r.exists():
            raise ThermocalError("no such file or directory", path=str(r))
    base = None  # the flow looks up the unit's current passport when the method needs one and none is named
    if base_passport is not None and (method == "auto" or _needs_base(method)):
        from pipeline.passport.document import read_passport

        base = read_passport(base_passport)
    from .calibrate import run_calibrate

    result = run_calibrate([str(r) for r in runs], str(registry), settings, method, base, dry_run)
    _emit(result, as_json, None if as_json else _calibrate_text(result))
    if result.get("status") == "fail":
        print(
            f"thermocal: calibrate: {result['unit']}: status fail (the compensated gravity-module error "
            "exceeds its limit at a verification position)",
            file=sys.stderr,
        )
        raise typer.Exit(1)


def _check_method(method: str) -> None:
    from pipeline.calibrate.methods import METHODS

    if method not in METHODS:
        raise ThermocalError(f"unknown method {method!r} ({', '.join(METHODS)})", where="--method")


def _needs_base(method: str) -> bool:
    from pipeline.calibrate.methods import NEEDS_BASE_PASSPORT

    return method in NEEDS_BASE_PASSPORT


def _calibration_settings(thermal_model: str, constants_method: str, tol_normal_g: float, tol_range_g: float):
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.constants import CONSTANTS_METHODS
    from pipeline.thermal import THERMAL_MODELS
    from pipeline.verify import Tolerances

    if thermal_model not in THERMAL_MODELS:
        raise ThermocalError(
            f"unknown thermal model {thermal_model!r} ({', '.join(THERMAL_MODELS[1:])})", where="--thermal-model"
        )
    if constants_method not in CONSTANTS_METHODS:
        raise ThermocalError(
            f"unknown constants method {constants_method!r} ({', '.join(CONSTANTS_METHODS)})",
            where="--constants-method",
        )
    return CalibrationSettings(
        thermal_model=thermal_model,
        constants_method=constants_method,
        tolerances=Tolerances(normal_g=tol_normal_g, operating_range_g=tol_range_g),
    )


def _calibrate_text(r: dict) -> str:
    from pipeline.passport.text import calibrate_lines

    doc = r.get("passport_content") if r.get("dry_run") else None
    if doc is None and r.get("passport") and Path(r["passport"]).is_file():
        try:
            doc = json.loads(Path(r["passport"]).read_text())
        except (OSError, ValueError):
            doc = None
    lines = calibrate_lines(r, doc)
    if r.get("base_passport_used"):
        lines.insert(1, r["base_passport_used"])
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------------- export
@app.command()
def export(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    version: int | None = typer.Argument(
        None,
        metavar="V",
        help="version number (default: the unit's current passport: its newest approved version, else its newest)",
    ),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    fmt: str = typer.Option(
        ...,
        "--format",
        help="px4 (TC_A0_* parameters) | ardupilot (INS_TCAL1_* parameters) | csv (every constant and coefficient)",
    ),
    out: Path | None = typer.Option(None, "--out", help="write the file here (default: print it)"),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """The passport in a format flight software or a spreadsheet loads, with what the format cannot hold and the
    error that leaves over the passport's valid temperature range."""
    from pipeline.passport.export import export_passport
    from pipeline.passport.registry import Registry

    doc, state = Registry(registry).load_state(unit, version)
    exp = export_passport(doc, fmt, state=state)
    if state.warning():
        print(f"thermocal: warning: export of {state.warning()}", file=sys.stderr)
    if out is not None:
        try:
            out.write_text(exp.text)
        except OSError as e:
            raise ThermocalError(f"cannot write the export ({e.strerror})", path=str(out)) from None
    if as_json:
        _emit(
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
        res = exp.residual
        tail = (
            f"; not held: scale/cross-axis temperature terms, worst {res['total_worst_ug']:.0f} micro-g over "
            f"{exp.valid_temp_c[0]:g}..{exp.valid_temp_c[1]:g} C"
            if res
            else ""
        )
        _emit(None, False, f"wrote {out} ({fmt}, {state.text()}){tail}")


# ------------------------------------------------------------------------------------------------------------ apply
@app.command()
def apply(
    passport: Path = typer.Argument(..., metavar="PASSPORT", help="passport JSON file"),
    run: Path = typer.Argument(..., metavar="RUN", help="an .mcap file or a Parquet run directory"),
    out: Path = typer.Option(..., "--out", help="output: a Parquet file, or MCAP when the name ends .mcap"),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """The passport's model (thermal model included) applied to every voltmeter sample: specific force in g, one
    row per input row, in_range per the passport's valid temperatures (a warning when some are outside)."""
    from pipeline.apply import apply_passport, write_applied
    from pipeline.io.runs import read_run
    from pipeline.passport.document import read_passport

    doc = read_passport(passport)
    r = read_run(run)
    applied = apply_passport(doc, r)
    path = write_applied(applied, out, passport=doc, run=r)
    for w in applied.warnings:
        print(f"thermocal: warning: {w}", file=sys.stderr)
    t = applied.table
    inr = int(t["in_range"].sum())
    obj = {
        "out": str(path),
        "rows": t.height,
        "in_range": inr,
        "out_of_range": t.height - inr,
        "valid_temp_c": list(applied.valid_temp_c) if applied.valid_temp_c else None,
        "passport": {
            "unit": doc.get("unit"),
            "version": doc.get("version"),
            "method": doc.get("method"),
            "status": doc.get("status"),
        },
        "warnings": applied.warnings,
    }
    _emit(obj, as_json, f"wrote {path}: {t.height} rows, {t.height - inr} outside the valid temperature range")


# --------------------------------------------------------------------------------------------------------- diagnose
@app.command()
def diagnose(
    run: Path = typer.Argument(..., metavar="RUN", help="an .mcap file or a Parquet run directory"),
    passport: Path | None = typer.Option(
        None, "--passport", help="the passport file to compare with (default: one fitted from the run itself)"
    ),
    registry: Path | None = typer.Option(
        None,
        "--registry",
        help="compare with the unit's current passport in this registry (its newest approved version, else its newest)",
    ),
    png: Path | None = typer.Option(
        None, "--png", help="where to write the figure (default: RUN.diagnose.png beside the run)"
    ),
    out_passport: Path | None = typer.Option(
        None,
        "--out-passport",
        help="where to write the passport extended by the findings (default: "
        "RUN.diagnose.passport.json beside the run)",
    ),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """Compare the recording with the model its passport predicts: locate, name and model the mismatch."""
    from .diagnose_cmd import diagnose_command, diagnose_text

    report = diagnose_command(run, passport, as_json, png, out_passport, registry)  # a failed passport: its notes
    _emit(report, as_json, None if as_json else diagnose_text(report))


# ------------------------------------------------------------------------------------------------- fleet and serve
@app.command()
def fleet(
    folder: Path = typer.Argument(
        ..., metavar="FOLDER", help="folder of runs (searched recursively; .mcap and Parquet)"
    ),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    dask_address: str | None = typer.Option(
        None, "--dask-address", help="run the units on this dask scheduler (tcp://host:8786) instead of this computer"
    ),
    workers: int | None = typer.Option(
        None, "--workers", help="how many units at once on this computer (default: the number of CPUs)"
    ),
    pool: str = typer.Option("auto", "--pool", help="run the units in processes or threads: auto | process | thread"),
    figures: bool = typer.Option(
        True, "--figures/--no-figures", help="the PNG of the VP errors beside each new passport"
    ),
    thermal_model: str = typer.Option("auto", "--thermal-model", help="as for calibrate"),
    constants_method: str = typer.Option("auto", "--constants-method", help="as for calibrate"),
    tol_normal_g: float = typer.Option(3e-4, "--tol-normal-g", help="as for calibrate"),
    tol_range_g: float = typer.Option(1e-3, "--tol-range-g", help="as for calibrate"),
    method: str = typer.Option(
        "auto",
        "--method",
        help="auto (default: as for calibrate, the method each unit's first run "
        "supports), tilt, scalar, or differential (starting from each unit's "
        "current passport in the registry: its newest approved, else newest, "
        "version not made by the differential method)",
    ),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """Calibrate every run under FOLDER, one passport per unit (Prefect flow, one task per unit).

    Runs already processed with the same settings are skipped; a bad run is reported and the rest go on.
    Exit status: 0 all done or skipped; 1 the fleet ran but some runs failed (listed); 2 it could not run.
    """
    from pipeline.calibrate.fleet import POOLS, discover_runs

    settings = _calibration_settings(thermal_model, constants_method, tol_normal_g, tol_range_g)
    if method != "auto":
        _check_method(method)
    if pool not in POOLS:
        raise ThermocalError(f"unknown pool {pool!r} ({', '.join(POOLS)})", where="--pool")
    if workers is not None and workers < 1:
        raise ThermocalError("must be at least 1", where="--workers")
    discover_runs(folder)  # a missing folder fails here, in one line, before Prefect starts
    from .fleet import run_fleet

    summary = run_fleet(
        str(folder),
        str(registry),
        settings,
        dask_address=dask_address,
        workers=workers,
        pool=pool,
        figures=figures,
        progress=True,
        method=method,
    )
    _emit(summary, as_json, None if as_json else _fleet_text(summary))
    if summary["failed"]:
        from pipeline.words import count_words

        from .fleet import failure_line

        failed = summary["failed"]
        print(
            f"thermocal: fleet: {count_words(len(failed), 'run')} failed: {failure_line(failed[0])}"
            + (" (and more, see the summary)" if len(failed) > 1 else ""),
            file=sys.stderr,
        )
        raise typer.Exit(1)


def _fleet_text(s: dict) -> str:
    from pipeline.words import count_words

    from .fleet import failure_line

    lines = [
        f"done: {count_words(len(s['done']), 'unit')}, failed: {count_words(len(s['failed']), 'run')}, "
        f"skipped: {count_words(len(s['skipped']), 'run')}"
    ]
    lines += [
        f"  {d['unit']:<12} v{d['version']:<4} {d['status']:<10} {'new' if d['created'] else 'existing':<8} "
        + ", ".join(Path(r).name for r in d["runs"])
        for d in s["done"]
    ]
    lines += [f"  FAILED  {failure_line(f)}" for f in s["failed"]]
    lines += [f"  skipped {x['run']}: {x['why']}" for x in s["skipped"]]
    return "\n".join(lines)


@app.command()
def serve(
    inbox: Path = typer.Option(..., "--inbox", help="folder the chamber runs arrive in"),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    cron: str = typer.Option("0 2 * * *", "--cron", help="when to run (cron syntax)"),
    timezone: str = typer.Option("UTC", "--timezone", help="time zone of the cron schedule"),
    name: str = typer.Option("nightly", "--name", help="deployment name (thermocal-fleet/NAME)"),
    dask_address: str | None = typer.Option(None, "--dask-address", help="as for fleet"),
    workers: int | None = typer.Option(None, "--workers", help="as for fleet"),
    thermal_model: str = typer.Option("auto", "--thermal-model", help="as for calibrate"),
    constants_method: str = typer.Option("auto", "--constants-method", help="as for calibrate"),
    tol_normal_g: float = typer.Option(3e-4, "--tol-normal-g", help="as for calibrate"),
    tol_range_g: float = typer.Option(1e-3, "--tol-range-g", help="as for calibrate"),
):
    """Serve the fleet flow over INBOX as a Prefect deployment on a cron schedule (blocks; Ctrl-C stops it).

    Needs a running Prefect server: `prefect server start`, and PREFECT_API_URL=http://127.0.0.1:4200/api.
    Trigger a run now with `prefect deployment run thermocal-fleet/NAME`.
    """
    from .serve import serve_nightly

    settings = _calibration_settings(thermal_model, constants_method, tol_normal_g, tol_range_g)
    serve_nightly(
        str(inbox),
        str(registry),
        cron=cron,
        timezone=timezone,
        name=name,
        settings=settings,
        dask_address=dask_address,
        workers=workers,
    )


# ----------------------------------------------------------------------------------------------------------- server
@server_app.command("status")
def server_status(as_json: bool = typer.Option(False, "--json", help=JSON_HELP)):
    """Where Prefect state lives (PREFECT_HOME) and the local server's API URL, if it is running."""
    from .localserver import LOG, read_state, use_prefect_home

    home = use_prefect_home()
    st = read_state(home) or {}
    obj = {
        "prefect_home": str(home),
        "running": bool(st),
        "api_url": st.get("api_url"),
        "ui_url": st.get("ui_url"),
        "pid": st.get("pid"),
        "idle_timeout_s": st.get("idle_s"),
        "log": str(home / LOG),
        "prefect_api_url_env": os.environ.get("PREFECT_API_URL"),
    }
    text = (
        f"PREFECT_HOME {home}\n"
        + (
            f"server running (pid {st['pid']}): API {st['api_url']}, UI {st['ui_url']}, "
            f"exits after {st['idle_s']:.0f} s without a command"
            if st
            else "server not running (starts with the next calibrate or fleet)"
        )
        + ("\nPREFECT_API_URL is set: flows are recorded there instead" if os.environ.get("PREFECT_API_URL") else "")
    )
    _emit(obj, as_json, text)


@server_app.command("start")
def server_start():
    """Start the local server now (else the next calibrate or fleet starts it); print its API URL."""
    from .localserver import ensure_server

    print(ensure_server()["api_url"])


@server_app.command("url")
def server_url():
    """The local server's API URL (starting it if needed), for `PREFECT_API_URL=$(thermocal server url) prefect
    flow-run ls` and the UI."""
    from .localserver import ensure_server

    print(ensure_server()["api_url"])


@server_app.command("stop")
def server_stop():
    """Stop the local server (and its warm worker); commands running on it are interrupted."""
    from .localserver import stop_server

    print("stopped" if stop_server() else "not running")


# ----------------------------------------------------------------------------------------------------------- report
@app.command()
def report(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    version: int | None = typer.Argument(
        None,
        metavar="V",
        help="version number (default: the unit's current passport: the newest approved version, else the newest)",
    ),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    out: Path = typer.Option(..., "--out", help="where to write the certificate (an .html file)"),
    pdf: Path | None = typer.Option(None, "--pdf", help="also print it to this PDF file (needs Chromium)"),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """A calibration certificate a person reads and signs: one HTML file that stands alone (figures embedded)."""
    from pipeline.passport.registry import Registry
    from pipeline.passport.report import certificate_html, print_pdf

    reg = Registry(registry)
    doc, state = reg.load_state(unit, version)
    if state.warning():
        print(f"thermocal: warning: certificate of {state.warning()}", file=sys.stderr)
    approved = _approval(reg, unit, doc)
    page = certificate_html(doc, approved=approved, registry=str(registry))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(page, encoding="utf-8")
        os.replace(tmp, out)
    except OSError as e:
        raise ThermocalError(f"cannot write the certificate ({e.strerror or e})", path=str(out)) from None
    pdf_path = str(print_pdf(out, pdf)) if pdf is not None else None
    obj = {
        "unit": unit,
        "version": doc.get("version"),
        "status": doc.get("status"),
        "certificate": str(out),
        "pdf": pdf_path,
        "approved": bool(approved),
        "current": state.current,
        "valid_temp_c": doc.get("valid_temp_c"),
    }
    valid = doc.get("valid_temp_c")
    text = (
        f"{unit} v{doc.get('version')} ({doc.get('status')}, "
        + (f"valid {valid[0]:+.1f} .. {valid[1]:+.1f} C, " if valid else "")
        + f"{'approved' if approved else 'not approved'}): certificate {out}"
        + (f", PDF {pdf_path}" if pdf_path else "")
    )
    _emit(obj, as_json, text)


# --------------------------------------------------------------------------------------------------------- passport
@passport_app.command("log")
def passport_log(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """Versions of a unit: number, date, method, thermal model, status, largest error after compensation,
    approval."""
    from pipeline.passport.registry import Registry
    from pipeline.passport.text import log_lines

    reg = Registry(registry)
    rows = reg.log(unit)
    if as_json:
        _emit({"unit": unit, "versions": rows}, True)
        return
    docs = {}
    for r in rows:
        try:
            docs[r["version"]] = reg.load(unit, r["version"])
        except ThermocalError:
            pass  # an unreadable version is listed with what the log knows
    _emit(None, False, "\n".join(log_lines(rows, docs)) if rows else f"{unit}: no versions")


@passport_app.command("show")
def passport_show(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    version: int | None = typer.Argument(None, metavar="V", help="version number (default: the newest)"),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    as_json: bool = typer.Option(False, "--json", help="print the passport document itself (JSON)"),
):
    """One version of a unit's passport (the newest when no version is given): a readable summary, or with --json
    the document itself."""
    from pipeline.passport.registry import Registry
    from pipeline.passport.text import passport_summary

    reg = Registry(registry)
    doc = reg.load(unit, version)
    if as_json:
        _emit(doc, True)
        return
    approved = _approval(reg, unit, doc)
    vdir = reg.unit_dir(unit)
    figures = [
        str(f)
        for suffix in (".png", ".constants.png")
        if (f := vdir / f"v{int(doc.get('version') or 0):04d}{suffix}").exists()
    ]
    _emit(None, False, passport_summary(doc, approved=approved, figures=figures))


def _approval(reg, unit: str, doc: dict):
    """The approval records of the passport ``doc`` of ``unit`` (``passport log``'s ``approved``), or None."""
    return next((r.get("approved") for r in reg.log(unit) if r["version"] == doc.get("version")), None)


@passport_app.command("diff")
def passport_diff(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    v1: int = typer.Argument(..., metavar="V1", help="the older version number"),
    v2: int = typer.Argument(..., metavar="V2", help="the newer version number"),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    show_all: bool = typer.Option(False, "--all", help="list the changes within their uncertainty too, one per line"),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """What changed between two versions: fields, settings, inputs, and each constant and thermal coefficient in
    ppm of the gain or micro-g, marked when it exceeds its combined uncertainty."""
    from pipeline.passport.registry import Registry
    from pipeline.passport.text import diff_lines

    d = Registry(registry).diff(unit, v1, v2)
    _emit(d, as_json, None if as_json else "\n".join(diff_lines(d, show_all)))


@passport_app.command("approve")
def passport_approve(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    version: int = typer.Argument(..., metavar="V", help="the version number to approve"),
    by: str = typer.Option(..., "--by", help="name of the person approving"),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """Approve a version: a signed record of who approved which version when (the version is not changed). The
    newest approved version is the unit's current passport."""
    from pipeline.passport.registry import Registry

    reg = Registry(registry)
    rec = reg.approve(unit, version, by)
    current = reg.current(unit)
    _emit(
        {"approval": rec, "current_version": current},
        as_json,
        f"{unit} v{rec['version']} approved by {rec['by']} at {rec['approved_utc']}; current passport: v{current}",
    )


@passport_app.command("verify")
def passport_verify(
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    against: Path | None = typer.Option(
        None,
        "--against",
        help="a head statement made earlier ('passport head'): name every "
        "version it listed that the registry no longer holds",
    ),
    as_json: bool = typer.Option(False, "--json", help=JSON_HELP),
):
    """Check every version's hashes, parent links and signatures; names any altered, unsigned, deleted or stray
    version and exits 1."""
    from pipeline.passport.registry import Registry

    head = _read_head(against) if against is not None else None
    rep = Registry(registry).verify(against=head)
    obj = {"ok": rep.ok, "problems": rep.problems, "notes": getattr(rep, "notes", [])}
    _emit(obj, as_json, "registry ok" if rep.ok else "\n".join(rep.problems))
    if not rep.ok:
        raise typer.Exit(1)


def _read_head(path: Path) -> dict:
    try:
        head = json.loads(path.read_bytes())
    except OSError as e:
        raise ThermocalError(f"cannot read the head statement ({e.strerror})", path=str(path)) from None
    except ValueError as e:
        raise ThermocalError(f"the head statement is not JSON ({e})", path=str(path)) from None
    if not isinstance(head, dict):
        raise ThermocalError("the head statement is not a JSON object", path=str(path))
    return head


@passport_app.command("head")
def passport_head(
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    out: Path | None = typer.Option(
        None, "--out", help="write the statement to this file (keep it outside the registry)"
    ),
):
    """A signed statement of every unit's newest version (JSON); keep it outside the registry and check the
    registry against it later with 'passport verify --against FILE'."""
    from pipeline.passport.canonical import canonical_json
    from pipeline.passport.registry import Registry

    data = canonical_json(Registry(registry).head())
    if out is not None:
        try:
            out.write_bytes(data)
        except OSError as e:
            raise ThermocalError(f"cannot write the head statement ({e.strerror})", path=str(out)) from None
    sys.stdout.write(data.decode("ascii"))
    sys.stdout.flush()


# ----------------------------------------------------------------------------------------------------------- main
def _click_errors() -> tuple[type, ...]:
    """The exception classes of a command-line usage error: click's, and typer's own copy of click's (newer typer
    vendors click)."""
    import click

    found = [click.ClickException]
    try:
        from typer._click.exceptions import ClickException as vendored
    except ImportError:
        pass
    else:
        found.append(vendored)
    return tuple(found)


_CLICK_ERRORS = _click_errors()


def _usage_line(e: Exception) -> str:
    """One line for a usage error: the message, the command it concerns and where help is."""
    msg = " ".join((e.format_message() if hasattr(e, "format_message") else str(e)).split())
    ctx = getattr(e, "ctx", None)
    cmd = ctx.command_path if ctx is not None and getattr(ctx, "command_path", "") else "thermocal"
    if not msg:  # a group called without its command
        msg = "missing command."
    return f"thermocal: usage error: {msg} (see `{cmd} --help`)"


def main(server_checked: bool = False) -> None:
    """Console entry point: one-line errors, no tracebacks (set THERMOCAL_DEBUG=1 to see them); a closed stdout
    (``| head``) ends the output quietly (:func:`flows.runtime.exit_guarded`). Commands that run a flow go to the
    local server's warm worker unless PREFECT_API_URL is set (:mod:`flows.localserver`; ``server_checked``: the
    caller, :func:`flows.console.main`, has already found that this command is not one of them)."""
    from .runtime import exit_guarded

    exit_guarded(lambda: _main(server_checked))


def _main(server_checked: bool) -> int:
    """The command's exit status (usage errors: their one line and 2)."""
    try:
        argv = sys.argv[1:]
        if not server_checked:
            from .localserver import run_on_server, runs_on_local_server

            if runs_on_local_server(argv):
                return run_on_server(argv)
        rc = app(standalone_mode=False, prog_name="thermocal")
        if rc == 130:  # typer's answer to Ctrl-C (KeyboardInterrupt) in a command
            raise KeyboardInterrupt
        return rc if isinstance(rc, int) else 0
    except _CLICK_ERRORS as e:  # usage: a missing or unknown command, option or value
        print(_usage_line(e), file=sys.stderr)
        return 2 if getattr(e, "exit_code", 2) in (None, 2) else e.exit_code
    except typer.Exit as e:
        return e.exit_code
    except typer.Abort:
        raise KeyboardInterrupt from None


if __name__ == "__main__":
    main()
