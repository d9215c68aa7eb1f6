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
    holding several units: each unit; several files of one unit: them as one recording; the files a run of several
    units was cut into: each unit's pieces as one recording, segmented as the whole file."""
    from pipeline.inspect import format_summary, format_units, summarize_runs, summarize_units
    from pipeline.io.runs import read_units

    if len(runs) > 1:
        read = [(str(r), read_units(r)) for r in runs]
        if any(got.several for _, got in read):  # the files a run of several units was cut into: each unit joined
            summary = summarize_units(read)
            emit(summary, as_json, None if as_json else format_units(summary))
            return
        summary = summarize_runs([got.one() for _, got in read])
        emit(summary, as_json, None if as_json else format_summary(summary))
        return
    got = read_units(runs[0])
    if got.several:
        summary = summarize_units(got)
        emit(summary, as_json, None if as_json else format_units(summary))
        return
    summary = summarize_runs([got.one()])
    emit(summary, as_json, None if as_json else format_summary(summary))
