"""The passport registry: an append-only, hash-chained, signed store of passport versions, one chain per unit.

Layout (everything is plain files; nothing but this module writes there)::

    ROOT/
      units/
        AU-0001/
          .lock          empty; fcntl.flock'ed by writers (exclusive) and by verify (shared)
          log.jsonl      append-only: one JSON line per version {version, sha256, created_utc, identity}
          v0001.json     passport version 1 (read-only, 0444)
          v0001.png      its verification figure (written after the version)
          v0001.constants.png   its constants against temperature (written by ``calibrate``)
          v0002.json     passport version 2, "parent_sha256" = sha256 of v0001.json's bytes
          approvals.jsonl  append-only: one signed approval record per line (:meth:`Registry.approve`)
          .tmp-*.json    only while a writer holds the lock (a leftover is a killed writer's, cleaned at next publish)

Any other name in a unit folder (``v2.json``, ``v002.json``, ``notes.txt``) is a stray file that verify names.

A version file is the passport serialised canonically (:func:`canonical_json`), so its sha256 is stable. Each
version carries ``parent_sha256`` (the previous version's file hash, a chain), ``content_sha256`` (the hash of its
own content without that field and the signature), ``signature`` (Ed25519 by the writing station's key, over the
same bytes: :mod:`pipeline.passport.signing`, keys kept outside the registry) and ``provenance.identity`` (the hash
of the input hashes and the settings: the same inputs calibrated with the same settings give the same identity, and
publish then returns the existing version). Altering a version breaks its own ``content_sha256`` (unless
recomputed), its signature (which only the station's key can remake), its child's ``parent_sha256`` and its row in
``log.jsonl``. Deleting the newest versions together with their log rows (a rollback) leaves a consistent shorter
chain: a head statement (:meth:`Registry.head`, signed, kept elsewhere) is what names them later
(``verify(against=...)``).

Versions are never modified or deleted: a new one is written to a temp file in the unit's folder, fsync'ed, then
hard-linked to its final name (which must not exist), and the folder fsync'ed; only then is its log row appended.
A unit whose chain does not verify (any version, any check) is never appended to; an interrupted write (a newest
version without its log row) is recovered only when it is this station's own signed version.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import secrets
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from pipeline.errors import RegistryError, ThermocalError
from pipeline.passport.canonical import (
    canonical_json,
    content_sha256,
    parse_canonical,
    parse_record,
    sha256_bytes,
    sha256_file,
)
from pipeline.passport.diff import diff_passports
from pipeline.passport.document import failed_verification
from pipeline.passport.signing import TrustStore, sign_record, station_key, trusted_keys, verify_record
from pipeline.passport.verification import (
    MAX_PASSPORT_BYTES,
    UNVERIFIED_HINT,
    MalformedPassport,
    SealCheck,
    UntrustedPassport,
    Verification,
    check_content,
    check_schema,
    check_sealed,
)
from pipeline.passport.verified_cache import VerifiedCache

__all__ = [
    "Problem",
    "PublishResult",
    "Registry",
    "VersionInfo",
    "VerifyReport",
    "canonical_json",
    "identity_key",
    "load_passport_file",
    "safe_unit_name",
    "sha256_bytes",
    "sha256_file",
    "content_sha256",
]

_VERSION_FILE = re.compile(r"^v(\d+)\.json$")
_FIGURE_FILE = re.compile(r"^v(\d+)(\.constants)?\.png$")
_TEMP_PREFIX = ".tmp-"
_UNIT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_LOG_NAME = "log.jsonl"
_LOCK_NAME = ".lock"
#: Other names a unit folder may hold besides versions, their figures, the log, the lock and temp files.
OTHER_UNIT_FILES: frozenset[str] = frozenset({"approvals.jsonl"})
HEAD_SCHEMA = "thermocal.head/1"
APPROVAL_SCHEMA = "thermocal.approval/1"
_APPROVALS_NAME = "approvals.jsonl"
_ERRNO_TEXT = {
    errno.ENOSPC: "no space left on device (disk full)",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large (size limit reached)",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied (read-only registry?)",
    errno.EPERM: "operation not permitted (read-only registry?)",
    errno.ENOTDIR: "not a directory",
    errno.EEXIST: "already exists",
}


# ---------------------------------------------------------------------------------------------------------------
# hashing and canonical serialisation


#: optional keys of a provenance input: the unit within a run with several units (log-format.md) and its run_id;
#: the PX4 device id of the unit's accelerometer from the run's metadata (``thermocal export --format px4``)
_INPUT_EXTRA_KEYS = ("unit", "run_id", "px4_accel_device_id")


def _input_record(item: dict) -> dict:
    """A provenance input as stored: ``path`` and ``sha256``, and ``unit`` / ``run_id`` when given (an input that
    is one unit of a run with several names the unit)."""
    out = {"path": str(item["path"]), "sha256": str(item["sha256"])}
    out.update({k: str(item[k]) for k in _INPUT_EXTRA_KEYS if item.get(k) is not None})
    return out


def identity_key(inputs: list[dict], settings: dict) -> str:
    """What makes two calibrations "the same": sha256 of the canonical JSON of the sorted input hashes and settings."""
    return sha256_bytes(canonical_json({"inputs": sorted(str(i["sha256"]) for i in inputs), "settings": settings}))


def safe_unit_name(unit: Any) -> str:
    """A unit serial usable as a folder name: letters, digits, ``.``, ``_``, ``-``; no separator, no ``..``."""
    if not isinstance(unit, str) or not _UNIT_NAME.match(unit) or ".." in unit:
        raise RegistryError(
            f"unit serial {unit!r} is not usable as a registry name "
            "(letters, digits, '.', '_', '-'; no path separator, no '..', at most 100 characters)"
        )
    return unit


def _version_name(version: int) -> str:
    """The one file name of a version: ``v0001.json`` ... ``v9999.json``, ``v10000.json`` ..."""
    return f"v{int(version):04d}.json"


def version_of_name(name: str) -> int | None:
    """The version a file name is the one name of (``v0003.json`` -> 3), else None."""
    m = _VERSION_FILE.match(name)
    return int(m.group(1)) if m and name == _version_name(int(m.group(1))) else None


class Problem(str):
    """A problem :meth:`Registry.verify` names (its text), with the version it concerns (None: the unit as a whole:
    a stray file, a damaged log), so that a command using version v is refused only for what concerns v or its
    ancestors."""

    version: int | None

    def __new__(cls, text: str, version: int | None = None) -> Problem:
        self = super().__new__(cls, text)
        self.version = version
        return self


def _problem_version(problem: str) -> int | None:
    """The version a problem line concerns (:class:`Problem`), None for the unit as a whole."""
    return problem.version if isinstance(problem, Problem) else None


def _version_info(v: int, path: Path, data: bytes, doc: dict | None) -> VersionInfo:
    """What a listing shows of a version: ``status`` "unreadable" when its bytes are not a record; fields of
    the wrong type are shown as missing."""
    if doc is None:
        return VersionInfo(v, path, sha256_bytes(data), None, "unreadable", [])

    def field_text(key: str) -> str | None:
        value = doc.get(key)
        return value if isinstance(value, str) else None

    provenance = doc.get("provenance")
    inputs = provenance.get("inputs") if isinstance(provenance, dict) else None
    return VersionInfo(
        v,
        path,
        sha256_bytes(data),
        field_text("created_utc"),
        field_text("status"),
        [i for i in inputs if isinstance(i, dict)] if isinstance(inputs, list) else [],
        field_text("method"),
    )


def _utc_now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


# ---------------------------------------------------------------------------------------------------------------
# file-system helpers (every OSError becomes a one-line RegistryError naming the path)


@contextlib.contextmanager
def _os_errors(path: Path, doing: str) -> Iterator[None]:
    try:
        yield
    except RegistryError:
        raise
    except OSError as exc:
        # name the file the user knows, not a temp file that is already removed
        named = exc.filename and not Path(os.fsdecode(exc.filename)).name.startswith(_TEMP_PREFIX)
        where = exc.filename if named else path
        reason = _ERRNO_TEXT.get(exc.errno or 0, exc.strerror or str(exc))  # errno 0: none given
        raise RegistryError(f"cannot {doing}: {reason}", path=str(where)) from exc


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def _flock(path: Path, exclusive: bool) -> Iterator[None]:
    """Hold flock on ``path`` (created if exclusive). A shared lock on a missing lock file is a no-op."""
    if exclusive:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    else:
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            yield
            return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)  # closing releases the lock


#: The largest log or approvals file read (a row is ~200 bytes: a million versions).
_MAX_LOG_BYTES = 256 << 20


def _read_small(path: Path, doing: str, limit: int = MAX_PASSPORT_BYTES) -> bytes | None:
    """The bytes of a registry file, or None when it is larger than ``limit``; only a regular file is opened (a
    FIFO planted in a unit folder must not hang verify). RegistryError (one line) when it cannot be read."""
    from pipeline.io.files import open_regular

    with _os_errors(path, doing):
        with open_regular(path, RegistryError) as f:
            if os.fstat(f.fileno()).st_size > limit:
                return None
            return f.read()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


# ---------------------------------------------------------------------------------------------------------------
# public records


@dataclass(frozen=True)
class PublishResult:
    """Outcome of :meth:`Registry.publish`: the version written (``created``) or the existing one with that identity."""

    unit: str
    version: int
    path: Path
    sha256: str
    created: bool
    passport: dict = field(default_factory=dict, repr=False, compare=False)


@dataclass(frozen=True)
class VersionInfo:
    """One version of a unit as stored. ``status`` is ``"unreadable"`` for a file that is not valid JSON."""

    version: int
    path: Path
    sha256: str
    created_utc: str | None
    status: str | None
    inputs: list[dict]
    method: str | None = None


@dataclass(frozen=True)
class VersionState:
    """What a person must know of the version a command uses: its status, who approved it, and whether it is the
    unit's current passport (docs/contract.md: the newest approved version, else the newest that did not fail;
    :meth:`Registry.state`)."""

    unit: str
    version: int
    status: str | None
    approved_by: tuple[str, ...]
    current: bool
    verification: Verification | None = None

    @classmethod
    def of_file(cls, doc: dict, verification: Verification) -> VersionState:
        """The state of a passport read from a file outside a registry (approval unknown, never current)."""
        version = doc.get("version")
        status = doc.get("status")
        return cls(
            str(doc.get("unit")),
            version if isinstance(version, int) else 0,
            status if isinstance(status, str) else None,
            (),
            False,
            verification,
        )

    @property
    def approved(self) -> bool:
        return bool(self.approved_by)

    @property
    def unverified(self) -> bool:
        """Used although it does not verify (``--unverified``)."""
        return self.verification is not None and not self.verification.verified

    def approval_text(self) -> str:
        """``approved by A. Metrologist`` or ``not approved`` (with, for the current passport, why it is current)."""
        if self.verification is not None and self.verification.loose:
            text = "approval unknown (a passport file, not read from a registry)"
        elif self.approved_by:
            text = f"approved by {', '.join(self.approved_by)}"
        else:
            text = "not approved" + (
                "; the current passport: the newest version that did not fail, none is approved" if self.current else ""
            )
        check = self.verification
        return text + (f"; {check.label}" if check is not None and not check.verified else "")

    def text(self) -> str:
        """``AU-0001 v2 (status pass, approved by A. Metrologist)``, ``AU-0001 v3 (status pass, not approved; the
        current passport: the newest version that did not fail, none is approved)``; ``UNVERIFIED (--unverified):
        <why>`` added for a version used without its verification."""
        return f"{self.unit} v{self.version} (status {self.status}, {self.approval_text()})"

    def warning(self) -> str | None:
        """One line for stderr when the version failed its verification (a failed version is never approved) or
        is used although it does not verify (``--unverified``)."""
        parts = []
        if self.status == "fail":
            parts.append(failed_verification(f"{self.unit} v{self.version}") + "; it is not approved")
        check = self.verification
        if check is not None and not check.verified:
            parts.append(f"{check.subject} is used {check.label}")
        return "; ".join(parts) or None

    def as_dict(self) -> dict:
        out = {
            "unit": self.unit,
            "version": self.version,
            "status": self.status,
            "approved": self.approved,
            "approved_by": list(self.approved_by),
            "current": self.current,
        }
        if self.verification is not None:
            out["verification"] = self.verification.as_dict()
        return out


@dataclass
class VerifyReport:
    """Integrity of a registry. ``problems`` (each naming unit and version) make ``ok`` False; ``notes`` do not."""

    ok: bool
    problems: list[str]
    notes: list[str]
    units_checked: int = 0
    versions_checked: int = 0


@dataclass
class _UnitState:
    """What a unit folder holds: version files, log rows, leftover temp files, other names."""

    files: dict[int, Path]
    log_rows: dict[int, dict]
    log_issues: list[tuple[str, bool]]  # (text, is_problem)
    temps: list[Path]
    partial_log_tail: bool
    strays: list[Path] = field(default_factory=list)

    @property
    def latest(self) -> int:
        return max([0, *self.files, *self.log_rows])


# ---------------------------------------------------------------------------------------------------------------
# the registry


class Registry:
    """A folder of passports, one append-only hash chain per unit (layout in the module docstring)."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    # -- paths --------------------------------------------------------------------------------------------------

    @property
    def units_dir(self) -> Path:
        return self.root / "units"

    def unit_dir(self, unit: str) -> Path:
        return self.units_dir / safe_unit_name(unit)

    def version_path(self, unit: str, version: int) -> Path:
        return self.unit_dir(unit) / _version_name(version)

    # -- reading ------------------------------------------------------------------------------------------------

    def units(self) -> list[str]:
        """Serials of the units with a folder in the registry (empty for a registry not yet written)."""
        if not self.units_dir.is_dir():
            return []
        with _os_errors(self.units_dir, "list units"):
            return sorted(
                p.name
                for p in self.units_dir.iterdir()
                if p.is_dir() and _UNIT_NAME.match(p.name) and ".." not in p.name
            )

    def _scan(self, unit: str) -> _UnitState:
        udir = self.unit_dir(unit)
        files: dict[int, Path] = {}
        temps: list[Path] = []
        strays: list[Path] = []
        with _os_errors(udir, "read unit folder"):
            for p in udir.iterdir():
                m = _VERSION_FILE.match(p.name)
                if m and p.name == _version_name(int(m.group(1))) and p.is_file():
                    files[int(m.group(1))] = p
                elif p.name.startswith(_TEMP_PREFIX):
                    temps.append(p)
                elif not (p.name in (_LOG_NAME, _LOCK_NAME, *OTHER_UNIT_FILES) or _FIGURE_FILE.match(p.name)):
                    strays.append(p)
            rows, issues, partial = self._read_log(udir / _LOG_NAME)
        return _UnitState(files, rows, issues, sorted(temps), partial, sorted(strays))

    @staticmethod
    def _read_log(path: Path) -> tuple[dict[int, dict], list[tuple[str, bool]], bool]:
        """Rows by version; issues found (text, is_problem); whether the last line is an unterminated fragment."""
        rows: dict[int, dict] = {}
        issues: list[tuple[str, bool]] = []
        if not path.exists():
            return rows, issues, False
        data = _read_small(path, "read the log", limit=_MAX_LOG_BYTES)
        if data is None:
            return rows, [(f"{_LOG_NAME} is larger than any registry's log: not read", True)], False
        partial = bool(data) and not data.endswith(b"\n")
        lines = data.split(b"\n")[:-1]  # without the text after the last newline ("" or a fragment)
        if partial:
            issues.append(
                (
                    "log.jsonl ends with an unterminated line (writer interrupted); it is dropped at the next publish",
                    False,
                )
            )
        for k, line in enumerate(lines, start=1):
            try:
                row = parse_record(line)
                v = row["version"]
                if not isinstance(v, int) or not isinstance(row["sha256"], str):
                    raise TypeError
            except (ValueError, KeyError, TypeError):
                issues.append((f"log.jsonl line {k} is not a valid log row", True))
                continue
            if v in rows:
                issues.append((f"log.jsonl has two rows for v{v}", True))
            rows[v] = row
        return rows, issues, partial

    def _require_unit(self, unit: str) -> Path:
        udir = self.unit_dir(unit)
        if not udir.is_dir():
            if not self.root.is_dir():
                raise RegistryError("no registry here (not a directory)", path=str(self.root))
            raise RegistryError(f"unknown unit {unit!r}", path=str(self.root))
        return udir

    def versions(self, unit: str) -> list[VersionInfo]:
        """Every stored version of ``unit``, oldest first (unknown unit -> RegistryError)."""
        self._require_unit(unit)
        out = []
        for v, path in sorted(self._scan(unit).files.items()):
            data = _read_small(path, "read passport")
            try:
                doc = parse_record(data) if data is not None else None
            except ValueError:
                doc = None
            data = data if data is not None else b""
            out.append(_version_info(v, path, data, doc))
        return out

    def load(self, unit: str, version: int | None = None) -> dict:
        """The passport document of ``unit`` at ``version`` (the latest if None)."""
        udir = self._require_unit(unit)
        files = self._scan(unit).files
        if not files:
            raise RegistryError(f"unit {unit!r} has no version", path=str(udir))
        v = max(files) if version is None else int(version)
        if v not in files:
            raise RegistryError(f"unit {unit!r} has no version {v} (versions 1..{max(files)})", path=str(udir))
        data = _read_small(files[v], "read passport")
        if data is None:
            raise RegistryError("larger than any passport: not read", path=str(files[v]))
        try:
            doc = json.loads(data)
        except (ValueError, RecursionError) as exc:
            raise RegistryError(f"passport is not valid JSON ({exc})", path=str(files[v])) from exc
        if not isinstance(doc, dict):
            raise RegistryError("passport is not a JSON object", path=str(files[v]))
        return doc

    def log(self, unit: str) -> list[dict]:
        """Rows for ``passport log``: version, created_utc, status, inputs (paths), sha256, and ``approved`` (the
        valid approval records of that version: by, approved_utc) and ``current`` (True for the unit's current
        passport, :meth:`current`)."""
        approvals = self.approvals(unit)
        current = self.current(unit)
        return [
            {
                "version": i.version,
                "created_utc": i.created_utc,
                "status": i.status,
                "inputs": [str(x.get("path")) for x in i.inputs if isinstance(x, dict)],
                "sha256": i.sha256,
                "approved": [
                    {"by": a["by"], "approved_utc": a["approved_utc"]}
                    for a in approvals
                    if a["version"] == i.version and a["sha256"] == i.sha256
                ],
                "current": i.version == current,
            }
            for i in self.versions(unit)
        ]

    # -- approvals and the current passport ----------------------------------------------------------------------

    def approve(self, unit: str, version: int, by: str) -> dict:
        """Record that ``by`` approved ``version`` of ``unit``: a signed record of its own (schema
        ``thermocal.approval/1``: unit, version, the version file's sha256, by, approved_utc), appended to the
        unit's ``approvals.jsonl``. The version itself is not changed. Approving an already approved version
        returns its existing record. RegistryError: unknown unit or version, a version that does not check
        out (altered after writing), a failed calibration, an empty name."""
        by = " ".join(str(by).split())
        if not by:
            raise RegistryError("approve needs the approver's name (--by NAME)")
        udir = self._require_unit(unit)
        if int(version) in self._scan(unit).files:
            self.load_state(unit, int(version))  # only a version that verifies is approved (else one line)
        key = station_key()
        with _os_errors(udir / _LOCK_NAME, "lock the unit"), _flock(udir / _LOCK_NAME, exclusive=True):
            state = self._scan(unit)
            v = int(version)
            if v not in state.files:
                raise RegistryError(f"unit {unit!r} has no version {v}", path=str(udir))
            with _os_errors(state.files[v], "read passport"):
                data = state.files[v].read_bytes()
            digest = sha256_bytes(data)
            row = state.log_rows.get(v)
            if row is None or row.get("sha256") != digest:
                raise RegistryError(
                    f"unit {unit} v{v} does not match its log.jsonl row (altered or not yet "
                    "recorded); run 'thermocal passport verify'",
                    path=str(state.files[v]),
                )
            status = json.loads(data).get("status")
            if status == "fail":
                raise RegistryError(
                    f"unit {unit} v{v} failed its verification (status fail) and cannot be approved",
                    path=str(state.files[v]),
                )
            for rec in self._approval_records(udir)[0]:
                if rec.get("version") == v and rec.get("sha256") == digest and rec.get("by") == by:
                    return rec
            record = sign_record(
                {
                    "schema": APPROVAL_SCHEMA,
                    "unit": unit,
                    "version": v,
                    "sha256": digest,
                    "status": status,
                    "by": by,
                    "approved_utc": _utc_now(),
                },
                key,
            )
            self._append_log(udir, record, _APPROVALS_NAME)
        return record

    @staticmethod
    def _approval_records(udir: Path) -> tuple[list[dict], list[tuple[str, bool]]]:
        """Every parsable record of ``approvals.jsonl`` (signature not checked) and the issues found (text,
        is_problem): a line that is not a record is a problem, an unterminated last line (a killed writer) a
        note."""
        path = udir / _APPROVALS_NAME
        if not path.exists():
            return [], []
        data = _read_small(path, f"read {_APPROVALS_NAME}", limit=_MAX_LOG_BYTES)
        if data is None:
            return [], [(f"{_APPROVALS_NAME} is larger than any registry's approvals: not read", True)]
        issues: list[tuple[str, bool]] = []
        if data and not data.endswith(b"\n"):
            issues.append((f"{_APPROVALS_NAME} ends with an unterminated line (writer interrupted); ignored", False))
        records = []
        for k, line in enumerate(data.split(b"\n")[:-1], start=1):
            try:
                rec = parse_record(line)  # no duplicate keys: one reading of who approved what
                if rec.get("schema") != APPROVAL_SCHEMA or not isinstance(rec.get("version"), int):
                    raise ValueError
                str(rec["sha256"]), str(rec["by"])
            except (ValueError, KeyError, TypeError):
                issues.append((f"{_APPROVALS_NAME} line {k} is not an approval record", True))
                continue
            records.append(rec)
        return records, issues

    def approvals(self, unit: str, trust: TrustStore | None = None) -> list[dict]:
        """The unit's approval records whose content and signature check out (oldest first)."""
        udir = self._require_unit(unit)
        records, _ = self._approval_records(udir)
        if not records:
            return []
        trust = trust or trusted_keys()
        return [r for r in records if r.get("content_sha256") == content_sha256(r) and verify_record(r, trust).ok]

    def current(self, unit: str, *, exclude_methods: tuple[str, ...] = ()) -> int | None:
        """The unit's current passport version, the one rule every command uses (docs/contract.md): the newest approved
        version (a valid approval record whose sha256 is the version file's), else the newest version that did not
        fail its verification (a failed calibration is never the current passport); None for a unit without such a
        version. ``exclude_methods``: leave out the versions made by these methods (the differential method's base
        is never a differential passport)."""
        return self._current(unit, self.versions(unit), self.approvals(unit), exclude_methods)

    @staticmethod
    def _current(
        unit: str, infos: list[VersionInfo], approvals: list[dict], exclude_methods: tuple[str, ...]
    ) -> int | None:
        versions = {i.version: i for i in infos if i.method not in exclude_methods}
        approved = [
            a["version"] for a in approvals if a["version"] in versions and versions[a["version"]].sha256 == a["sha256"]
        ]
        if approved:
            return max(approved)
        usable = [v for v, i in versions.items() if i.status != "fail"]
        return max(usable) if usable else None

    def state(
        self, unit: str, version: int | None = None, *, exclude_methods: tuple[str, ...] = ()
    ) -> VersionState | None:
        """The state of ``version`` of ``unit`` (default: the current passport, :meth:`current`): its status, its
        approvals, whether it is current. None when there is no such version (no current one)."""
        infos, approvals = self.versions(unit), self.approvals(unit)
        current = self._current(unit, infos, approvals, exclude_methods)
        v = current if version is None else version
        info = next((i for i in infos if i.version == v), None)
        if info is None:
            return None
        by = tuple(a["by"] for a in approvals if a["version"] == v and a["sha256"] == info.sha256)
        return VersionState(unit, info.version, info.status, by, v == self._current(unit, infos, approvals, ()))

    def load_state(
        self,
        unit: str,
        version: int | None = None,
        *,
        exclude_methods: tuple[str, ...] = (),
        unverified: bool = False,
        expect_bytes: bytes | None = None,
    ) -> tuple[dict, VersionState]:
        """The passport at ``version`` (default: the unit's current passport, :meth:`current`), verified, and its
        :class:`VersionState` (with its :class:`~pipeline.passport.verification.Verification`): the one path by
        which a command uses a registry's passport.

        The unit's chain is checked as :meth:`verify` does (canonical bytes, hashes, signatures, parent links, log,
        approvals) from the bytes that are returned. A problem with the version used, an older one, or the unit as
        a whole (and, for the current passport, which depends on every version, any problem) refuses it in one
        line (:class:`~pipeline.passport.verification.UntrustedPassport`) unless ``unverified``; then it is used
        and its state says so. Its content is checked either way
        (:func:`~pipeline.passport.verification.check_content`). ``expect_bytes``: the version's bytes as a caller
        read them (a file named by path): anything else is a problem. RegistryError: no such unit or version."""
        udir = self._require_unit(unit)
        trust = trusted_keys()
        problems: list[str] = []
        with _os_errors(udir / _LOCK_NAME, "lock the unit"), _flock(udir / _LOCK_NAME, exclusive=False):
            scan = self._scan(unit)
            docs = self._check_unit(unit, scan, trust, problems, [])
        if not scan.files:
            raise RegistryError(f"unit {unit!r} has no version", path=str(udir))
        infos = [_version_info(v, scan.files[v], data, doc) for v, (doc, data) in sorted(docs.items())]
        approvals = self.approvals(unit, trust)
        if version is None:
            v = self._current(unit, infos, approvals, exclude_methods)
            if v is None:
                only = f" other than by the {', '.join(exclude_methods)} method" if exclude_methods else ""
                raise RegistryError(
                    f"unit {unit!r} has no current passport: no version{only} is approved and every one failed its "
                    "verification (status fail); name a version to use one",
                    path=str(udir),
                )
        else:
            v = int(version)
            if v not in scan.files:
                raise RegistryError(f"unit {unit!r} has no version {v} (versions 1..{max(scan.files)})", path=str(udir))
        blocking = [p for p in problems if version is None or (pv := _problem_version(p)) is None or pv <= v]
        doc, data = docs[v]
        if expect_bytes is not None and expect_bytes != data:
            blocking.insert(0, Problem(f"{unit} v{v}: the file changed while it was read", v))
        if blocking and not unverified:
            more = f" (and {len(blocking) - 1} more)" if len(blocking) > 1 else ""
            raise UntrustedPassport(
                f"{unit} v{v} is not used: the registry does not verify: {blocking[0]}{more}; run 'thermocal "
                f"passport verify --registry {self.root}' ({UNVERIFIED_HINT})",
                path=str(scan.files[v]),
            )
        subject = f"{unit} v{v}"
        if doc is None:
            raise UntrustedPassport(f"{subject} is not a passport record: {blocking[0]}", path=str(scan.files[v]))
        check_content(doc, f"{scan.files[v]}")
        sig = doc.get("signature")
        key_id = sig.get("key_id") if isinstance(sig, dict) and isinstance(sig.get("key_id"), str) else None
        verification = Verification(subject, not blocking, str(blocking[0]) if blocking else None, key_id)
        info = next(i for i in infos if i.version == v)
        by = tuple(a["by"] for a in approvals if a["version"] == v and a["sha256"] == info.sha256)
        current = v == self._current(unit, infos, approvals, ())
        return doc, VersionState(unit, v, info.status, by, current, verification)

    def verified_versions(self, unit: str) -> tuple[dict[int, dict], list[str]]:
        """Every version of ``unit`` that verifies together with all its ancestors (oldest first: the history a
        command such as ``trends`` may read), and the problems found (empty: the whole chain verifies). A version
        whose content is malformed is left out with its reason. RegistryError: no such unit."""
        docs, problems, _ = self.verified_history(unit)
        return docs, problems

    def verified_history(
        self, unit: str, trust: TrustStore | None = None, cache: VerifiedCache | None = None
    ) -> tuple[dict[int, dict], list[str], int | None]:
        """:meth:`verified_versions` and the unit's :meth:`current` version, from the one reading of its files
        (``trends``: each version read, parsed and encoded once). ``trust``: the trusted keys
        (:func:`~pipeline.passport.signing.trusted_keys` unless given: a caller reading many units reads them once).
        ``cache``: files verified in full before (:mod:`~pipeline.passport.verified_cache`) skip the checks of their
        bytes alone (canonical form, self-hash, signature, content), never those of their place in the chain; the
        versions verified in full here are added to it."""
        udir = self._require_unit(unit)
        trust = trust or trusted_keys()
        problems: list[str] = []
        shas: dict[int, str] = {}
        cached: set[int] = set()
        with _os_errors(udir / _LOCK_NAME, "lock the unit"), _flock(udir / _LOCK_NAME, exclusive=False):
            scan = self._scan(unit)
            docs = self._check_unit(unit, scan, trust, problems, [], cache, shas, cached)
        infos = [_version_info(v, scan.files[v], data, doc) for v, (doc, data) in sorted(docs.items())]
        current = self._current(unit, infos, self.approvals(unit, trust), ())
        whole_unit = [p for p in problems if _problem_version(p) is None]
        first_bad = min((pv for p in problems if (pv := _problem_version(p)) is not None), default=None)
        out: dict[int, dict] = {}
        if whole_unit:
            return out, problems, current
        for v, (doc, _) in sorted(docs.items()):
            if (first_bad is not None and v >= first_bad) or doc is None:
                break
            if v not in cached:
                try:
                    check_content(doc, f"{unit} v{v}")
                except ThermocalError as exc:
                    problems.append(Problem(exc.one_line(), v))
                    break
            out[v] = doc
        if cache is not None:
            cache.add([shas[v] for v in out if v not in cached])
        return out, problems, current

    def planned(self, passport: dict, *, inputs: list[dict], settings: dict) -> tuple[int, bool]:
        """What :meth:`publish` would do, writing nothing (``calibrate --dry-run``): (the version it would
        write, False), or (the existing version with the same identity, True)."""
        unit = safe_unit_name(passport.get("unit"))
        try:
            inputs = [_input_record(i) for i in inputs]
            settings = json.loads(canonical_json(settings))
        except (KeyError, TypeError, ValueError) as exc:
            raise RegistryError(f"inputs or settings are not valid JSON content ({exc})") from exc
        if not self.unit_dir(unit).is_dir():
            return 1, False
        found = self.find(unit, identity_key(inputs, settings))
        if found is not None:
            return found.version, True
        return self._scan(unit).latest + 1, False

    def find(self, unit: str, identity: str, *more: str) -> VersionInfo | None:
        """The latest version of ``unit`` published with this identity key (see :func:`identity_key`), if any; with
        ``more`` keys, that of the first key (in the order given) that has one. One scan of the unit's folder."""
        if not self.unit_dir(unit).is_dir():
            return None
        rows = self._scan(unit).log_rows
        for key in (identity, *more):
            hits = [v for v, row in rows.items() if row.get("identity") == key]
            if hits:
                v = max(hits)
                return next((i for i in self.versions(unit) if i.version == v), None)
        return None

    # -- writing ------------------------------------------------------------------------------------------------

    def publish(self, passport: dict, *, inputs: list[dict], settings: dict, code_version: str) -> PublishResult:
        """Store ``passport`` as the next version of its unit, or return the version with the same identity.

        Sets ``version``, ``parent_sha256``, ``created_utc``, ``provenance`` {inputs, code_version, settings,
        identity} (other provenance keys kept) and ``content_sha256``. The caller's dict is not modified.
        Raises RegistryError (one line, with the path) if the registry cannot be written; nothing partial is left.
        """
        if not isinstance(passport, dict):
            raise RegistryError("a passport must be a JSON object (dict)")
        unit = safe_unit_name(passport.get("unit"))
        try:
            inputs = [_input_record(i) for i in inputs]
            settings = json.loads(canonical_json(settings))
            doc = json.loads(canonical_json(passport))
        except (KeyError, TypeError, ValueError) as exc:
            raise RegistryError(f"passport, inputs or settings are not valid JSON content ({exc})") from exc
        identity = identity_key(inputs, settings)

        udir = self.unit_dir(unit)
        if udir.exists() and not udir.is_dir():
            raise RegistryError("cannot create the unit folder: a file is in the way", path=str(udir))
        with _os_errors(udir, "create the unit folder"):
            created_dir = not udir.is_dir()
            udir.mkdir(parents=True, exist_ok=True)
            if created_dir:
                _fsync_dir(udir.parent)
        key = station_key()  # before the lock: created on first use, with its message
        trust = trusted_keys()
        with _os_errors(udir / _LOCK_NAME, "lock the unit"), _flock(udir / _LOCK_NAME, exclusive=True):
            state = self._prepare_locked(unit, udir, trust)
            for v, row in sorted(state.log_rows.items(), reverse=True):
                if row.get("identity") == identity:
                    return PublishResult(unit, v, state.files[v], row["sha256"], False, self.load(unit, v))
            latest = state.latest
            doc["version"] = latest + 1
            doc["parent_sha256"] = state.log_rows[latest]["sha256"] if latest else None
            doc["created_utc"] = _utc_now()
            doc["provenance"] = {
                **(doc.get("provenance") or {}),
                "inputs": inputs,
                "code_version": code_version,
                "settings": settings,
                "identity": identity,
            }
            doc = sign_record(doc, key)
            data = canonical_json(doc)
            final = self.version_path(unit, doc["version"])
            self._write_version(udir, final, data)
            digest = sha256_bytes(data)
            try:
                self._append_log(
                    udir,
                    {
                        "version": doc["version"],
                        "sha256": digest,
                        "created_utc": doc["created_utc"],
                        "identity": identity,
                    },
                )
            except RegistryError:
                # all or nothing: the version is not published until logged, so take it back
                with contextlib.suppress(OSError):
                    final.unlink()
                    _fsync_dir(udir)
                raise
        _remember_verified(data, digest, trust)
        return PublishResult(unit, doc["version"], final, digest, True, doc)

    def _prepare_locked(self, unit: str, udir: Path, trust: TrustStore) -> _UnitState:
        """Under the unit's exclusive lock: clean a killed writer's leftovers, check the whole chain, return state.

        Repairs only what an interrupted writer can leave: temp files, an unterminated last log line, and a newest
        version file whose log row was not yet appended: recorded now, but only if it is this station's own signed
        version with a correct self-hash and parent link. Then every version of the unit must verify
        (:meth:`verify`'s checks, signatures included); if any does not, the publish is refused in one line.
        """
        state = self._scan(unit)
        with _os_errors(udir, "clean up after an interrupted writer"):
            for tmp in state.temps:
                tmp.unlink(missing_ok=True)
            state.temps = []
            log_path = udir / _LOG_NAME
            if state.partial_log_tail:
                data = log_path.read_bytes()
                with open(log_path, "r+b") as f:
                    f.truncate(data.rfind(b"\n") + 1)
                    f.flush()
                    os.fsync(f.fileno())
                state.log_issues = [(text, p) for text, p in state.log_issues if p]
                state.partial_log_tail = False
        last_logged = max(state.log_rows, default=0)
        unlogged = sorted(v for v in state.files if v > last_logged)
        if len(unlogged) == 1 and unlogged[0] == last_logged + 1 and not any(p for _, p in state.log_issues):
            v = unlogged[0]
            with _os_errors(state.files[v], "read passport"):
                data = state.files[v].read_bytes()
            try:
                doc = json.loads(data)
                doc_ok = content_sha256(doc) == doc.get("content_sha256")
            except (ValueError, AttributeError, TypeError):
                doc, doc_ok = {}, False
            parent = state.log_rows[last_logged]["sha256"] if last_logged else None
            sig = verify_record(doc, trust) if doc_ok else None
            if not doc_ok or doc.get("parent_sha256") != parent or doc.get("version") != v:
                why = "fails its own checks"
            elif sig is not None and not (sig.ok and sig.own):  # (sig is None only when not doc_ok)
                why = (
                    "is not this station's own signed version"
                    + (f" ({sig.problem})" if sig.problem else "")
                    + "; it is not recovered"
                )
            else:
                why = None
            if why:
                raise RegistryError(
                    f"unit {unit} v{v}: not in log.jsonl and {why}; run 'thermocal passport verify'",
                    path=str(state.files[v]),
                )
            row = {
                "version": v,
                "sha256": sha256_bytes(data),
                "created_utc": doc.get("created_utc"),
                "identity": (doc.get("provenance") or {}).get("identity"),
                "recovered": True,
            }
            self._append_log(udir, row)
            state.log_rows[v] = row
        problems: list[str] = []
        self._check_unit(unit, state, trust, problems, [])
        if problems:
            more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
            raise RegistryError(
                f"refusing to append to a chain that does not verify: {problems[0]}{more}; run "
                "'thermocal passport verify'",
                path=str(udir),
            )
        return state

    @staticmethod
    def _write_version(udir: Path, final: Path, data: bytes) -> None:
        """Atomically create ``final``: temp file, fsync, link (never over an existing name), fsync the folder."""
        tmp = udir / f"{_TEMP_PREFIX}{final.stem}-{os.getpid()}-{secrets.token_hex(4)}.json"
        try:
            with _os_errors(final, "write passport"):
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                try:
                    _write_all(fd, data)
                    os.fsync(fd)
                    os.fchmod(fd, 0o444)
                finally:
                    os.close(fd)
            with _os_errors(final, "publish passport"):
                try:
                    os.link(tmp, final)  # fails if final exists: a version is never overwritten
                except OSError as exc:
                    if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
                        raise
                    # no hard links on this file system: rename, safe because we hold the unit's lock
                    if final.exists():
                        raise FileExistsError(errno.EEXIST, "version already exists", str(final)) from exc
                    os.rename(tmp, final)
                _fsync_dir(udir)
        finally:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)

    @staticmethod
    def _append_log(udir: Path, row: dict, name: str = _LOG_NAME) -> None:
        line = json.dumps(row, sort_keys=True, separators=(",", ":")).encode("ascii") + b"\n"
        path = udir / name
        with _os_errors(path, f"append to {name}"):
            existed = path.exists()
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                size = os.fstat(fd).st_size
                try:
                    _write_all(fd, line)
                    os.fsync(fd)
                except OSError:
                    with contextlib.suppress(OSError):
                        os.ftruncate(fd, size)  # no fragment of this row left behind
                    raise
            finally:
                os.close(fd)
            if not existed:
                _fsync_dir(udir)

    # -- integrity ----------------------------------------------------------------------------------------------

    def verify(self, against: dict | None = None) -> VerifyReport:
        """Check every version's hashes, parent links and signature against each other, the logs and the trusted
        keys; name what is wrong. ``against``: a head statement (:meth:`head`) made earlier: every version it
        listed must still be here, unchanged.

        Problems: unparsable JSON, a stored content_sha256 that does not match the content, a file whose sha256
        differs from its log row or from its child's parent_sha256, a broken parent link, a missing (deleted)
        version, a version gap, a damaged log, a version without a valid signature by a trusted key, a stray or
        misnamed file in a unit folder, a version listed by ``against`` that is gone or replaced, a head statement
        not signed by a trusted key. Notes (not problems): a killed writer's leftover temp file or unterminated log
        line, a newest version whose log row was not yet appended.
        """
        if not self.root.is_dir():
            raise RegistryError("no registry here (not a directory)", path=str(self.root))
        trust = trusted_keys()
        report = VerifyReport(ok=True, problems=[], notes=[])
        if self.units_dir.is_dir():
            with _os_errors(self.units_dir, "list units"):
                for p in sorted(self.units_dir.iterdir()):
                    if p.is_dir() and _UNIT_NAME.match(p.name) and ".." not in p.name:
                        self._verify_unit(p.name, report, trust)
                    else:
                        report.notes.append(f"{p}: not a unit folder, ignored")
        if against is not None:
            self._verify_against(against, report, trust)
        report.ok = not report.problems
        return report

    def _verify_unit(self, unit: str, report: VerifyReport, trust: TrustStore) -> None:
        udir = self.unit_dir(unit)
        with _os_errors(udir / _LOCK_NAME, "lock the unit"), _flock(udir / _LOCK_NAME, exclusive=False):
            state = self._scan(unit)
            self._check_unit(unit, state, trust, report.problems, report.notes)
            report.units_checked += 1
            report.versions_checked += len(state.files)

    def _check_unit(
        self,
        unit: str,
        state: _UnitState,
        trust: TrustStore,
        problems: list[str],
        notes: list[str],
        cache: VerifiedCache | None = None,
        shas: dict[int, str] | None = None,
        cached: set[int] | None = None,
    ) -> dict[int, tuple[dict | None, bytes]]:
        """Append the unit's problems (each a :class:`Problem` naming its version) and notes (the checks of
        :meth:`verify`); return the versions read: {version: (record or None when the bytes are not one, the file's
        bytes)}. The bytes checked are the bytes returned (a version is read once). ``cache``: a file whose bytes it
        knows as verified in full is parsed without the checks of its bytes alone (their versions go into
        ``cached``); ``shas`` receives each file's sha256."""

        def problem(text: str, version: int | None = None) -> None:
            problems.append(Problem(text, version))

        for tmp in state.temps:
            notes.append(
                f"{unit}: leftover temp file {tmp.name} from an interrupted writer "
                "(not a version; removed at the next publish)"
            )
        for stray in state.strays:
            m = _VERSION_FILE.match(stray.name)
            hint = f" (misnamed: version {int(m.group(1))} would be {_version_name(int(m.group(1)))})" if m else ""
            problem(f"{unit}: stray file {stray.name!r} in the unit folder, not written by thermocal{hint}")
        for text, is_problem in state.log_issues:
            if is_problem:
                problem(f"{unit}: {text}")
            else:
                notes.append(f"{unit}: {text}")
        self._check_approvals(unit, state, trust, problems, notes)
        sha: dict[int, str] = {}
        docs: dict[int, tuple[dict | None, bytes]] = {}
        altered: set[int] = set()
        unsigned: set[int] = set()
        for v, path in sorted(state.files.items()):
            data = _read_small(path, "read passport")
            if data is None:
                problem(f"{unit} v{v}: larger than any passport ({MAX_PASSPORT_BYTES} bytes at most): altered", v)
                altered.add(v)
                docs[v] = (None, b"")
                continue
            sha[v] = sha256_bytes(data)
            row = state.log_rows.get(v)
            if row is not None and row["sha256"] != sha[v]:
                problem(f"{unit} v{v}: file was altered after writing (sha256 differs from log.jsonl)", v)
                altered.add(v)
            if cache is not None and cache.known(sha[v]):
                # the same bytes passed every check of bytes alone before (canonical: the plain parser reads them)
                seal = SealCheck(parse_canonical(data), (), canonical=True, self_hash_ok=True)
                if cached is not None:
                    cached.add(v)
            else:
                seal = check_sealed(data, trust)
            if seal.record is None:
                problem(f"{unit} v{v}: altered: {seal.problems[0]}", v)
                altered.add(v)
                docs[v] = (None, data)
                continue
            doc = seal.record
            docs[v] = (doc, data)
            if not seal.canonical:
                problem(f"{unit} v{v}: altered: {seal.problems[0]}", v)
                altered.add(v)
            elif not seal.self_hash_ok:
                problem(f"{unit} v{v}: {seal.problems[0]}", v)
                altered.add(v)
            if doc.get("version") != v or doc.get("unit") != unit:
                problem(f"{unit} v{v}: file says unit {doc.get('unit')!r} version {doc.get('version')!r}", v)
            if seal.canonical and seal.self_hash_ok and not seal.ok:  # (a bad self-hash already names it)
                sig_problem = seal.problems[0]
                problem(
                    f"{unit} v{v}: hashes are consistent but it is {sig_problem}"
                    if sig_problem.startswith(("not signed", "signed by"))
                    else f"{unit} v{v}: {sig_problem}",
                    v,
                )
                unsigned.add(v)
        if shas is not None:
            shas.update(sha)
        last_logged = max(state.log_rows, default=0)
        for v in range(1, state.latest + 1):
            if v not in state.files:
                what = "deleted (listed in log.jsonl)" if v in state.log_rows else "version gap"
                problem(f"{unit} v{v}: version file missing, {what}", v)
            elif v not in state.log_rows:
                if v == state.latest and v == last_logged + 1 and v not in altered | unsigned:
                    notes.append(
                        f"{unit} v{v}: not yet in log.jsonl (writer interrupted after writing it); "
                        "recorded at the next publish"
                    )
                else:
                    problem(f"{unit} v{v}: not recorded in log.jsonl", v)
        for v, (record, _) in sorted(docs.items()):
            if record is None:
                continue
            parent = record.get("parent_sha256")
            if v == 1:
                if parent is not None:
                    problem(f"{unit} v1: parent_sha256 should be null", v)
            elif v - 1 in sha and parent != sha[v - 1]:
                if v - 1 in altered:
                    problem(
                        f"{unit} v{v - 1}: file sha256 does not match v{v}'s parent_sha256 (v{v - 1} altered)", v - 1
                    )
                else:
                    problem(f"{unit} v{v}: broken parent link (parent_sha256 does not match v{v - 1}'s file)", v)
        return docs

    def _check_approvals(
        self, unit: str, state: _UnitState, trust: TrustStore, problems: list[str], notes: list[str]
    ) -> None:
        """Every approval record: its own hash, a trusted signature, and a version that holds the approved bytes."""
        records, issues = self._approval_records(self.unit_dir(unit))
        for text, is_problem in issues:
            (problems if is_problem else notes).append(Problem(f"{unit}: {text}") if is_problem else f"{unit}: {text}")
        for rec in records:
            v = int(rec["version"])
            what = f"{unit} approval of v{v} by {rec['by']!r}"
            if rec.get("content_sha256") != content_sha256(rec) or rec.get("unit") != unit:
                problems.append(Problem(f"{what}: altered (content_sha256 does not match)", v))
                continue
            check = verify_record(rec, trust)
            if not check.ok:
                problems.append(Problem(f"{what}: {check.problem}", v))
            path = state.files.get(v)
            if path is None:
                problems.append(Problem(f"{what}: the approved version is missing", v))
            elif sha256_file(path) != rec["sha256"]:
                problems.append(Problem(f"{what}: the version file is not the one approved (sha256 differs)", v))

    # -- head statements -----------------------------------------------------------------------------------------

    def head(self) -> dict:
        """A signed statement of every unit's newest version (``passport head``): {"schema", "registry",
        "created_utc", "units": {unit: {"version", "sha256"}}, "content_sha256", "signature"}. Kept outside the
        registry, it lets a later ``verify --against`` name versions that were deleted or rolled back.

        A registry that does not verify gets no statement (RegistryError naming the first problem): a head
        statement must not vouch for a forged version.
        """
        report = self.verify()
        if not report.ok:
            more = f" (and {len(report.problems) - 1} more)" if len(report.problems) > 1 else ""
            raise RegistryError(
                f"the registry does not verify, no head statement signed: {report.problems[0]}{more}",
                path=str(self.root),
            )
        units: dict[str, dict] = {}
        for unit in self.units():
            udir = self.unit_dir(unit)
            with _os_errors(udir / _LOCK_NAME, "lock the unit"), _flock(udir / _LOCK_NAME, exclusive=False):
                files = self._scan(unit).files
                if files:
                    v = max(files)
                    with _os_errors(files[v], "read passport"):
                        units[unit] = {"version": v, "sha256": sha256_file(files[v])}
        return sign_record(
            {"schema": HEAD_SCHEMA, "registry": str(self.root.resolve()), "created_utc": _utc_now(), "units": units}
        )

    def _verify_against(self, head: dict, report: VerifyReport, trust: TrustStore) -> None:
        """Name every version the head statement listed that this registry no longer holds, or holds changed."""
        problems = report.problems
        if not isinstance(head, dict) or head.get("schema") != HEAD_SCHEMA or not isinstance(head.get("units"), dict):
            raise RegistryError(f"not a head statement (schema {HEAD_SCHEMA}, from 'thermocal passport head')")
        when = head.get("created_utc")
        if head.get("content_sha256") != content_sha256(head):
            problems.append(f"head statement of {when}: altered (content_sha256 does not match)")
        else:
            check = verify_record(head, trust)
            if not check.ok:
                problems.append(f"head statement of {when}: {check.problem}")
        for unit, entry in sorted(head["units"].items()):
            try:
                listed, listed_sha = int(entry["version"]), str(entry["sha256"])
                udir = self.unit_dir(unit)
            except (KeyError, TypeError, ValueError, RegistryError):
                problems.append(f"head statement of {when}: entry for unit {unit!r} is malformed")
                continue
            files = self._scan(unit).files if udir.is_dir() else {}
            gone = [v for v in range(1, listed + 1) if v not in files]
            for v in gone:
                problems.append(
                    f"{unit} v{v}: listed by the head statement of {when} and no longer in the "
                    f"registry ({'unit folder deleted' if not files else 'deleted or rolled back'})"
                )
            if listed in files and sha256_file(files[listed]) != listed_sha:
                problems.append(
                    f"{unit} v{listed}: differs from the head statement of {when} (replaced: rolled "
                    "back and written again, or altered)"
                )
        report.ok = not problems

    # -- comparison ---------------------------------------------------------------------------------------------

    def diff(self, unit: str, v1: int, v2: int) -> dict:
        """What changed from version ``v1`` to ``v2`` of ``unit``, in the units of docs/physics.md
        (:func:`pipeline.passport.diff.diff_passports`)."""
        docs = [self.load(unit, v) for v in (v1, v2)]
        for v, doc in zip((v1, v2), docs):
            check_content(doc, f"{unit} v{v}")
        return diff_passports(*docs, unit=unit, v1=v1, v2=v2)


def _remember_verified(data: bytes, sha256: str, trust: TrustStore) -> None:
    """Put the bytes this station has just published into its cache of verified files
    (:mod:`~pipeline.passport.verified_cache`) when they pass the checks of bytes alone that a reader makes
    (:func:`~pipeline.passport.verification.check_sealed` under ``trust``, :func:`check_content`): the lab's own
    registry is then read warm from its first ``trends``. Never an error (the version is published already)."""
    seal = check_sealed(data, trust)
    if not seal.ok or seal.record is None:
        return
    try:
        check_content(seal.record)
    except ThermocalError:
        return
    VerifiedCache.open(trust, read_entries=False).add([sha256])


def load_passport_file(path: str | os.PathLike, *, unverified: bool = False, trust: TrustStore | None = None):
    """A passport file and its :class:`pipeline.passport.registry.VersionState` (with its :class:`Verification`),
    for a command given a file (``apply``, ``diagnose --passport``, ``calibrate --base-passport``, export and
    report given a file). A version file inside a registry (``REG/units/UNIT/vNNNN.json``) is verified as that
    registry's version (parent link, log, approvals); any other file by its own seal. Refused in one line
    (:class:`UntrustedPassport`) unless ``unverified``; always checked for well-formedness
    (:func:`check_content`)."""
    p = Path(path)
    data = _read_file(p)
    in_registry = _registry_version(p)
    if in_registry is not None:
        root, unit, version = in_registry
        return Registry(root).load_state(unit, version, unverified=unverified, expect_bytes=data)
    trust = trust or trusted_keys()
    check = check_sealed(data, trust)
    subject = str(p)
    if check.record is None:
        reason = check.problems[0].removeprefix("not a record: ")
        if reason.startswith(("unparsable JSON", "not UTF-8")):
            reason = f"the file is not JSON ({reason})"
        raise MalformedPassport(f"not a passport: {reason}", path=subject)
    check_schema(check.record, subject)
    if check.ok:
        verification = Verification(subject, True, key_id=check.key_id, loose=True)
    elif unverified:
        verification = Verification(subject, False, check.problems[0], check.key_id, loose=True)
    else:
        raise UntrustedPassport(
            f"passport does not verify: {check.problems[0]}; not used ({UNVERIFIED_HINT})", path=subject
        )
    check_content(check.record, subject)
    return check.record, VersionState.of_file(check.record, verification)


def _read_file(p: Path) -> bytes:
    from pipeline.io.files import read_regular_bytes

    return read_regular_bytes(p, what="passport", limit=MAX_PASSPORT_BYTES)


def _registry_version(p: Path) -> tuple[Path, str, int] | None:
    """(registry root, unit, version) when ``p`` is a version file in a registry's unit folder."""
    v = version_of_name(p.name)
    if v is None:
        return None
    udir = p.resolve().parent
    root = udir.parent.parent
    if udir.parent.name != "units" or not (udir / "log.jsonl").exists():
        return None
    return root, udir.name, v
