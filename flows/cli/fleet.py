"""``thermocal fleet FOLDER`` (every unit under a folder, the Prefect flow :mod:`flows.fleet`) and
``thermocal serve`` (the same flow as a deployment on a cron schedule, :mod:`flows.serve`)."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from pipeline.calibrate.methods import names as method_names
from pipeline.errors import ThermocalError

from .app import REGISTRY_HELP, GradeOption, JsonFlag, app, calibration_settings, check_method, emit


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
    grade: GradeOption = None,
    tol_normal_g: float | None = typer.Option(None, "--tol-normal-g", help="as for calibrate"),
    tol_range_g: float | None = typer.Option(None, "--tol-range-g", help="as for calibrate"),
    method: str = typer.Option(
        "auto",
        "--method",
        help="auto (default: as for calibrate, the method each unit's first run "
        f"supports) | {' | '.join(method_names())} (a method that starts from "
        "a base passport takes each unit's current passport in the registry: "
        "its newest approved, else newest, version not made by such a method)",
    ),
    as_json: JsonFlag = False,
):
    """Calibrate every run under FOLDER, one passport per unit (Prefect flow, one task per unit).

    Runs already processed with the same settings are skipped; a bad run is reported and the rest go on.
    Exit status: 0 all done or skipped; 1 the fleet ran but some runs failed (listed) or some units' calibrations
    have status fail (as calibrate's); 2 it could not run.
    """
    from pipeline.calibrate.fleet import POOLS, discover_runs

    settings = calibration_settings(thermal_model, constants_method, tol_normal_g, tol_range_g, grade)
    if method != "auto":
        check_method(method)
    if pool not in POOLS:
        raise ThermocalError(f"unknown pool {pool!r} ({', '.join(POOLS)})", where="--pool")
    if workers is not None and workers < 1:
        raise ThermocalError("must be at least 1", where="--workers")
    discover_runs(folder)  # a missing folder fails here, in one line, before Prefect starts
    from ..fleet import run_fleet

    summary = run_fleet(
        str(folder.resolve()),
        str(registry.resolve()),
        settings,
        dask_address=dask_address,
        workers=workers,
        pool=pool,
        figures=figures,
        progress=True,
        method=method,
    )
    emit(summary, as_json, None if as_json else fleet_text(summary))
    from pipeline.words import count_words

    failed = summary["failed"]
    failing_done = [d for d in summary["done"] if d["status"] == "fail"]
    failing = [d["unit"] for d in failing_done]
    if failed:
        from ..fleet import failure_line

        print(
            f"thermocal: fleet: {count_words(len(failed), 'run')} failed: {failure_line(failed[0])}"
            + (" (and more, see the summary)" if len(failed) > 1 else ""),
            file=sys.stderr,
        )
    elif failing:
        from .calibrate import fail_reason

        reasons = [fail_reason(d) for d in failing_done]  # calibrate's words, per unit where they differ
        why = reasons[0] if len(set(reasons)) == 1 else "; ".join(f"{u}: {r}" for u, r in zip(failing, reasons))
        print(
            f"thermocal: fleet: {count_words(len(failing), 'unit')} with status fail ({', '.join(failing)}): {why}",
            file=sys.stderr,
        )
    if failed or failing:
        raise typer.Exit(1)


def fleet_text(s: dict) -> str:
    from pipeline.words import count_words

    from ..fleet import failure_line

    lines = [
        f"done: {count_words(len(s['done']), 'unit')}, failed: {count_words(len(s['failed']), 'run')}, "
        f"skipped: {count_words(len(s['skipped']), 'run')}"
    ]
    for d in s["done"]:
        lines.append(
            f"  {d['unit']:<12} v{d['version']:<4} {d['status']:<10} {'new' if d['created'] else 'existing':<8} "
            + ", ".join(Path(r).name for r in d["runs"])
        )
        lines += [f"      warning: {w}" for w in d.get("warnings", ())]
    lines += [f"  FAILED  {failure_line(f)}" for f in s["failed"]]
    lines += [
        f"  skipped {x['run']}: {x['why']}" + (f" (units {', '.join(x['units'])})" if x.get("units") else "")
        for x in s["skipped"]
    ]
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
    grade: GradeOption = None,
    tol_normal_g: float | None = typer.Option(None, "--tol-normal-g", help="as for calibrate"),
    tol_range_g: float | None = typer.Option(None, "--tol-range-g", help="as for calibrate"),
):
    """Serve the fleet flow over INBOX as a Prefect deployment on a cron schedule (blocks; Ctrl-C stops it).

    Needs a running Prefect server: `prefect server start`, and PREFECT_API_URL=http://127.0.0.1:4200/api.
    Trigger a run now with `prefect deployment run thermocal-fleet/NAME`.
    """
    from ..serve import serve_nightly

    settings = calibration_settings(thermal_model, constants_method, tol_normal_g, tol_range_g, grade)
    serve_nightly(
        str(inbox.resolve()),
        str(registry.resolve()),
        cron=cron,
        timezone=timezone,
        name=name,
        settings=settings,
        dask_address=dask_address,
        workers=workers,
    )
