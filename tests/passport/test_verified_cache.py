"""The cache of fully verified passport files (pipeline/passport/verified_cache.py, read by ``thermocal trends``):
a warm read gives the cold read's report while skipping the checks of the bytes alone; nothing in it makes other
bytes pass (a file altered after caching, entries planted without the secret), another key set verifies in full,
an unusable cache verifies in full without an error, and the registry folder is never written."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

import pipeline.passport.registry as registry_module
from pipeline.passport import verified_cache
from pipeline.passport.registry import Registry
from pipeline.passport.signing import create_key
from pipeline.passport.trends import fleet_trends
from pipeline.passport.verified_cache import CACHE_ENV, VerifiedCache
from pipeline.simulate.history import FleetSpec, write_fleet

SPEC = FleetSpec(units=4, versions=3, seed=11)
VERSIONS = 12


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cache") / "registry"
    write_fleet(root, SPEC)
    return root


@pytest.fixture
def counted(monkeypatch, tmp_path) -> dict:
    """A fresh cache folder and the number of files whose bytes were checked (seal, content) since."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    calls = {"sealed": 0, "content": 0}

    def count(name, fn):
        def wrapped(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(registry_module, "check_sealed", count("sealed", registry_module.check_sealed))
    monkeypatch.setattr(registry_module, "check_content", count("content", registry_module.check_content))
    return calls


def _reset(calls: dict) -> None:
    calls.update(sealed=0, content=0)


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(root.rglob("*"))}


def _copy(fleet: Path, tmp_path: Path) -> Path:
    root = tmp_path / "registry"
    shutil.copytree(fleet, root)
    return root


def test_warm_read_gives_the_cold_report_without_rechecking_the_bytes(fleet, counted, tmp_path):
    before = _snapshot(fleet)
    cold = fleet_trends(fleet).report
    assert counted == {"sealed": VERSIONS, "content": VERSIONS} and cold["versions"] == VERSIONS
    entries = (tmp_path / "cache" / "verified").read_text().split()
    assert len(entries) == VERSIONS and all(len(e) == 64 for e in entries)
    assert (tmp_path / "cache" / "secret").stat().st_mode & 0o777 == 0o600
    _reset(counted)
    warm = fleet_trends(fleet).report
    assert warm == cold and counted == {"sealed": 0, "content": 0}
    assert len((tmp_path / "cache" / "verified").read_text().split()) == VERSIONS  # nothing added twice
    assert _snapshot(fleet) == before  # the registry folder is never written


def test_a_file_altered_after_caching_is_refused(fleet, counted, tmp_path):
    root = _copy(fleet, tmp_path)
    fleet_trends(root)  # every file cached
    path = Registry(root).version_path("AU-0002", 3)
    doc = json.loads(path.read_bytes())
    doc["coefficients"]["U0"][0] += 1e-3  # (the canonical layout kept: only the seal tells)
    path.write_bytes(registry_module.canonical_json(doc))
    _reset(counted)
    r = fleet_trends(root).report
    assert counted["sealed"] == 1  # the altered file alone was checked again, and refused
    (bad,) = r["not_verified"]
    assert bad["unit"] == "AU-0002" and bad["versions_used"] == [1, 2] and "altered" in " ".join(bad["problems"])
    assert r["versions"] == VERSIONS - 1


def test_planted_entries_change_nothing(fleet, counted, tmp_path):
    root = _copy(fleet, tmp_path)
    path = Registry(root).version_path("AU-0004", 2)
    doc = json.loads(path.read_bytes())
    doc["coefficients"]["U0"][1] -= 1e-3
    path.write_bytes(registry_module.canonical_json(doc))
    data_sha = hashlib.sha256(path.read_bytes()).hexdigest()
    fleet_trends(fleet)  # the original bytes (the same names, other bytes) cached
    planted = [
        data_sha,  # the altered file's own hash, bare
        hashlib.sha256(b"another secret" + data_sha.encode()).hexdigest(),  # its tag under another secret
        "not an entry",
        "0" * 64,
    ]
    with open(tmp_path / "cache" / "verified", "a") as f:
        f.write("\n".join(planted) + "\n\x00\xff garbage")
    _reset(counted)
    r = fleet_trends(root).report
    (bad,) = r["not_verified"]
    assert bad["unit"] == "AU-0004" and bad["versions_used"] == [1] and counted["sealed"] == 1


def test_another_key_set_verifies_in_full(fleet, counted, tmp_path, monkeypatch):
    fleet_trends(fleet)
    _reset(counted)
    assert fleet_trends(fleet).report["not_verified"] == [] and counted["sealed"] == 0
    keys = tmp_path / "keys"
    shutil.copytree(os.environ["THERMOCAL_KEY_DIR"], keys)
    other = create_key(tmp_path / "other-station")
    (keys / "trusted").mkdir(mode=0o700, exist_ok=True)
    (keys / "trusted" / "other.pub").write_text(other.public_hex + "\n")
    monkeypatch.setenv("THERMOCAL_KEY_DIR", str(keys))
    r = fleet_trends(fleet).report
    assert r["not_verified"] == [] and counted == {"sealed": VERSIONS, "content": VERSIONS}


@pytest.mark.parametrize("spoil", ["shared secret", "cache is a file", "no cache"])
def test_an_unusable_cache_verifies_in_full_without_an_error(fleet, counted, tmp_path, monkeypatch, spoil):
    cache = tmp_path / "cache"
    if spoil == "shared secret":
        fleet_trends(fleet)
        (cache / "secret").chmod(0o644)
    elif spoil == "cache is a file":
        cache.write_text("not a folder")
    else:
        monkeypatch.setenv(CACHE_ENV, "")
    fleet_trends(fleet)
    _reset(counted)
    r = fleet_trends(fleet).report
    assert r["not_verified"] == [] and counted == {"sealed": VERSIONS, "content": VERSIONS}
    if spoil == "shared secret":
        assert not VerifiedCache.open(registry_module.trusted_keys()).known("0" * 64)


def _move_bytes(root: Path, how: str) -> str:
    """Put cached bytes where they do not belong; returns the unit that must be refused."""
    reg = Registry(root)
    if how == "an older version's bytes":
        reg.version_path("AU-0001", 3).write_bytes(reg.version_path("AU-0001", 2).read_bytes())
        return "AU-0001"
    if how == "another unit's version":
        reg.version_path("AU-0003", 2).write_bytes(reg.version_path("AU-0004", 2).read_bytes())
        return "AU-0003"
    a, b = reg.version_path("AU-0002", 2), reg.version_path("AU-0002", 3)
    data_a, data_b = a.read_bytes(), b.read_bytes()
    a.write_bytes(data_b)
    b.write_bytes(data_a)
    return "AU-0002"


@pytest.mark.parametrize("how", ["an older version's bytes", "another unit's version", "two versions swapped"])
def test_cached_bytes_in_another_place_are_refused_as_without_the_cache(fleet, counted, tmp_path, monkeypatch, how):
    root = _copy(fleet, tmp_path)
    fleet_trends(root)  # every file cached
    unit = _move_bytes(root, how)
    _reset(counted)
    warm = fleet_trends(root).report
    assert counted["sealed"] == 0  # every file's bytes are cached: only their place refuses them
    (bad,) = warm["not_verified"]
    assert bad["unit"] == unit and bad["versions_used"] == ([1, 2] if how == "an older version's bytes" else [1])
    monkeypatch.setenv(CACHE_ENV, "")
    assert fleet_trends(root).report == warm


def test_a_key_removed_refuses_what_it_signed_though_cached(fleet, counted, tmp_path, monkeypatch):
    """The fleet's signer trusted as another station, the cache filled, then its key file removed from trusted/."""
    signer = Path(os.environ["THERMOCAL_KEY_DIR"])
    keys = tmp_path / "keys"
    create_key(keys)
    (keys / "trusted").mkdir(mode=0o700, exist_ok=True)
    shutil.copy(next(signer.glob("*.pub")), keys / "trusted" / "signer.pub")
    monkeypatch.setenv("THERMOCAL_KEY_DIR", str(keys))
    assert fleet_trends(fleet).report["not_verified"] == []
    (keys / "trusted" / "signer.pub").unlink()
    _reset(counted)
    r = fleet_trends(fleet).report
    assert counted["sealed"] == VERSIONS and r["versions"] == 0
    assert len(r["not_verified"]) == SPEC.units and all(
        "does not trust" in " ".join(b["problems"]) for b in r["not_verified"]
    )


def test_any_edit_of_the_checks_verifies_in_full(fleet, counted, tmp_path, monkeypatch):
    files = verified_cache.acceptance_files()
    names = {f"{f.parent.name}/{f.name}" for f in files}
    assert {"passport/verification.py", "passport/canonical.py", "passport/signing.py", "pipeline/jsonable.py"} <= names
    assert {"passport/verified_cache.py", "passport/registry.py"} <= names  # (registry.py: what a hit skips)
    copies = []
    for f in files:
        copies.append(tmp_path / "src" / f.parent.name / f.name)
        copies[-1].parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, copies[-1])
    fleet_trends(fleet)

    def rerun(sources: list[Path]) -> dict:
        monkeypatch.setattr(verified_cache, "acceptance_files", lambda: sources)
        verified_cache.checks_fingerprint.cache_clear()
        _reset(counted)
        return fleet_trends(fleet).report

    try:
        assert rerun(copies)["not_verified"] == [] and counted["sealed"] == 0  # the same bytes elsewhere: same checks
        edited = next(c for c in copies if c.name == "verification.py")
        edited.write_bytes(edited.read_bytes() + b"\n# a changed check\n")
        assert rerun(copies)["not_verified"] == [] and counted == {"sealed": VERSIONS, "content": VERSIONS}
        assert rerun(copies) is not None and counted["sealed"] == 0  # (the new checks' entries are used)
    finally:
        verified_cache.checks_fingerprint.cache_clear()


def test_a_station_s_own_publish_fills_the_cache(counted, tmp_path, monkeypatch):
    """What this station publishes (signed by it, checked as a reader checks) is cached as it is written: the first
    read of its own registry checks no file's bytes and reports what a read without the cache reports; a
    registry copied from elsewhere (another user's cache) is read in full once; what is not a passport is not
    cached."""
    root = tmp_path / "own"
    write_fleet(root, FleetSpec(units=2, versions=2, seed=11))
    entries = (tmp_path / "cache" / "verified").read_text().split()
    assert len(entries) == 4
    Registry(root).publish({"unit": "AU-0099"}, inputs=[], settings={}, code_version="test")  # no coefficients
    assert len((tmp_path / "cache" / "verified").read_text().split()) == 4
    _reset(counted)
    warm = fleet_trends(root).report
    assert counted["sealed"] == 1 and warm["versions"] == 4  # AU-0099's file alone: checked, and malformed
    assert [b["unit"] for b in warm["not_verified"]] == ["AU-0099"]
    monkeypatch.setenv(CACHE_ENV, "")
    assert fleet_trends(root).report == warm
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "another user's cache"))
    _reset(counted)
    assert fleet_trends(root).report == warm and counted["sealed"] == 5
