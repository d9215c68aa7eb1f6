"""Counts in words for the text people read (no dependencies: the passport texts and inspect share it)."""

from __future__ import annotations


def count_words(n: int, noun: str) -> str:
    """``1 plateau``, ``7 plateaus``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"
