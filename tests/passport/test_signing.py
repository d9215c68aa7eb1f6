"""Signatures of registry records: the station key (created on first use, outside the registry), trusted keys."""

from __future__ import annotations

import shutil
import stat

import pytest

from pipeline.errors import RegistryError
from pipeline.passport.canonical import content_sha256
from pipeline.passport.signing import (
    PRIVATE_NAME,
    PUBLIC_NAME,
    key_dir,
    sign_record,
    station_key,
    trusted_keys,
    verify_record,
)

RECORD = {"kind": "approval", "unit": "AU-0001", "version": 3, "by": "A. Tester", "ratio": 0.1 + 0.2}


def test_key_created_on_first_use_with_a_message_and_kept_private(tmp_path, capsys):
    folder = tmp_path / "station-a"
    key = station_key(folder)
    err = capsys.readouterr().err
    assert f"created this station's signing key {folder / PRIVATE_NAME}" in err and key.key_id in err
    assert len(err.strip().splitlines()) == 1
    assert stat.S_IMODE((folder / PRIVATE_NAME).stat().st_mode) == 0o600
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert (folder / PUBLIC_NAME).read_text().strip() == key.public_hex
    # the second use loads it, silently, and it is the same key
    assert station_key(folder).public_hex == key.public_hex
    assert capsys.readouterr().err == ""


def test_key_folder_comes_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("THERMOCAL_KEY_DIR", str(tmp_path / "k"))
    assert key_dir() == tmp_path / "k"
    monkeypatch.delenv("THERMOCAL_KEY_DIR")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "cfg"))
    assert key_dir() == tmp_path / "cfg" / "thermocal" / "keys"


def test_signed_record_verifies_and_any_change_is_named(tmp_path):
    folder = tmp_path / "a"
    key, trust = station_key(folder), trusted_keys(folder)
    signed = sign_record(RECORD, key)
    assert signed["content_sha256"] == content_sha256(signed) and signed["signature"]["key_id"] == key.key_id
    check = verify_record(signed, trust)
    assert check.ok and check.own and check.key_id == key.key_id
    # changed content (self-hash recomputed by the forger): the signature no longer matches
    forged = {**signed, "version": 4}
    forged["content_sha256"] = content_sha256(forged)
    bad = verify_record(forged, trust)
    assert not bad.ok and "does not match the content" in bad.problem and key.key_id in bad.problem
    # no signature, a malformed one, a key id that is not the public key's
    assert "not signed" in verify_record({k: v for k, v in signed.items() if k != "signature"}, trust).problem
    assert "malformed" in verify_record({**signed, "signature": {"alg": "ed25519"}}, trust).problem
    swapped = {**signed, "signature": {**signed["signature"], "key_id": "0" * 16}}
    assert not verify_record(swapped, trust).ok


def test_another_stations_key_is_named_until_trusted(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    key_b = station_key(b)
    signed_by_b = sign_record(RECORD, key_b)
    check = verify_record(signed_by_b, trusted_keys(a))
    assert not check.ok and check.key_id == key_b.key_id
    assert f"signed by key {key_b.key_id}, which this station does not trust" in check.problem
    # the operator copies b's public key into a's trusted folder: accepted, and not a's own
    (a / "trusted").mkdir(parents=True)
    shutil.copy(b / PUBLIC_NAME, a / "trusted" / "station-b.pub")
    check = verify_record(signed_by_b, trusted_keys(a))
    assert check.ok and not check.own
    # a damaged trusted-key file is a one-line error naming it
    (a / "trusted" / "junk.pub").write_text("not a key")
    with pytest.raises(RegistryError, match="junk.pub"):
        trusted_keys(a)


def test_unwritable_key_folder_is_a_one_line_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(RegistryError) as exc:
        station_key(blocker / "keys")
    assert "THERMOCAL_KEY_DIR" in str(exc.value) and "\n" not in str(exc.value)
