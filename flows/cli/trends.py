"""``thermocal trends --registry DIR [--html FILE]``: the fleet over time (docs/contract.md "trends")."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import REGISTRY_HELP, JsonFlag, app, emit


@app.command()
def trends(
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    html: Path | None = typer.Option(
        None, "--html", help="also write the findings as one HTML page with a figure per finding"
    ),
    as_json: JsonFlag = False,
):
    """The fleet over time: constants drifting across a unit's passports (and when they reach the grade's limit),
    units far from the fleet of their type. Exit status 1 when a unit's passports did not all verify."""
    from pipeline.passport.trends import fleet_trends, trends_text

    result = fleet_trends(registry)
    report = result.report
    text = trends_text(report)
    if html is not None:
        from pipeline.passport.trends_page import write_trends_page

        text += f"\npage: {write_trends_page(result, html, registry=str(registry))}"
    emit(report, as_json, text)
    if report["not_verified"]:
        raise typer.Exit(1)
