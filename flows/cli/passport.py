"""``thermocal passport log|show|diff|approve|verify|head``: the passport audit trail in a registry."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer

from pipeline.errors import ThermocalError

from .app import REGISTRY_HELP, UNIT_HELP, JsonFlag, emit, passport_app, warn


@passport_app.command("log")
def passport_log(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    as_json: JsonFlag = False,
):
    """Versions of a unit: number, date, method, thermal model, status, largest error after compensation,
    approval."""
    from pipeline.passport.registry import Registry
    from pipeline.passport.text import log_lines

    reg = Registry(registry)
    rows = reg.log(unit)
    if as_json:
        emit({"unit": unit, "versions": rows}, True)
        return
    from pipeline.passport.verification import check_content

    docs = {}
    for r in rows:
        try:
            doc = reg.load(unit, r["version"])
            check_content(doc)
            docs[r["version"]] = doc
        except ThermocalError:
            pass  # an unreadable or malformed version is listed with what the log knows
    emit(None, False, "\n".join(log_lines(rows, docs)) if rows else f"{unit}: no versions")


@passport_app.command("show")
def passport_show(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    version: int | None = typer.Argument(None, metavar="V", help="version number (default: the newest)"),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    as_json: bool = typer.Option(False, "--json", help="print the passport document itself (JSON)"),
):
    """One version of a unit's passport (the newest when no version is given): a readable summary with how it
    verifies, or with --json the document itself."""
    from pipeline.passport.registry import Registry
    from pipeline.passport.text import passport_summary

    reg = Registry(registry)
    newest = version if version is not None else max((i.version for i in reg.versions(unit)), default=None)
    doc, state = reg.load_state(unit, newest, unverified=True)  # shown either way, with what its checks found
    check = state.verification
    if check is not None and not check.verified:  # said on stderr too: the document itself (--json) cannot say it
        warn(f"{unit} v{newest} DOES NOT VERIFY: {check.problem}")
    if as_json:
        emit(reg.load(unit, version), True)
        return
    approved = approval(reg, unit, doc)
    vdir = reg.unit_dir(unit)
    figures = [
        str(f)
        for suffix in (".png", ".constants.png")
        if (f := vdir / f"v{int(doc.get('version') or 0):04d}{suffix}").exists()
    ]
    said = "not checked" if check is None else check.label if check.verified else f"DOES NOT VERIFY: {check.problem}"
    emit(None, False, passport_summary(doc, approved=approved, figures=figures) + f"\nverification: {said}")


def approval(reg, unit: str, doc: dict):
    """The approval records of the passport ``doc`` of ``unit`` (``passport log``'s ``approved``), or None."""
    return next((r.get("approved") for r in reg.log(unit) if r["version"] == doc.get("version")), None)


@passport_app.command("diff")
def passport_diff(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    v1: int = typer.Argument(..., metavar="V1", help="the older version number"),
    v2: int = typer.Argument(..., metavar="V2", help="the newer version number"),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    show_all: bool = typer.Option(False, "--all", help="list the changes within their uncertainty too, one per line"),
    as_json: JsonFlag = False,
):
    """What changed between two versions: fields, settings, inputs, and each constant and thermal coefficient in
    ppm of the gain or micro-g, marked when it exceeds its combined uncertainty."""
    from pipeline.passport.registry import Registry
    from pipeline.passport.text import diff_lines

    d = Registry(registry).diff(unit, v1, v2)
    emit(d, as_json, None if as_json else "\n".join(diff_lines(d, show_all)))


@passport_app.command("approve")
def passport_approve(
    unit: str = typer.Argument(..., metavar="UNIT", help=UNIT_HELP),
    version: int = typer.Argument(..., metavar="V", help="the version number to approve"),
    by: str = typer.Option(..., "--by", help="name of the person approving"),
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    as_json: JsonFlag = False,
):
    """Approve a version: a signed record of who approved which version when (the version is not changed). The
    newest approved version is the unit's current passport."""
    from pipeline.passport.registry import Registry

    reg = Registry(registry)
    rec = reg.approve(unit, version, by)
    current = reg.current(unit)
    emit(
        {"approval": rec, "current_version": current},
        as_json,
        f"{unit} v{rec['version']} approved by {rec['by']} at {rec['approved_utc']}; current passport: v{current}",
    )


@passport_app.command("verify")
def passport_verify(
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    against: Path | None = typer.Option(
        None,
        "--against",
        help="a head statement made earlier ('passport head'): name every "
        "version it listed that the registry no longer holds",
    ),
    as_json: JsonFlag = False,
):
    """Check every version's hashes, parent links and signatures; names any altered, unsigned, deleted or stray
    version and exits 1."""
    from pipeline.passport.registry import Registry

    head = _read_head(against) if against is not None else None
    rep = Registry(registry).verify(against=head)
    obj = {"ok": rep.ok, "problems": rep.problems, "notes": getattr(rep, "notes", [])}
    emit(obj, as_json, "registry ok" if rep.ok else "\n".join(rep.problems))
    if not rep.ok:
        raise typer.Exit(1)


def _read_head(path: Path) -> dict:
    try:
        head = json.loads(path.read_bytes())
    except OSError as e:
        raise ThermocalError(f"cannot read the head statement ({e.strerror})", path=str(path)) from None
    except ValueError as e:
        raise ThermocalError(f"the head statement is not JSON ({e})", path=str(path)) from None
    if not isinstance(head, dict):
        raise ThermocalError("the head statement is not a JSON object", path=str(path))
    return head


@passport_app.command("head")
def passport_head(
    registry: Path = typer.Option(..., "--registry", help=REGISTRY_HELP),
    out: Path | None = typer.Option(
        None, "--out", help="write the statement to this file (keep it outside the registry)"
    ),
):
    """A signed statement of every unit's newest version (JSON); keep it outside the registry and check the
    registry against it later with 'passport verify --against FILE'."""
    from pipeline.passport.canonical import canonical_json
    from pipeline.passport.registry import Registry

    data = canonical_json(Registry(registry).head())
    if out is not None:
        try:
            out.write_bytes(data)
        except OSError as e:
            raise ThermocalError(f"cannot write the head statement ({e.strerror})", path=str(out)) from None
    sys.stdout.write(data.decode("ascii"))
    sys.stdout.flush()
