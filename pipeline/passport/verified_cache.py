"""Which passport files this user has already verified in full (``thermocal trends``: a large registry read again).

An entry says: the file whose exact bytes have this sha256 is canonical, its stored ``content_sha256`` is its
content's, a key of this trusted key set signed it, and its content passed :func:`check_content`, all by this
version of the checks. Each is a property of the bytes, the key set and the checker alone, so a file whose bytes
hash to an entry may skip those checks; everything that depends on where the file lies (its unit and version
number, the log's sha256, the parent link to the version before, the chain order) is still checked every time.

An entry is ``HMAC-SHA256(secret, checks' fingerprint | key-set fingerprint | file sha256)`` in hex, one a line,
in ``verified`` under :func:`cache_dir`; the secret (32 random bytes, created 0600 by its owner beside the cache)
makes an entry impossible to plant without it. Different bytes, another key set or other checks never meet an
entry: the checks' fingerprint (:func:`checks_fingerprint`) hashes the source of every module that decides what
passes, so any edit of the checks invalidates every entry, with nothing to remember. A missing, unreadable, corrupt
or unwritable cache means: verify in full (never an error). The registry folder is never written.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import os
import secrets
import stat
import sys
from pathlib import Path
from types import ModuleType

from pipeline import __version__
from pipeline.passport import verification
from pipeline.passport.signing import TrustStore, _raw_public

#: Override of the cache folder (an empty value: no cache, every file verified in full).
CACHE_ENV = "THERMOCAL_CACHE_DIR"
_ENTRIES_NAME = "verified"
_SECRET_NAME = "secret"
#: A cache file larger than this is dropped and started again (about 120,000 entries).
MAX_CACHE_BYTES = 8 << 20


def cache_dir() -> Path | None:
    """``$THERMOCAL_CACHE_DIR``, else ``$XDG_CACHE_HOME/thermocal``, else ``~/.cache/thermocal``; None when
    ``THERMOCAL_CACHE_DIR`` is set empty (no cache)."""
    if CACHE_ENV in os.environ:
        return Path(os.environ[CACHE_ENV]) if os.environ[CACHE_ENV] else None
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "thermocal"


#: The module that uses the cache: what a hit skips is decided there (Registry._check_unit, verified_history). Its
#: own source counts, not the modules it imports (the whole calibration pipeline: any edit there would empty every
#: cache).
_USER = "registry.py"


def acceptance_files() -> list[Path]:
    """The source files of :mod:`pipeline.passport.verification` (check_sealed, check_content), this module and every
    ``pipeline`` module they use at module level, transitively (canonical form, hashing, signatures, JSON
    conversion, ...), and of the registry module that skips checks on a hit (:data:`_USER`), sorted: what decides
    whether a file's bytes pass."""
    seen: dict[str, ModuleType] = {}
    todo: list[ModuleType] = [verification, sys.modules[__name__]]
    while todo:
        mod = todo.pop()
        if mod.__name__ in seen:
            continue
        seen[mod.__name__] = mod
        for value in vars(mod).values():
            name = value.__name__ if isinstance(value, ModuleType) else getattr(value, "__module__", None)
            if isinstance(name, str) and name.split(".")[0] == "pipeline" and name in sys.modules:
                todo.append(sys.modules[name])
    return sorted({Path(f) for m in seen.values() if (f := m.__file__)} | {Path(__file__).with_name(_USER)})


def fingerprint_of(files: list[Path]) -> str:
    """sha256 over the files' bytes (each with its length: no two sets of contents give one stream), the Python,
    cryptography, numpy and orjson versions (parsing, float text, signatures, K's condition number) and the
    project's."""
    import cryptography
    import numpy
    import orjson

    versions = f"{sys.version}|{cryptography.__version__}|{numpy.__version__}|{orjson.__version__}|{__version__}|"
    h = hashlib.sha256(versions.encode())
    for f in files:
        data = f.read_bytes()
        h.update(b"%d|" % len(data) + data)
    return h.hexdigest()


@functools.cache
def checks_fingerprint() -> str:
    """:func:`fingerprint_of` the :func:`acceptance_files`, computed once per process (about 1 ms); "" when a file
    cannot be read (then no cache: :meth:`VerifiedCache.open`)."""
    try:
        return fingerprint_of(acceptance_files())
    except OSError:
        return ""


def key_set_fingerprint(trust: TrustStore) -> str:
    """sha256 of the trusted public keys' raw bytes, sorted: the same for the same key set, whatever the files."""
    return hashlib.sha256(b"".join(sorted(_raw_public(k) for k in trust.keys.values()))).hexdigest()


def _secret(folder: Path) -> bytes | None:
    """The folder's secret, created (0600, 32 random bytes) when missing; None when it cannot be had or is not this
    user's alone."""
    path = folder / _SECRET_NAME
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            pass
        else:
            try:
                os.write(fd, secrets.token_bytes(32))
            finally:
                os.close(fd)
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
                return None
            value = os.read(fd, 64)
        finally:
            os.close(fd)
    except OSError:
        return None
    return value if len(value) == 32 else None


class VerifiedCache:
    """The entries of :func:`cache_dir` for one trusted key set (:meth:`open`); ``hits``: the sha256s found."""

    def __init__(self, folder: Path | None, secret: bytes | None, trust: TrustStore, entries: set[str]):
        self.folder, self._secret, self._entries = folder, secret, entries
        self._prefix = f"{checks_fingerprint()}|{key_set_fingerprint(trust)}|".encode("ascii")

    @classmethod
    def open(cls, trust: TrustStore, read_entries: bool = True) -> VerifiedCache:
        """The cache for ``trust`` (an empty one that keeps nothing when there is no usable cache). ``read_entries``
        False: only to :meth:`add` (a publish: its new file is in no entry yet; the entries file is not read)."""
        folder = cache_dir() if checks_fingerprint() else None
        secret = _secret(folder) if folder is not None else None
        entries: set[str] = set()
        if folder is not None and secret is not None and read_entries:
            path = folder / _ENTRIES_NAME
            try:
                if path.stat().st_size > MAX_CACHE_BYTES:
                    path.unlink()
                else:
                    entries = set(path.read_bytes().decode("ascii", "replace").split())
            except OSError:
                pass
        return cls(folder, secret, trust, entries)

    def _tag(self, file_sha256: str) -> str:
        assert self._secret is not None
        return hmac.new(self._secret, self._prefix + file_sha256.encode("ascii"), hashlib.sha256).hexdigest()

    def known(self, file_sha256: str) -> bool:
        """True when the file with these bytes was verified in full under this key set and checker."""
        return self._secret is not None and bool(self._entries) and self._tag(file_sha256) in self._entries

    def add(self, file_sha256s: list[str]) -> None:
        """Record files verified in full (appended in one write; nothing when the cache cannot be written)."""
        if self._secret is None or self.folder is None:
            return
        tags = [t for t in (self._tag(s) for s in file_sha256s) if t not in self._entries]
        if not tags:
            return
        try:
            fd = os.open(self.folder / _ENTRIES_NAME, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o600)
            try:
                os.write(fd, "".join(t + "\n" for t in tags).encode("ascii"))
            finally:
                os.close(fd)
        except OSError:
            return
        self._entries.update(tags)
