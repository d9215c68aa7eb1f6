"""``thermocal trends --registry DIR``: the fleet over time (docs/contract.md "trends")."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import REGISTRY_HELP, JsonFlag, app, emit


@app.command()
def trends(
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    as_json: JsonFlag = False,
):
    """The fleet over time: constants drifting across a unit's passports (and when they reach the grade's limit),
    units far from the fleet of their type. Exit status 1 when a unit's passports did not all verify."""
    from pipeline.passport.trends import fleet_trends, trends_text

    report = fleet_trends(registry).report
    emit(report, as_json, trends_text(report))
    if report["not_verified"]:
        raise typer.Exit(1)
