"""``thermocal key create|show|trust FILE|rotate``: this station's signing key (:mod:`pipeline.passport.signing`):
made on first use or by ``create``, never silently replaced; ``trust`` adds another station's public key."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import JsonFlag, PlainTyper, app, emit

key_app = PlainTyper(
    no_args_is_help=True,
    help="This station's signing key: create, show, trust another station's key, rotate. Kept outside the registry "
    "($THERMOCAL_KEY_DIR, else ~/.config/thermocal/keys).",
)
app.add_typer(key_app, name="key")


@key_app.command("create")
def key_create(as_json: JsonFlag = False):
    """Make this station's signing key (refused when it has one: 'rotate' replaces a key)."""
    from pipeline.passport.signing import create_key

    key = create_key()
    emit(
        {"created": True, "key_id": key.key_id, "public_key": key.public_hex, "private_key": str(key.path)},
        as_json,
        f"created this station's signing key {key.path} (key id {key.key_id}); keep it private. Other stations "
        f"accept what it signs once {key.path.with_suffix('.pub')} is in their trusted keys ('thermocal key trust')",
    )


@key_app.command("show")
def key_show(as_json: JsonFlag = False):
    """This station's key (id, public key; whether its private key is missing) and the keys it trusts; the key
    folder's permissions are checked."""
    from pipeline.passport.signing import describe_keys

    info = describe_keys()
    if info.key_id is None:
        own = "no signing key yet (made on first use, or by 'thermocal key create')"
    elif info.missing:
        own = (
            f"key id {info.key_id}: its private key is MISSING (restore it from a backup, or 'thermocal key "
            "rotate'); what it signed still verifies"
        )
    else:
        own = f"key id {info.key_id}, public key {info.public_hex}"
    lines = [f"key folder {info.folder}", f"this station: {own}"]
    lines += [f"trusted: {k} ({f})" for k, f in sorted(info.trusted.items())] or ["trusted: no other station"]
    emit(info.as_dict(), as_json, "\n".join(lines))


@key_app.command("trust")
def key_trust(
    file: Path = typer.Argument(..., metavar="FILE", help="another station's public key (64 hex digits or PEM)"),
    as_json: JsonFlag = False,
):
    """Trust what another station signs: its public key goes into this station's trusted keys."""
    from pipeline.passport.signing import trust_key_file

    key_id, where, added = trust_key_file(file)
    emit(
        {"key_id": key_id, "file": str(where), "added": added},
        as_json,
        f"{'trusted' if added else 'already trusted'}: key {key_id} ({where})",
    )


@key_app.command("rotate")
def key_rotate(
    distrust_old: bool = typer.Option(
        False,
        "--distrust-old",
        help="do not trust the old key any more (it may have leaked): what it signed is then named by verify",
    ),
    as_json: JsonFlag = False,
):
    """Replace this station's key with a new one (also when its private key was lost). The old private key is
    kept under retired/ and its public key stays trusted, so what it signed still verifies."""
    from pipeline.passport.signing import rotate_key

    rot = rotate_key(distrust_old=distrust_old)
    old = (
        "no key before"
        if rot.old_key_id is None
        else f"old key {rot.old_key_id} "
        + ("no longer trusted" if rot.old_trusted is None else f"stays trusted ({rot.old_trusted})")
        + (f", its private key kept in {rot.retired}" if rot.retired else ", its private key was missing")
    )
    emit(
        {
            "key_id": rot.key.key_id,
            "public_key": rot.key.public_hex,
            "old_key_id": rot.old_key_id,
            "old_key_trusted": rot.old_trusted is not None,
            "retired": str(rot.retired) if rot.retired else None,
        },
        as_json,
        f"new signing key {rot.key.key_id} ({rot.key.path}); {old}",
    )
