"""Signatures of registry records (passport versions, approvals, head statements): Ed25519 via ``cryptography``.

Every record a station writes into a registry is signed with that station's private key; ``passport verify`` checks
each signature against the public keys this station trusts. Both live OUTSIDE the registry, in the key folder:

    $THERMOCAL_KEY_DIR            (if set; tests and CI point it at a temporary folder)
    else $XDG_CONFIG_HOME/thermocal/keys, else ~/.config/thermocal/keys
      station_ed25519.pem         this station's private key (PKCS#8 PEM, mode 0600), created on first use
      station_ed25519.pub         its public key (64 hex digits): copy it into other stations' trusted/ folder
      trusted/*.pub               public keys of other stations whose records this station accepts (64 hex
                                  digits, or a PEM public key); this station's own key is always trusted

So someone with write access to the registry folder alone can neither sign a forged version nor add a key that
verify would accept. What is signed: the same bytes as ``content_sha256`` hashes (:func:`pipeline.passport.canonical.
signed_body`, the canonical JSON without ``content_sha256`` and ``signature``). A signed record carries::

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
import sys
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from pipeline.errors import RegistryError
from pipeline.passport.canonical import content_sha256, signed_body

__all__ = [
    "KEY_DIR_ENV",
    "SignatureCheck",
    "StationKey",
    "TrustStore",
    "key_dir",
    "sign_record",
    "station_key",
    "trusted_keys",
    "verify_record",
]

KEY_DIR_ENV = "THERMOCAL_KEY_DIR"
PRIVATE_NAME = "station_ed25519.pem"
PUBLIC_NAME = "station_ed25519.pub"
TRUSTED_DIR = "trusted"
ALG = "ed25519"


def key_dir() -> Path:
    """The key folder: ``$THERMOCAL_KEY_DIR``, else ``$XDG_CONFIG_HOME/thermocal/keys``, else
    ``~/.config/thermocal/keys``."""
    env = os.environ.get(KEY_DIR_ENV)
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "thermocal" / "keys"


def _raw_public(pub: Ed25519PublicKey) -> bytes:
    return pub.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def key_id_of(raw_public: bytes) -> str:
    """A public key's short name: the first 16 hex digits of the sha256 of its 32 raw bytes."""
    return hashlib.sha256(raw_public).hexdigest()[:16]


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


def station_key(folder: str | os.PathLike | None = None) -> StationKey:
    """This station's signing key (from :func:`key_dir` unless ``folder`` is given), created on first use with a
    one-line message on stderr saying where. Loaded once per process and folder. RegistryError if it cannot be
    read or created."""
    return _station_key(str(Path(folder) if folder is not None else key_dir()))


@functools.lru_cache(maxsize=8)
def _station_key(folder: str) -> StationKey:
    d = Path(folder)
    path = d / PRIVATE_NAME
    if not path.exists():
        _create_key(d, path)
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


def _create_key(d: Path, path: Path) -> None:
    """Create the key atomically (temp file, then a hard link that fails if another process was first)."""
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    tmp = d / f".tmp-{os.getpid()}-{secrets.token_hex(4)}.pem"
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, pem)
            os.fsync(fd)
        finally:
            os.close(fd)
        try:
            os.link(tmp, path)
        except FileExistsError:
            return  # another process created it first: use that one
        raw = _raw_public(key.public_key())
        (d / PUBLIC_NAME).write_text(raw.hex() + "\n")
    except OSError as exc:
        raise RegistryError(
            f"cannot create this station's signing key ({exc.strerror}); set {KEY_DIR_ENV} to a "
            "writable folder outside the registry",
            path=str(path),
        ) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
    print(
        f"thermocal: created this station's signing key {path} (key id {key_id_of(raw)}); it signs every record "
        f"this station writes into a registry: keep it private. Other stations accept them once "
        f"{d / PUBLIC_NAME} is copied into their {TRUSTED_DIR}/ key folder.",
        file=sys.stderr,
    )


@dataclass(frozen=True)
class TrustStore:
    """Public keys whose signatures are accepted, by key id; ``folder`` is where they were read from."""

    keys: dict[str, Ed25519PublicKey]
    folder: Path


def trusted_keys(folder: str | os.PathLike | None = None) -> TrustStore:
    """This station's own public key (the key is created if there is none yet) and every ``trusted/*.pub``.
    A trusted-key file that cannot be read as a public key is a RegistryError naming it."""
    d = Path(folder) if folder is not None else key_dir()
    own = station_key(d)
    keys: dict[str, Ed25519PublicKey] = {own.key_id: own.private.public_key()}
    tdir = d / TRUSTED_DIR
    if tdir.is_dir():
        for f in sorted(tdir.glob("*.pub")):
            pub = _load_public(f)
            keys[key_id_of(_raw_public(pub))] = pub
    return TrustStore(keys, d)


def _load_public(path: Path) -> Ed25519PublicKey:
    try:
        data = path.read_bytes()
        text = data.decode("ascii").strip()
        if len(text) == 64 and all(c in "0123456789abcdefABCDEF" for c in text):
            return Ed25519PublicKey.from_public_bytes(bytes.fromhex(text))
        key = serialization.load_pem_public_key(data)
    except (OSError, UnicodeDecodeError, ValueError, TypeError) as exc:
        raise RegistryError(f"not a public key (64 hex digits or PEM): {exc}", path=str(path)) from None
    if not isinstance(key, Ed25519PublicKey):
        raise RegistryError("not an Ed25519 public key", path=str(path))
    return key


# ---------------------------------------------------------------------------------------------------------------
# records


def sign_record(record: dict, key: StationKey | None = None) -> dict:
    """A copy of ``record`` (a JSON object) with ``content_sha256`` and ``signature`` set by this station's key.
    The record must be JSON-able (canonical_json's rules: no NaN, ...)."""
    key = key or station_key()
    body = {k: v for k, v in record.items() if k not in ("content_sha256", "signature")}
    value = key.private.sign(signed_body(body))
    return {
        **body,
        "content_sha256": content_sha256(body),
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


def verify_record(record: dict, trust: TrustStore | None = None) -> SignatureCheck:
    """Check a record's signature against the trusted keys (:func:`trusted_keys` unless given)."""
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
    own = key_id == station_key(trust.folder).key_id
    if pub is None:
        return SignatureCheck(
            False,
            f"signed by key {key_id}, which this station does not trust (not in {trust.folder / TRUSTED_DIR})",
            key_id,
        )
    try:
        pub.verify(value, signed_body(record))
    except InvalidSignature:
        return SignatureCheck(
            False, f"signature by key {key_id} does not match the content (altered or forged)", key_id, own
        )
    return SignatureCheck(True, None, key_id, own)
