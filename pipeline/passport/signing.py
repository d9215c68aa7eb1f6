"""Signatures of registry records (passport versions, approvals, head statements): Ed25519 via ``cryptography``.

Every record a station writes into a registry is signed with that station's private key; every command that reads a
passport checks its signature against the public keys this station trusts. Both live OUTSIDE the registry, in the
key folder:

    $THERMOCAL_KEY_DIR            (if set; tests and CI point it at a temporary folder)
    else $XDG_CONFIG_HOME/thermocal/keys, else ~/.config/thermocal/keys
      station_ed25519.pem         this station's private key (PKCS#8 PEM, mode 0600)
      station_ed25519.pub         its public key (64 hex digits): copy it into other stations' trusted/ folder
      trusted/*.pub               public keys of other stations whose records this station accepts (64 hex
                                  digits, or a PEM public key); this station's own key is always trusted
      retired/*.pem               private keys replaced by ``thermocal key rotate`` (kept, never used to sign)

So someone with write access to the registry folder alone can neither sign a forged version nor add a key that
verify would accept; and the key folder itself must be this user's and closed to others (:func:`check_key_folder`:
a folder or a trusted/ folder others can write to, or a private key others can read, is refused in one line).

The key is made on first use (the first record this station signs, with one line on stderr saying where) or by
``thermocal key create``, and never silently replaced: when the private key is missing while its public key is still
there (it was deleted or moved), signing stops with one line saying how to restore it or rotate
(:func:`rotate_key`); reading and verifying never need the private key and never create one.

What is signed: the same bytes as ``content_sha256`` hashes (:func:`pipeline.passport.canonical.signed_body`, the
canonical JSON without ``content_sha256`` and ``signature``). A signed record carries::

    "signature": {"alg": "ed25519", "key_id": "<16 hex: sha256 of the raw public key>",
                  "public_key": "<64 hex>", "value": "<base64 of the 64-byte signature>"}

API for other record writers: :func:`sign_record` (a copy with ``content_sha256`` and ``signature`` set) and
:func:`verify_record` (a :class:`SignatureCheck`).
"""

from __future__ import annotations

import base64
import contextlib
import functools
import hashlib
import os
import secrets
import stat
import sys
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from pipeline.errors import RegistryError
from pipeline.passport.canonical import sha256_bytes, signed_body

__all__ = [
    "KEY_DIR_ENV",
    "KeyFolder",
    "SignatureCheck",
    "StationKey",
    "TrustStore",
    "check_key_folder",
    "create_key",
    "describe_keys",
    "key_dir",
    "rotate_key",
    "sign_record",
    "station_key",
    "trust_key_file",
    "trusted_keys",
    "verify_record",
]

KEY_DIR_ENV = "THERMOCAL_KEY_DIR"
PRIVATE_NAME = "station_ed25519.pem"
PUBLIC_NAME = "station_ed25519.pub"
TRUSTED_DIR = "trusted"
RETIRED_DIR = "retired"
ALG = "ed25519"


def key_dir() -> Path:
    """The key folder: ``$THERMOCAL_KEY_DIR``, else ``$XDG_CONFIG_HOME/thermocal/keys``, else
    ``~/.config/thermocal/keys``."""
    env = os.environ.get(KEY_DIR_ENV)
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "thermocal" / "keys"


def _folder(folder: str | os.PathLike | None) -> Path:
    return Path(folder) if folder is not None else key_dir()


def _raw_public(pub: Ed25519PublicKey) -> bytes:
    return pub.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def key_id_of(raw_public: bytes) -> str:
    """A public key's short name: the first 16 hex digits of the sha256 of its 32 raw bytes."""
    return hashlib.sha256(raw_public).hexdigest()[:16]


# ---------------------------------------------------------------------------------------------------------------
# the key folder's permissions


def _refuse(path: Path, what: str, fix: str) -> RegistryError:
    return RegistryError(
        f"{what}: anyone who can change it can make this station trust forged records; {fix}", path=str(path)
    )


def check_key_folder(folder: str | os.PathLike | None = None) -> None:
    """RegistryError (one line, with the command that fixes it) when the key folder, its ``trusted/`` folder or a
    file in it can be written by another user, is owned by another user, or the private key can be read by
    others. A folder that does not exist yet passes (it is created private)."""
    d = _folder(folder)
    for path in (d, d / TRUSTED_DIR, d / RETIRED_DIR):
        _own_mode(path, "folder")
    files = [d / PRIVATE_NAME, d / PUBLIC_NAME]
    with contextlib.suppress(OSError):
        files += sorted((d / TRUSTED_DIR).glob("*.pub"))
    for f in files:
        mode = _own_mode(f, "file")
        if mode is not None and f.name == PRIVATE_NAME and mode & 0o077:
            raise RegistryError(
                f"this station's private key is readable by others (mode {mode:04o}): anyone who reads it can sign "
                f"as this station; run chmod 600 '{f}' (and rotate the key if others may have read it: "
                "'thermocal key rotate')",
                path=str(f),
            )


def _own_mode(path: Path, kind: str) -> int | None:
    """The permission bits of the key ``kind`` (``folder`` or ``file``) at ``path``, None if it does not exist;
    RegistryError when it cannot be read, a folder is not a directory, or it is owned by another user or writable
    by others."""
    try:
        st = path.stat()
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as exc:
        raise RegistryError(f"cannot read the key {kind} ({exc.strerror})", path=str(path)) from None
    if kind == "folder" and not stat.S_ISDIR(st.st_mode):
        raise RegistryError("the key folder is not a directory", path=str(path))
    mode = stat.S_IMODE(st.st_mode)
    uid = os.geteuid() if hasattr(os, "geteuid") else None
    if uid is not None and st.st_uid != uid:
        fix = "use a folder of your own" if kind == "folder" else "use a key of your own"
        raise _refuse(path, f"the key {kind} is owned by user id {st.st_uid}, not by you", fix)
    if mode & 0o022:
        chmod = "700" if kind == "folder" else "600"
        raise _refuse(path, f"the key {kind} is writable by others (mode {mode:04o})", f"run chmod {chmod} '{path}'")
    return mode


# ---------------------------------------------------------------------------------------------------------------
# this station's key


@dataclass(frozen=True)
class StationKey:
    """This station's signing key and where it is kept."""

    private: Ed25519PrivateKey
    path: Path

    @property
    def public_hex(self) -> str:
        return _raw_public(self.private.public_key()).hex()

    @property
    def key_id(self) -> str:
        return key_id_of(_raw_public(self.private.public_key()))


def station_key(folder: str | os.PathLike | None = None, *, create: bool = True) -> StationKey:
    """This station's signing key (from :func:`key_dir` unless ``folder`` is given). On first use (no private and
    no public key in the folder) it is created when ``create``, with a one-line message on stderr saying where;
    a private key that is missing while its public key is there is never replaced: RegistryError saying how to
    restore it or rotate. Loaded once per process and folder. RegistryError if it cannot be read or created, or the
    folder is open to others (:func:`check_key_folder`)."""
    d = _folder(folder)
    check_key_folder(d)
    path = d / PRIVATE_NAME
    if not path.exists():
        _missing_key(d, create)
    return _load_key(str(path))


def _missing_key(d: Path, create: bool) -> None:
    """The private key is not there: create it on first use, else say why not and what to do."""
    path, pub = d / PRIVATE_NAME, d / PUBLIC_NAME
    if pub.exists():
        known = _public_file_id(pub)
        raise RegistryError(
            f"this station's signing key is missing, but its public key {pub.name}{known} is still there: it was "
            f"deleted or moved, and is not replaced silently; restore it from a backup, or make a new one with "
            f"'thermocal key rotate' (what the old key signed stays trusted)",
            path=str(path),
        )
    if not create:
        raise RegistryError(
            f"this station has no signing key yet; 'thermocal key create' makes one (or set {KEY_DIR_ENV} to the "
            "folder that holds it)",
            path=str(path),
        )
    _create_key(d, path)


def _public_file_id(pub: Path) -> str:
    try:
        return f" (key id {key_id_of(_raw_public(_load_public(pub)))})"
    except RegistryError:
        return ""


@functools.lru_cache(maxsize=8)
def _load_key(path_text: str) -> StationKey:
    path = Path(path_text)
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except OSError as exc:
        raise RegistryError(
            f"cannot read this station's signing key ({exc.strerror}); set {KEY_DIR_ENV} to a folder of your own",
            path=str(path),
        ) from None
    except (ValueError, TypeError) as exc:
        raise RegistryError(
            f"this station's signing key is not a valid PEM private key ({exc})", path=str(path)
        ) from None
    if not isinstance(key, Ed25519PrivateKey):
        raise RegistryError("this station's signing key is not an Ed25519 key", path=str(path))
    return StationKey(key, path)


def _write_private(d: Path, path: Path, key: Ed25519PrivateKey) -> bool:
    """Write ``key`` to ``path`` atomically (temp file, then a hard link that fails if the name exists); False
    when another process was first."""
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    tmp = d / f".tmp-{os.getpid()}-{secrets.token_hex(4)}.pem"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, pem)
            os.fsync(fd)
        finally:
            os.close(fd)
        try:
            os.link(tmp, path)
        except FileExistsError:
            return False
        return True
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def _write_public(path: Path, raw: bytes) -> None:
    tmp = path.with_name(f".tmp-{os.getpid()}-{secrets.token_hex(4)}.pub")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            os.write(fd, (raw.hex() + "\n").encode("ascii"))
        finally:
            os.close(fd)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def _create_key(d: Path, path: Path, announce: bool = True) -> StationKey:
    key = Ed25519PrivateKey.generate()
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        check_key_folder(d)
        if not _write_private(d, path, key):
            return _load_key(str(path))  # another process created it first: use that one
        raw = _raw_public(key.public_key())
        _write_public(d / PUBLIC_NAME, raw)
    except OSError as exc:
        raise RegistryError(
            f"cannot create this station's signing key ({exc.strerror}); set {KEY_DIR_ENV} to a "
            "writable folder outside the registry",
            path=str(path),
        ) from None
    _load_key.cache_clear()
    if announce:
        print(
            f"thermocal: created this station's signing key {path} (key id {key_id_of(raw)}); it signs every record "
            f"this station writes into a registry: keep it private. Other stations accept them once "
            f"{d / PUBLIC_NAME} is copied into their {TRUSTED_DIR}/ key folder.",
            file=sys.stderr,
        )
    return _load_key(str(path))


def create_key(folder: str | os.PathLike | None = None) -> StationKey:
    """``thermocal key create``: make this station's key; RegistryError when it has one (or had one: its public key
    is there), which is never replaced but by :func:`rotate_key`."""
    d = _folder(folder)
    check_key_folder(d)
    if (d / PRIVATE_NAME).exists():
        key = _load_key(str(d / PRIVATE_NAME))
        raise RegistryError(
            f"this station already has a signing key (key id {key.key_id}); 'thermocal key rotate' replaces it",
            path=str(d / PRIVATE_NAME),
        )
    if (d / PUBLIC_NAME).exists():
        _missing_key(d, create=False)
    return _create_key(d, d / PRIVATE_NAME, announce=False)


@dataclass(frozen=True)
class Rotation:
    """What :func:`rotate_key` did: the new key, the old key's id (None: there was none), where the old private key
    went (None: it was missing) and where its public key is now trusted (None: distrusted)."""

    key: StationKey
    old_key_id: str | None
    retired: Path | None
    old_trusted: Path | None


def rotate_key(folder: str | os.PathLike | None = None, *, distrust_old: bool = False) -> Rotation:
    """``thermocal key rotate``: a new key for this station. The old private key (if still there) moves to
    ``retired/`` (never used to sign again); its public key goes into ``trusted/`` so that what it signed still
    verifies, unless ``distrust_old`` (a key that may have leaked: what it signed is then named by verify)."""
    d = _folder(folder)
    check_key_folder(d)
    priv, pub = d / PRIVATE_NAME, d / PUBLIC_NAME
    old_raw: bytes | None = None
    retired = trusted = None
    try:
        if priv.exists():
            old_raw = _raw_public(_load_key(str(priv)).private.public_key())
        elif pub.exists():
            old_raw = _raw_public(_load_public(pub))
        old_id = key_id_of(old_raw) if old_raw is not None else None
        if old_raw is not None and not distrust_old:
            (d / TRUSTED_DIR).mkdir(mode=0o700, exist_ok=True)
            trusted = d / TRUSTED_DIR / f"station-{old_id}.pub"
            _write_public(trusted, old_raw)
        if priv.exists():
            (d / RETIRED_DIR).mkdir(mode=0o700, exist_ok=True)
            retired = d / RETIRED_DIR / f"station-{old_id}.pem"
            os.replace(priv, retired)
        pub.unlink(missing_ok=True)
    except OSError as exc:
        raise RegistryError(f"cannot rotate the key ({exc.strerror})", path=str(exc.filename or d)) from None
    _load_key.cache_clear()
    return Rotation(_create_key(d, priv, announce=False), old_id, retired, trusted)


def trust_key_file(path: str | os.PathLike, folder: str | os.PathLike | None = None) -> tuple[str, Path, bool]:
    """``thermocal key trust FILE``: copy another station's public key (64 hex digits or PEM) into ``trusted/``;
    (its key id, where it was put, False when it was already trusted). RegistryError when the file is not a
    public key."""
    d = _folder(folder)
    check_key_folder(d)
    raw = _raw_public(_load_public(Path(path)))
    key_id = key_id_of(raw)
    target = d / TRUSTED_DIR / f"station-{key_id}.pub"
    trust = trusted_keys(d)
    if key_id in trust.keys:
        return key_id, (trust.files or {}).get(key_id, target), False
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        (d / TRUSTED_DIR).mkdir(mode=0o700, exist_ok=True)
        _write_public(target, raw)
    except OSError as exc:
        raise RegistryError(f"cannot add the trusted key ({exc.strerror})", path=str(target)) from None
    return key_id, target, True


# ---------------------------------------------------------------------------------------------------------------
# trusted keys (reading and verifying never need the private key)


@dataclass(frozen=True)
class TrustStore:
    """Public keys whose signatures are accepted, by key id; ``folder`` is where they were read from; ``own_id``
    this station's own key id (None: it has no key yet); ``files`` where each key was read from."""

    keys: dict[str, Ed25519PublicKey]
    folder: Path
    own_id: str | None = None
    files: dict[str, Path] | None = None


def trusted_keys(folder: str | os.PathLike | None = None) -> TrustStore:
    """This station's own public key (from its private key, else its public key file; none when it has no key: no
    key is created here) and every ``trusted/*.pub``. A trusted-key file that cannot be read as a public key, or a
    key folder open to others, is a RegistryError naming it."""
    d = _folder(folder)
    check_key_folder(d)
    keys: dict[str, Ed25519PublicKey] = {}
    files: dict[str, Path] = {}
    own_id = None
    own: Ed25519PublicKey | None = None
    if (d / PRIVATE_NAME).exists():
        own, files_own = _load_key(str(d / PRIVATE_NAME)).private.public_key(), d / PRIVATE_NAME
    elif (d / PUBLIC_NAME).exists():
        own, files_own = _load_public(d / PUBLIC_NAME), d / PUBLIC_NAME
    if own is not None:
        own_id = key_id_of(_raw_public(own))
        keys[own_id], files[own_id] = own, files_own
    tdir = d / TRUSTED_DIR
    if tdir.is_dir():
        for f in sorted(tdir.glob("*.pub")):
            pub = _load_public(f)
            kid = key_id_of(_raw_public(pub))
            keys.setdefault(kid, pub)
            files.setdefault(kid, f)
    return TrustStore(keys, d, own_id, files)


def _load_public(path: Path) -> Ed25519PublicKey:
    try:
        data = path.read_bytes()
        text = data.decode("ascii").strip()
        if len(text) == 64 and all(c in "0123456789abcdefABCDEF" for c in text):
            return Ed25519PublicKey.from_public_bytes(bytes.fromhex(text))
        key = serialization.load_pem_public_key(data)
    except (OSError, UnicodeDecodeError, ValueError, TypeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise RegistryError(f"not a public key (64 hex digits or PEM): {reason}", path=str(path)) from None
    if not isinstance(key, Ed25519PublicKey):
        raise RegistryError("not an Ed25519 public key", path=str(path))
    return key


@dataclass(frozen=True)
class KeyFolder:
    """``thermocal key show``: the folder, this station's key (id and public key, None: none yet; ``missing``:
    its private key is gone while its public key is there) and the trusted keys (id -> file)."""

    folder: Path
    key_id: str | None
    public_hex: str | None
    missing: bool
    trusted: dict[str, str]

    def as_dict(self) -> dict:
        return {
            "folder": str(self.folder),
            "key_id": self.key_id,
            "public_key": self.public_hex,
            "private_key_missing": self.missing,
            "trusted": self.trusted,
        }


def describe_keys(folder: str | os.PathLike | None = None) -> KeyFolder:
    """What the key folder holds (checked first: :func:`check_key_folder`)."""
    d = _folder(folder)
    trust = trusted_keys(d)
    own = trust.keys.get(trust.own_id) if trust.own_id else None
    missing = own is not None and not (d / PRIVATE_NAME).exists()
    others = {k: str(f) for k, f in (trust.files or {}).items() if k != trust.own_id}
    return KeyFolder(d, trust.own_id, _raw_public(own).hex() if own else None, missing, others)


# ---------------------------------------------------------------------------------------------------------------
# records


def sign_record(record: dict, key: StationKey | None = None) -> dict:
    """A copy of ``record`` (a JSON object) with ``content_sha256`` and ``signature`` set by this station's key.
    The record must be JSON-able (canonical_json's rules: no NaN, ...)."""
    key = key or station_key()
    body = {k: v for k, v in record.items() if k not in ("content_sha256", "signature")}
    signed = signed_body(body)  # what the signature signs and content_sha256 hashes: encoded once
    value = key.private.sign(signed)
    return {
        **body,
        "content_sha256": sha256_bytes(signed),
        "signature": {
            "alg": ALG,
            "key_id": key.key_id,
            "public_key": key.public_hex,
            "value": base64.b64encode(value).decode("ascii"),
        },
    }


@dataclass(frozen=True)
class SignatureCheck:
    """Outcome of :func:`verify_record`: ``ok`` when a trusted key signed exactly this content. ``problem`` says
    what is wrong otherwise (one phrase); ``key_id`` names the signing key when the record names one; ``own`` is
    True when that key is this station's."""

    ok: bool
    problem: str | None = None
    key_id: str | None = None
    own: bool = False


def verify_record(record: dict, trust: TrustStore | None = None, body: bytes | None = None) -> SignatureCheck:
    """Check a record's signature against the trusted keys (:func:`trusted_keys` unless given). ``body``: the
    record's :func:`signed_body` when the caller has it already (:func:`pipeline.passport.canonical.read_sealed`)."""
    trust = trust or trusted_keys()
    sig = record.get("signature")
    if sig is None:
        return SignatureCheck(False, "not signed (no signature)")
    try:
        if sig.get("alg") != ALG:
            return SignatureCheck(False, f"signature algorithm {sig.get('alg')!r} is not {ALG}")
        key_id = str(sig["key_id"])
        raw = bytes.fromhex(str(sig["public_key"]))
        value = base64.b64decode(str(sig["value"]), validate=True)
    except (AttributeError, KeyError, TypeError, ValueError):
        return SignatureCheck(False, "signature field is malformed")
    if key_id_of(raw) != key_id:
        return SignatureCheck(False, "signature names a key id that is not its public key's", key_id)
    pub = trust.keys.get(key_id)
    own = key_id == trust.own_id
    if pub is None:
        return SignatureCheck(
            False,
            f"signed by key {key_id}, which this station does not trust (not in {trust.folder / TRUSTED_DIR})",
            key_id,
        )
    try:
        pub.verify(value, body if body is not None else signed_body(record))
    except InvalidSignature:
        return SignatureCheck(
            False, f"signature by key {key_id} does not match the content (altered or forged)", key_id, own
        )
    return SignatureCheck(True, None, key_id, own)
