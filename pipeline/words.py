"""Words for the text people read (no dependencies: the passport texts, inspect and the command line share it):
counts (:func:`count_words`) and text made safe to print (:func:`printable`)."""

from __future__ import annotations


def count_words(n: int, noun: str) -> str:
    """``1 plateau``, ``7 plateaus``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _escape_table(keep: str) -> dict[int, str]:
    codes = [*range(0x00, 0x20), 0x7F, *range(0x80, 0xA0), *range(0x202A, 0x202F), *range(0x2066, 0x206A)]
    return {c: (f"\\x{c:02x}" if c < 0x100 else f"\\u{c:04x}") for c in codes if chr(c) not in keep}


_LINES = _escape_table("\n\t")
_ONE_LINE = _escape_table("")


def printable(text: str, *, lines: bool = True) -> str:
    """``text`` with every control character written as an escape (ESC -> ``\\x1b``): C0 and C1 controls, DEL, and
    the bidirectional overrides that reorder what a terminal shows. ``lines``: newlines and tabs are kept (a
    command's text output); otherwise they are escaped too (a field inside one line). Whatever a registry, a run or
    a file name holds (an approver's name with ANSI escapes, a serial with a carriage return) is shown, never
    obeyed by the terminal."""
    return text.translate(_LINES if lines else _ONE_LINE)
