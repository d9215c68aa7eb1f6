"""``thermocal export UNIT [V] --format px4|ardupilot|csv``: a passport in a format flight software or a
spreadsheet loads."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from pipeline.errors import ThermocalError

from .app import REGISTRY_HELP, UNIT_HELP, JsonFlag, app, emit


@app.command()
def export(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    version: int | None = typer.Argument(
        None,
        metavar="V",
        help="version number (default: the unit's current passport: its newest approved version, else its newest)",
    ),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    fmt: str = typer.Option(
        ...,
        "--format",
        help="px4 (TC_A0_* parameters) | ardupilot (INS_TCAL1_* parameters) | csv (every constant and coefficient)",
    ),
    out: Path | None = typer.Option(None, "--out", help="write the file here (default: print it)"),
    as_json: JsonFlag = False,
):
    """The passport in a format flight software or a spreadsheet loads, with what the format cannot hold and the
    error that leaves over the passport's valid temperature range."""
    from pipeline.passport.export import export_passport
    from pipeline.passport.registry import Registry

    doc, state = Registry(registry).load_state(unit, version)
    exp = export_passport(doc, fmt, state=state)
    if state.warning():
        print(f"thermocal: warning: export of {state.warning()}", file=sys.stderr)
    if out is not None:
        try:
            out.write_text(exp.text)
        except OSError as e:
            raise ThermocalError(f"cannot write the export ({e.strerror})", path=str(out)) from None
    if as_json:
        emit(
            {
                **exp.summary(),
                "passport_used": state.as_dict(),
                "out": str(out) if out else None,
                "text": None if out else exp.text,
            },
            True,
        )
    elif out is None:
        sys.stdout.write(exp.text)
        sys.stdout.flush()
    else:
        res = exp.residual
        tail = (
            f"; not held: scale/cross-axis temperature terms, worst {res['total_worst_ug']:.0f} micro-g over "
            f"{exp.valid_temp_c[0]:g}..{exp.valid_temp_c[1]:g} C"
            if res
            else ""
        )
        emit(None, False, f"wrote {out} ({fmt}, {state.text()}){tail}")
