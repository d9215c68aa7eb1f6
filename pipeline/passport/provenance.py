"""Content hashes of input runs and the code version, for passports' provenance."""

from __future__ import annotations

import functools
import hashlib
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

from pipeline import __version__
from pipeline.passport.canonical import sha256_file


@dataclass(frozen=True)
class RunDigest:
    """A run's content hash (:func:`input_digest`) and its :func:`file_signature` taken just before hashing."""

    sha256: str
    signature: tuple


def file_signature(path: str | Path) -> tuple:
    """What changes when a run is rewritten or replaced: (device, inode, size, mtime ns) of the file, or of each
    file of a Parquet run directory (with its name). A stat per file, no reading."""
    p = Path(path)
    if p.is_dir():
        return tuple((f.relative_to(p).as_posix(), *_stat_key(f)) for f in sorted(p.rglob("*")) if f.is_file())
    return _stat_key(p)


def _stat_key(path: Path) -> tuple[int, int, int, int]:
    st = os.stat(path)
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def hash_run(path: str | Path) -> RunDigest:
    """The run's :func:`input_digest` with its signature, for reuse by a later ``input_digest(path, known=...)``.
    A file changed while it was hashed has a later signature than the one recorded, so it is hashed again then."""
    signature = file_signature(path)
    return RunDigest(input_digest(path), signature)


def input_digest(path: str | Path, known: RunDigest | None = None) -> str:
    """sha256 of a run: of the file for MCAP; for a Parquet run directory, of the sorted list of
    ``name sha256`` lines of its files (so the digest does not depend on the directory's location).

    ``known``: the :func:`hash_run` of this path made earlier (the fleet's planning): its hash is returned without
    reading the run again while the run's :func:`file_signature` is unchanged (neither rewritten nor replaced).
    """
    p = Path(path)
    if known is not None and file_signature(p) == known.signature:
        return known.sha256
    if p.is_dir():
        lines = [f"{f.relative_to(p).as_posix()} {sha256_file(f)}\n" for f in sorted(p.rglob("*")) if f.is_file()]
        return hashlib.sha256("".join(lines).encode()).hexdigest()
    return sha256_file(p)


@functools.cache
def code_version() -> str:
    """``thermocal <version>`` plus the git commit of the source tree when it is a checkout. Asked of git once per
    process (two ``git`` runs, ~10 ms): the code a process runs is what it imported, whatever the checkout does
    later."""
    here = Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True, timeout=5
        )
        if rev.returncode == 0 and rev.stdout.strip():
            dirty = subprocess.run(
                ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                capture_output=True,
                text=True,
                timeout=5,
            ).stdout.strip()
            return f"thermocal {__version__} ({rev.stdout.strip()}{'-dirty' if dirty else ''})"
    except (OSError, subprocess.SubprocessError):
        pass
    return f"thermocal {__version__}"
