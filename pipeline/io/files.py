"""Only regular files are read: a FIFO, a device or a socket where a run or a passport is expected is named in one
line and never opened for reading (opening a FIFO blocks until someone writes to it; a device may never end).

:func:`special_kind` says what a path is when it is not a regular file or a directory (a stat, no open);
:func:`open_regular` opens without blocking and checks the opened file itself (no race between the check and the
open); :func:`read_regular_bytes` reads a small file whole, up to a limit.
"""

from __future__ import annotations

import fcntl
import os
import stat
from pathlib import Path
from typing import BinaryIO

from pipeline.errors import RunFormatError, ThermocalError

__all__ = ["NOT_REGULAR", "open_regular", "read_regular_bytes", "require_regular", "special_kind", "write_text_whole"]

_KINDS = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)
#: The phrase that ends the one line about such a path.
NOT_REGULAR = "not a regular file: not read"


def kind_of_mode(mode: int) -> str | None:
    """``a FIFO (named pipe)``, ``a character device``, ... for a special file's mode; None for a regular file or a
    directory."""
    return next((name for test, name in _KINDS if test(mode)), None)


def special_kind(path: str | os.PathLike) -> str | None:
    """What ``path`` is when it exists and is neither a regular file nor a directory (symlinks followed); else
    None."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    return kind_of_mode(mode)


def require_regular(path: str | os.PathLike, error: type[ThermocalError] = RunFormatError) -> None:
    """``error`` (one line naming the path and what it is) when ``path`` is a FIFO, device or socket."""
    kind = special_kind(path)
    if kind is not None:
        raise error(f"is {kind}, {NOT_REGULAR}", path=str(path))


def open_regular(path: str | os.PathLike, error: type[ThermocalError] = RunFormatError) -> BinaryIO:
    """``path`` opened for reading in binary mode, only if it is a regular file: opened without blocking (a FIFO
    would wait for a writer), then the open file checked. ``error`` (one line) for a special file or an OSError."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise error(f"cannot open the file ({exc.strerror})", path=str(path)) from None
    try:
        st = os.fstat(fd)
        kind = kind_of_mode(st.st_mode)
        if kind is not None or not stat.S_ISREG(st.st_mode):
            raise error(f"is {kind or 'a directory'}, {NOT_REGULAR}", path=str(path))
        if hasattr(os, "O_NONBLOCK"):
            fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular_bytes(
    path: str | os.PathLike, *, what: str = "file", limit: int = 1 << 30, error: type[ThermocalError] = ThermocalError
) -> bytes:
    """The bytes of a small regular file (a passport, a head statement, run metadata), at most ``limit`` bytes:
    ``error`` in one line for a special file, a missing one or one larger than the limit."""
    p = Path(path)
    if p.is_dir():
        raise error(f"is a directory, not a {what} file", path=str(p))
    with open_regular(p, error) as f:
        size = os.fstat(f.fileno()).st_size
        if size > limit:
            raise error(f"{size} bytes: larger than any {what} ({limit} bytes at most); not read", path=str(p))
        try:
            return f.read(limit + 1)[:limit]
        except OSError as exc:
            raise error(f"cannot read the {what} ({exc.strerror})", path=str(p)) from None


def write_text_whole(path: str | os.PathLike, text: str, what: str, *, make_folder: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``path`` whole or not at all: under a temporary name beside it, then renamed (its
    folder created unless ``make_folder`` is False); a file already there stays as it was when the writing fails.
    ThermocalError "cannot write the ``what`` (reason)" naming the file when it cannot be written."""
    out = Path(path)
    tmp = out.with_name(f".{out.name}.tmp")
    try:
        if make_folder:
            out.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, out)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise ThermocalError(f"cannot write the {what} ({e.strerror or e})", path=str(out)) from None
    return out
