"""The tampered-registry corpus of issue 15: what an attacker with write access to the registry folder (but not to
the station's key folder) can do to it, one :class:`Attack` each, as the broken-run corpus does for runs.

:func:`build_base` writes a small signed registry (two units, three versions each, through
:meth:`pipeline.passport.registry.Registry.publish`) and, kept outside it, a head statement made before the attack.
Each attack changes a copy of it; ``names`` are the fragments ``passport verify`` (with ``--against`` the head
statement when ``against`` is set) must report, each in one problem line that also names the unit and version.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline.passport.canonical import canonical_json, content_sha256
from pipeline.passport.registry import Registry, sha256_file
from pipeline.passport.signing import sign_record, station_key

UNITS = ("AU-0301", "AU-0302")
VERSIONS = 3


def passport(unit: str, k: int) -> dict:
    """A small passport (docs/contract.md's required fields, seed 000's magnitudes); ``k`` varies one constant."""
    K = [[-0.5506, 0.0005 + 1e-5 * k, 0.0164], [-0.0132, -0.5485, -0.0007], [-0.0147, -0.0004, -0.5486]]
    return {
        "schema": "thermocal.passport/1",
        "unit": unit,
        "normal_temp_c": 20.0,
        "g_local_mps2": 9.80665,
        "status": "pass",
        "method": "tilt_six_position",
        "coefficients": {"K": K, "U0": [0.0045, -0.0044, -0.0035]},
        "per_plateau": [],
        "thermal_model": {
            "kind": "polynomial",
            "order": 1,
            "alpha": {"x": [1e-4], "y": [1e-4], "z": [1e-4]},
            "beta": {"xx": [1e-5], "yy": [1e-5], "zz": [1e-5]},
            "gamma": {g: [0.0] for g in ("xy", "xz", "yx", "yz", "zx", "zy")},
        },
        "verification": [],
    }


def publish(reg: Registry, unit: str, k: int):
    return reg.publish(
        passport(unit, k),
        inputs=[{"path": f"/runs/{unit}-{k}.mcap", "sha256": f"{k:064x}"}],
        settings={"k": k},
        code_version="test",
    )


def build_base(folder: Path) -> tuple[Path, Path]:
    """A signed registry and a head statement of it (outside it); returns (registry root, head file)."""
    reg = Registry(folder / "registry")
    for unit in UNITS:
        for k in range(1, VERSIONS + 1):
            publish(reg, unit, k)
    head = folder / "head.json"
    head.write_bytes(canonical_json(reg.head()))
    return reg.root, head


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` by relative path (the lock file aside), to show nothing was lost or altered."""
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file() and p.name != ".lock"
    }


# --- attacks ------------------------------------------------------------------------------------------------------


def _vpath(root: Path, unit: str, v: int) -> Path:
    return root / "units" / unit / f"v{v:04d}.json"


def _write(path: Path, data: bytes) -> None:
    if path.exists():
        os.chmod(path, 0o644)
    path.write_bytes(data)


def _forge_next(root: Path, unit: str, sign: Callable[[dict], dict] | None, keep_signature: bool = False) -> None:
    """The issue's forgery: copy the newest version, change K[0][0], set version n+1, parent = sha256(newest),
    recompute content_sha256 (and sign with ``sign`` if given, or keep the copied signature)."""
    n = max(int(p.stem[1:]) for p in (root / "units" / unit).glob("v[0-9][0-9][0-9][0-9].json"))
    doc = json.loads(_vpath(root, unit, n).read_bytes())
    doc["coefficients"]["K"][0][0] = -0.5606
    doc["version"] = n + 1
    doc["parent_sha256"] = sha256_file(_vpath(root, unit, n))
    if not keep_signature:
        doc.pop("signature")
    doc["content_sha256"] = content_sha256(doc)
    if sign is not None:
        doc = sign(doc)
    _write(_vpath(root, unit, n + 1), canonical_json(doc))


def forged_unsigned(root: Path, unit: str = UNITS[0]) -> None:
    _forge_next(root, unit, None)


def forged_old_signature(root: Path) -> None:
    _forge_next(root, UNITS[0], None, keep_signature=True)


def forged_other_key(root: Path) -> None:
    """Signed with a key the attacker made (its public key even left inside the registry folder)."""
    mine = station_key(root.parent / "attacker-keys")
    (root / "trusted").mkdir()
    shutil.copy(root.parent / "attacker-keys" / "station_ed25519.pub", root / "trusted" / "attacker.pub")
    _forge_next(root, UNITS[0], lambda d: sign_record(d, mine))


def forged_and_logged(root: Path) -> None:
    """The forgery, with its log row appended too (as the writer would have)."""
    _forge_next(root, UNITS[0], None)
    path = _vpath(root, UNITS[0], VERSIONS + 1)
    row = {
        "version": VERSIONS + 1,
        "sha256": sha256_file(path),
        "created_utc": "2026-11-22T00:00:00Z",
        "identity": "x" * 64,
    }
    with open(root / "units" / UNITS[0] / "log.jsonl", "a") as f:
        f.write(json.dumps(row, sort_keys=True, separators=(",", ":")) + "\n")


def _drop_last_log_line(root: Path, unit: str) -> None:
    log = root / "units" / unit / "log.jsonl"
    log.write_bytes(b"".join(log.read_bytes().splitlines(keepends=True)[:-1]))


def rollback_newest(root: Path) -> None:
    """Delete the newest version file and its log row: a consistent, shorter chain."""
    _vpath(root, UNITS[0], VERSIONS).unlink()
    (root / "units" / UNITS[0] / f"v{VERSIONS:04d}.png").unlink(missing_ok=True)
    _drop_last_log_line(root, UNITS[0])


def rollback_and_republish(root: Path) -> None:
    """Roll back, then let the station publish other content under the old number."""
    rollback_newest(root)
    publish(Registry(root), UNITS[0], 99)


def delete_unit(root: Path) -> None:
    shutil.rmtree(root / "units" / UNITS[1])


def altered_older(root: Path) -> None:
    """v2's K changed in place (self-hash not recomputed)."""
    p = _vpath(root, UNITS[0], 2)
    _write(p, p.read_bytes().replace(b"-0.5506", b"-0.5507", 1))


def thermal_x10_stale_hashes(root: Path) -> None:
    """Issue 26: the newest version's thermal coefficient alpha_x times 10 in place, hashes left stale (the
    consumers used it: export, report's clean certificate, apply, diagnose)."""
    p = _vpath(root, UNITS[0], VERSIONS)
    doc = json.loads(p.read_bytes())
    doc["thermal_model"]["alpha"]["x"] = [10 * a for a in doc["thermal_model"]["alpha"]["x"]]
    _write(p, canonical_json(doc))


def altered_older_rehashed(root: Path) -> None:
    """v2's K changed, content_sha256 recomputed, signature kept."""
    p = _vpath(root, UNITS[0], 2)
    doc = json.loads(p.read_bytes())
    doc["coefficients"]["K"][0][0] = -0.5507
    doc["content_sha256"] = content_sha256(doc)
    _write(p, canonical_json(doc))


def altered_newest_rehashed(root: Path) -> None:
    """The newest version (no child to catch it) changed, re-hashed, its log row rewritten to match."""
    unit, p = UNITS[0], _vpath(root, UNITS[0], VERSIONS)
    doc = json.loads(p.read_bytes())
    doc["status"] = "fail"
    doc["content_sha256"] = content_sha256(doc)
    _write(p, canonical_json(doc))
    log = root / "units" / unit / "log.jsonl"
    rows = [json.loads(x) for x in log.read_text().splitlines()]
    rows[-1]["sha256"] = sha256_file(p)
    log.write_text("".join(json.dumps(r, sort_keys=True, separators=(",", ":")) + "\n" for r in rows))


def signature_stripped(root: Path) -> None:
    """An older version with its signature removed (hashes recomputed, children untouched: the file hash changes)."""
    p = _vpath(root, UNITS[1], 1)
    doc = json.loads(p.read_bytes())
    doc.pop("signature")
    _write(p, canonical_json(doc))


def duplicate_keys_prepended(root: Path) -> None:
    """Issue 26: the newest version with duplicate keys prepended (``"status": "pass"`` and an identity K) and its
    log row updated: Python's json reads the last value of a key (the signed one), a first-key parser the forged
    one, so the hash and signature check out for one reader and the other uses the forgery."""
    unit, p = UNITS[0], _vpath(root, UNITS[0], VERSIONS)
    identity = {"K": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "U0": [0.0, 0.0, 0.0]}
    head = b'{\n  "coefficients": ' + json.dumps(identity).encode() + b',\n  "status": "pass",\n'
    _write(p, head + p.read_bytes()[2:])
    log = root / "units" / unit / "log.jsonl"
    rows = [json.loads(x) for x in log.read_text().splitlines()]
    rows[-1]["sha256"] = sha256_file(p)
    log.write_text("".join(json.dumps(r, sort_keys=True, separators=(",", ":")) + "\n" for r in rows))


def reformatted(root: Path) -> None:
    """The newest version's same content in other bytes (compact JSON, keys unsorted), its log row updated: the
    content hash and signature still match the content, but the file is not the record's canonical bytes."""
    unit, p = UNITS[0], _vpath(root, UNITS[0], VERSIONS)
    doc = json.loads(p.read_bytes())
    _write(p, json.dumps(dict(reversed(list(doc.items())))).encode())
    log = root / "units" / unit / "log.jsonl"
    rows = [json.loads(x) for x in log.read_text().splitlines()]
    rows[-1]["sha256"] = sha256_file(p)
    log.write_text("".join(json.dumps(r, sort_keys=True, separators=(",", ":")) + "\n" for r in rows))


def stray_files(root: Path) -> None:
    """Misnamed copies beside the real versions, and a file that is no version at all."""
    udir = root / "units" / UNITS[0]
    shutil.copy(_vpath(root, UNITS[0], 2), udir / "v2.json")
    shutil.copy(_vpath(root, UNITS[0], 2), udir / "v002.json")
    (udir / "notes.txt").write_text("K looked off on Tuesday\n")


@dataclass(frozen=True)
class Attack:
    """One attack: ``apply`` changes the registry copy; ``names``: (unit, version or None, fragment) each problem
    verify must report; ``against``: checked with ``--against`` the head statement made before the attack;
    ``refuses``: the unit whose next publish must be refused (None: publish may go on)."""

    name: str
    apply: Callable[[Path], None]
    names: tuple[tuple[str, int | None, str], ...]
    against: bool = False
    refuses: str | None = UNITS[0]


U0, U1 = UNITS
ATTACKS: tuple[Attack, ...] = (
    Attack("forged-version-unsigned", forged_unsigned, ((U0, 4, "not signed"),)),
    Attack("forged-version-old-signature", forged_old_signature, ((U0, 4, "does not match the content"),)),
    Attack("forged-version-attacker-key", forged_other_key, ((U0, 4, "which this station does not trust"),)),
    Attack("forged-version-logged", forged_and_logged, ((U0, 4, "not signed"),)),
    Attack("rollback-newest", rollback_newest, ((U0, 3, "no longer in the registry"),), against=True, refuses=None),
    Attack(
        "rollback-and-republish",
        rollback_and_republish,
        ((U0, 3, "differs from the head statement"),),
        against=True,
        refuses=None,
    ),
    Attack(
        "delete-unit-folder",
        delete_unit,
        tuple((U1, v, "unit folder deleted") for v in (1, 2, 3)),
        against=True,
        refuses=None,
    ),
    Attack("altered-older-version", altered_older, ((U0, 2, "altered"),)),
    Attack("thermal-x10-newest-stale-hashes", thermal_x10_stale_hashes, ((U0, 3, "altered"),)),
    Attack("altered-older-version-rehashed", altered_older_rehashed, ((U0, 2, "does not match the content"),)),
    Attack("altered-newest-rehashed-and-logged", altered_newest_rehashed, ((U0, 3, "does not match the content"),)),
    Attack("signature-stripped", signature_stripped, ((U1, 1, "altered"),), refuses=U1),
    Attack("duplicate-keys-prepended", duplicate_keys_prepended, ((U0, 3, 'duplicate key "coefficients"'),)),
    Attack("reformatted-newest", reformatted, ((U0, 3, "not in canonical form"),)),
    Attack(
        "stray-and-misnamed-files",
        stray_files,
        ((U0, None, "'v2.json'"), (U0, None, "'v002.json'"), (U0, None, "'notes.txt'")),
    ),
)
