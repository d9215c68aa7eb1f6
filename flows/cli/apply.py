"""``thermocal apply PASSPORT RUN --out FILE``: a passport's model applied to every voltmeter sample."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import JsonFlag, UnverifiedFlag, app, emit, refuse_out_over_inputs, warn


@app.command()
def apply(
    passport: Path = typer.Argument(
        ...,
        metavar="PASSPORT",
        help="passport JSON file (verified first)",
    ),
    run: Path = typer.Argument(..., metavar="RUN", help="an .mcap file or a Parquet run directory"),
    out: Path = typer.Option(
        ..., "--out", help="output: Parquet (.parquet, .pq or no suffix), MCAP (.mcap) or CSV (.csv)"
    ),
    unverified: UnverifiedFlag = False,
    as_json: JsonFlag = False,
):
    """The passport's model (thermal model included) applied to every voltmeter sample: specific force in g, one
    row per input row, in_range per the passport's valid temperatures (a warning when some are outside)."""
    from pipeline.apply import apply_passport, output_format, write_applied
    from pipeline.io.runs import read_run, read_units_meta
    from pipeline.passport.document import load_passport
    from pipeline.passport.registry import load_passport_file

    refuse_out_over_inputs(out, [passport, run])  # never over what it reads or a registry's records
    output_format(out)  # a name of no format it writes: refused before anything is read
    doc, state = load_passport_file(passport, unverified=unverified)  # verified, or refused in one line
    p = load_passport(doc)
    r = read_run(run, str(p.unit) if read_units_meta(run)[1] else None)  # several units: the passport's
    applied = apply_passport(p, r)
    path = write_applied(applied, out, passport=p, run=r, verification=state.verification)
    if state.warning():
        warn(f"apply of {state.warning()}")
    for w in applied.warnings:
        warn(w)
    t = applied.table
    inr = int(t["in_range"].sum())
    obj = {
        "out": str(path),
        "rows": t.height,
        "in_range": inr,
        "out_of_range": t.height - inr,
        "valid_temp_c": list(applied.valid_temp_c) if applied.valid_temp_c else None,
        "passport": {
            "unit": p.unit,
            "version": p.version,
            "method": p.method,
            "status": p.status,
            "verification": state.verification.as_dict(),
        },
        "warnings": applied.warnings,
    }
    label = f" (passport {state.verification.label})" if state.unverified else ""
    emit(obj, as_json, f"wrote {path}: {t.height} rows, {t.height - inr} outside the valid temperature range{label}")
