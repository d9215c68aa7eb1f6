"""``thermocal inspect RUN...``: what a run holds, several files of one unit as one recording (no Prefect)."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import JsonFlag, app, emit


@app.command()
def inspect(
    runs: list[Path] = typer.Argument(
        ..., metavar="RUN", help="an .mcap file or a Parquet run directory; several files of one unit are one recording"
    ),
    as_json: JsonFlag = False,
):
    """What a run holds: metadata, streams, rates, gaps, the plateaus and static positions found (no Prefect); a run
    holding several units: each unit; several files of one unit: them as one recording."""
    from pipeline.inspect import format_summary, format_units, summarize_runs, summarize_units
    from pipeline.io.runs import read_run, read_units

    if len(runs) > 1:
        summary = summarize_runs([read_run(r) for r in runs])
        emit(summary, as_json, None if as_json else format_summary(summary))
        return
    got = read_units(runs[0])
    if got.several:
        summary = summarize_units(got)
        emit(summary, as_json, None if as_json else format_units(summary))
        return
    summary = summarize_runs([got.one()])
    emit(summary, as_json, None if as_json else format_summary(summary))
