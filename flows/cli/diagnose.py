"""``thermocal diagnose RUN...``: the recording against the model its passport predicts (the work:
:mod:`flows.diagnose_cmd`)."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import JsonFlag, UnverifiedFlag, app, emit


@app.command()
def diagnose(
    runs: list[Path] = typer.Argument(
        ..., metavar="RUN", help="an .mcap file or a Parquet run directory; several files of one unit are one recording"
    ),
    passport: Path | None = typer.Option(
        None,
        "--passport",
        help="the passport file to compare with, verified first (default: one fitted from the run itself)",
    ),
    registry: Path | None = typer.Option(
        None,
        "--registry",
        help="compare with the unit's current passport in this registry (its newest approved version, else its "
        "newest that did not fail), verified first",
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        help="folder for the figure and the extended passport (default: DIR/diagnose/UNIT beside the registry's "
        "units with --registry, else the current folder)",
    ),
    png: Path | None = typer.Option(
        None, "--png", help="where to write the figure (default: RUN.diagnose.png in the --out folder)"
    ),
    out_passport: Path | None = typer.Option(
        None,
        "--out-passport",
        help="where to write the passport extended by the findings (default: RUN.diagnose.passport.json in the "
        "--out folder)",
    ),
    unit: str | None = typer.Option(
        None, "--unit", metavar="SERIAL", help="the unit to diagnose, of a run holding several units"
    ),
    unverified: UnverifiedFlag = False,
    as_json: JsonFlag = False,
):
    """Compare the recording with the model its passport predicts: locate, name and model the mismatch."""
    from ..diagnose_cmd import diagnose_command, diagnose_text

    report = diagnose_command(
        runs, passport, as_json, png, out_passport, registry, unit, out_dir=out, unverified=unverified
    )  # a failed passport: its notes
    emit(report, as_json, None if as_json else diagnose_text(report))
