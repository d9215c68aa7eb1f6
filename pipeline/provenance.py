"""Content hashes of input runs and the code version, for passports' provenance."""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

from . import __version__

_BUF = 1 << 20


def sha256_of_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_BUF):
            h.update(chunk)
    return h.hexdigest()


def input_digest(path: str | Path) -> str:
    """sha256 of a run: of the file for MCAP; for a Parquet run directory, of the sorted list of
    ``name sha256`` lines of its files (so the digest does not depend on the directory's location)."""
    p = Path(path)
    if p.is_dir():
        lines = [f"{f.relative_to(p).as_posix()} {sha256_of_file(f)}\n"
                 for f in sorted(p.rglob("*")) if f.is_file()]
        return hashlib.sha256("".join(lines).encode()).hexdigest()
    return sha256_of_file(p)


def code_version() -> str:
    """``thermocal <version>`` plus the git commit of the source tree when it is a checkout."""
    here = Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(["git", "-C", str(here), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                             text=True, timeout=5)
        if rev.returncode == 0 and rev.stdout.strip():
            dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                                   capture_output=True, text=True, timeout=5).stdout.strip()
            return f"thermocal {__version__} ({rev.stdout.strip()}{'-dirty' if dirty else ''})"
    except (OSError, subprocess.SubprocessError):
        pass
    return f"thermocal {__version__}"
