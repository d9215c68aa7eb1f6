"""``thermocal inspect RUN``: what a run holds (no Prefect)."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import JsonFlag, app, emit


@app.command()
def inspect(
    run: Path = typer.Argument(..., metavar="RUN", help="an .mcap file or a Parquet run directory"),
    as_json: JsonFlag = False,
):
    """What a run holds: metadata, streams, rates, gaps, the plateaus and static positions found (no Prefect); a run
    holding several units: each unit."""
    from pipeline.inspect import format_summary, format_units, summarize_run, summarize_units
    from pipeline.io.runs import read_units

    got = read_units(run)
    if got.several:
        summary = summarize_units(got)
        emit(summary, as_json, None if as_json else format_units(summary))
        return
    summary = summarize_run(got.one())
    emit(summary, as_json, None if as_json else format_summary(summary))
