"""``thermocal report UNIT [V] --out FILE.html``: the calibration certificate."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import typer

from pipeline.errors import ThermocalError

from .app import REGISTRY_HELP, UNIT_HELP, JsonFlag, app, emit
from .passport import approval


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
    as_json: JsonFlag = False,
):
    """A calibration certificate a person reads and signs: one HTML file that stands alone (figures embedded)."""
    from pipeline.passport.document import load_passport
    from pipeline.passport.registry import Registry
    from pipeline.passport.report import certificate_html, print_pdf

    reg = Registry(registry)
    doc, state = reg.load_state(unit, version)
    if state.warning():
        print(f"thermocal: warning: certificate of {state.warning()}", file=sys.stderr)
    approved = approval(reg, unit, doc)
    page = certificate_html(doc, approved=approved, registry=str(registry))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(page, encoding="utf-8")
        os.replace(tmp, out)
    except OSError as e:
        raise ThermocalError(f"cannot write the certificate ({e.strerror or e})", path=str(out)) from None
    pdf_path = str(print_pdf(out, pdf)) if pdf is not None else None
    p = load_passport(doc)
    obj = {
        "unit": unit,
        "version": p.version,
        "status": p.status,
        "certificate": str(out),
        "pdf": pdf_path,
        "approved": bool(approved),
        "current": state.current,
        "valid_temp_c": list(p.valid_temp_c) if p.valid_temp_c else None,
    }
    valid = p.valid_temp_c
    text = (
        f"{unit} v{p.version} ({p.status}, "
        + (f"valid {valid[0]:+.1f} .. {valid[1]:+.1f} C, " if valid else "")
        + f"{'approved' if approved else 'not approved'}): certificate {out}"
        + (f", PDF {pdf_path}" if pdf_path else "")
    )
    emit(obj, as_json, text)
