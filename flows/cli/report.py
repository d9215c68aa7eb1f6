"""``thermocal report UNIT [V] --out FILE.html``: the calibration certificate."""

from __future__ import annotations

from pathlib import Path

import typer

from pipeline.io.files import write_text_whole

from .app import (
    REGISTRY_HELP,
    UNIT_OR_FILE_HELP,
    JsonFlag,
    UnverifiedFlag,
    app,
    emit,
    passport_in_use,
    refuse_out_over_inputs,
    warn,
)
from .passport import approval


@app.command()
def report(
    unit: str = typer.Argument(..., metavar="UNIT|FILE", help=UNIT_OR_FILE_HELP),
    version: int | None = typer.Argument(
        None,
        metavar="V",
        help="version number (default: the unit's current passport: the newest approved version, else the newest "
        "that did not fail)",
    ),
    registry: Path | None = typer.Option(None, "--registry", help=REGISTRY_HELP),
    out: Path = typer.Option(..., "--out", help="where to write the certificate (an .html file)"),
    pdf: Path | None = typer.Option(None, "--pdf", help="also print it to this PDF file (needs Chromium)"),
    unverified: UnverifiedFlag = False,
    as_json: JsonFlag = False,
):
    """A calibration certificate a person reads and signs: one HTML file that stands alone (figures embedded)."""
    from pipeline.passport.document import load_passport
    from pipeline.passport.registry import Registry
    from pipeline.passport.report import certificate_html, print_pdf

    for path in (out, pdf) if pdf is not None else (out,):  # never over the passport read or a registry's records
        refuse_out_over_inputs(path, [Path(unit)] if registry is None else [], registry)
    doc, state = passport_in_use(unit, version, registry, unverified)  # verified, or refused in one line
    if state.warning():
        warn(f"certificate of {state.warning()}")
    approved = approval(Registry(registry), state.unit, doc) if registry is not None else None
    page = certificate_html(
        doc, approved=approved, registry=str(registry) if registry else None, verification=state.verification
    )
    write_text_whole(out, page, "certificate")
    pdf_path = str(print_pdf(out, pdf)) if pdf is not None else None
    p = load_passport(doc)
    obj = {
        "unit": state.unit,
        "version": p.version,
        "status": p.status,
        "certificate": str(out),
        "pdf": pdf_path,
        "approved": bool(approved),
        "current": state.current,
        "valid_temp_c": list(p.valid_temp_c) if p.valid_temp_c else None,
        "passport_used": state.as_dict(),
    }
    valid = p.valid_temp_c
    text = (
        f"{state.unit} v{p.version} ({p.status}, "
        + (f"valid {valid[0]:+.1f} .. {valid[1]:+.1f} C, " if valid else "")
        + f"{'approved' if approved else 'not approved'}"
        + (f", {state.verification.label}" if state.unverified else "")
        + f"): certificate {out}"
        + (f", PDF {pdf_path}" if pdf_path else "")
    )
    emit(obj, as_json, text)
