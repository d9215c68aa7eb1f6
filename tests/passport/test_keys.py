"""The station's signing key (issue 26 item 5): never silently replaced, made on first use or by ``key create``,
rotated and trusted explicitly; a key folder open to other users is refused; verify never needs the private key."""

from __future__ import annotations

import json
import os
import stat

import pytest

from pipeline.errors import RegistryError
from pipeline.passport.registry import Registry
from pipeline.passport.signing import (
    PRIVATE_NAME,
    PUBLIC_NAME,
    create_key,
    describe_keys,
    rotate_key,
    station_key,
    trust_key_file,
    trusted_keys,
)
from tests.acceptance.tampered import publish


def _files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def station(tmp_path, monkeypatch):
    """A station with its key and a registry of one unit, two versions."""
    keys = tmp_path / "keys"
    monkeypatch.setenv("THERMOCAL_KEY_DIR", str(keys))
    reg = Registry(tmp_path / "reg")
    publish(reg, "AU-0501", 1)
    publish(reg, "AU-0501", 2)
    return keys, reg


def test_deleted_private_key_is_never_replaced(station, capsys):
    """The issue: verify with the private key deleted made a new key, overwrote the public key file and then called
    every version untrusted. Now verify uses the public key and writes nothing; signing stops with one line saying
    how to restore or rotate."""
    keys, reg = station
    old = station_key().key_id
    (keys / PRIVATE_NAME).unlink()
    before = _files(keys)
    capsys.readouterr()
    report = reg.verify()
    assert report.ok, report.problems
    doc, st = reg.load_state("AU-0501")
    assert st.verification.verified and st.verification.key_id == old
    assert _files(keys) == before and capsys.readouterr().err == ""
    with pytest.raises(RegistryError) as info:
        publish(reg, "AU-0501", 3)
    line = info.value.one_line()
    assert "\n" not in line and "missing" in line and "restore it from a backup" in line and "key rotate" in line
    assert old in line and _files(keys) == before
    assert [i.version for i in reg.versions("AU-0501")] == [1, 2]


def test_rotate_keeps_what_the_old_key_signed_trusted(station):
    keys, reg = station
    old = station_key().key_id
    (keys / PRIVATE_NAME).unlink()  # lost: rotate is the way on
    rot = rotate_key()
    assert rot.old_key_id == old and rot.key.key_id != old and rot.retired is None
    assert (keys / PUBLIC_NAME).read_text().strip() == rot.key.public_hex
    assert rot.old_trusted is not None and rot.old_trusted.parent.name == "trusted"
    publish(reg, "AU-0501", 3)  # signed by the new key
    assert reg.verify().ok
    doc, st = reg.load_state("AU-0501", 2)
    assert st.verification.key_id == old
    assert describe_keys().trusted == {old: str(rot.old_trusted)}
    # a second rotation retires the new key's private file (kept, mode 0600) and trusts it too
    again = rotate_key()
    assert again.retired is not None and stat.S_IMODE(again.retired.stat().st_mode) == 0o600
    assert reg.verify().ok


def test_rotate_with_distrust_names_what_the_old_key_signed(station):
    keys, reg = station
    old = station_key().key_id
    rotate_key(distrust_old=True)
    report = reg.verify()
    assert not report.ok and all(f"signed by key {old}" in p for p in report.problems)


def test_create_refuses_to_replace_a_key(station):
    keys, _ = station
    with pytest.raises(RegistryError, match="already has a signing key"):
        create_key()
    (keys / PRIVATE_NAME).unlink()
    with pytest.raises(RegistryError, match="key rotate"):
        create_key()


def test_create_show_and_trust(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert describe_keys(a).key_id is None  # nothing is created by looking
    assert not a.exists()
    ka, kb = create_key(a), create_key(b)
    assert stat.S_IMODE((a / PRIVATE_NAME).stat().st_mode) == 0o600 and stat.S_IMODE(a.stat().st_mode) == 0o700
    shown = describe_keys(a)
    assert shown.key_id == ka.key_id and shown.public_hex == ka.public_hex and shown.trusted == {}
    key_id, where, added = trust_key_file(b / PUBLIC_NAME, a)
    assert added and key_id == kb.key_id and where.parent == a / "trusted"
    assert trust_key_file(b / PUBLIC_NAME, a)[2] is False  # already trusted
    assert kb.key_id in trusted_keys(a).keys
    (tmp_path / "junk.pub").write_text("not a key\n")
    with pytest.raises(RegistryError, match="not a public key"):
        trust_key_file(tmp_path / "junk.pub", a)


@pytest.mark.parametrize(
    ("target", "mode", "fragment"),
    [
        ("", 0o777, "writable by others"),
        ("", 0o775, "writable by others"),
        ("trusted", 0o777, "writable by others"),
        (PRIVATE_NAME, 0o644, "readable by others"),
        (f"trusted/{PUBLIC_NAME}", 0o666, "writable by others"),
    ],
)
def test_key_folder_open_to_others_is_refused(station, target, mode, fragment):
    """The issue: a pre-existing world-writable key folder was used without a word (anyone could drop a key into
    trusted/ or swap the station's)."""
    keys, reg = station
    (keys / "trusted").mkdir(mode=0o700, exist_ok=True)
    (keys / "trusted" / PUBLIC_NAME).write_text((keys / PUBLIC_NAME).read_text())
    os.chmod(keys / "trusted" / PUBLIC_NAME, 0o644)
    os.chmod(keys / target, mode)
    for attempt in (station_key, trusted_keys, reg.verify, lambda: publish(reg, "AU-0501", 3)):
        with pytest.raises(RegistryError) as info:
            attempt()
        line = info.value.one_line()
        assert fragment in line and "chmod" in line and "\n" not in line, line
    assert [i.version for i in reg.versions("AU-0501")] == [1, 2]


def test_key_command(tmp_path, monkeypatch, capsys):
    from tests.conftest import run_main

    keys = tmp_path / "k"
    monkeypatch.setenv("THERMOCAL_KEY_DIR", str(keys))
    code, out, err = run_main(monkeypatch, capsys, "key", "show", "--json")
    assert code == 0 and json.loads(out)["key_id"] is None and not keys.exists()
    code, out, err = run_main(monkeypatch, capsys, "key", "create", "--json")
    created = json.loads(out)["key_id"]
    assert code == 0 and err == "" and (keys / PRIVATE_NAME).exists()
    code, out, err = run_main(monkeypatch, capsys, "key", "create")
    assert code == 2 and out == "" and len(err.splitlines()) == 1 and "key rotate" in err
    other = create_key(tmp_path / "other")
    code, out, err = run_main(monkeypatch, capsys, "key", "trust", str(tmp_path / "other" / PUBLIC_NAME))
    assert code == 0 and f"trusted: key {other.key_id}" in out
    code, out, err = run_main(monkeypatch, capsys, "key", "rotate", "--json")
    rot = json.loads(out)
    assert code == 0 and rot["old_key_id"] == created and rot["old_key_trusted"] and rot["key_id"] != created
    code, out, err = run_main(monkeypatch, capsys, "key", "show")
    assert code == 0 and rot["key_id"] in out and created in out and other.key_id in out
    (keys / PRIVATE_NAME).unlink()
    code, out, err = run_main(monkeypatch, capsys, "key", "show")
    assert code == 0 and "MISSING" in out
    os.chmod(keys, 0o777)
    code, out, err = run_main(monkeypatch, capsys, "key", "show")
    assert code == 2 and "chmod 700" in err and len(err.splitlines()) == 1
