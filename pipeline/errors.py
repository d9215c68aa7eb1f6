"""The project's own error type: one line naming the file, the stream and the time or row."""

from __future__ import annotations


class ThermocalError(Exception):
    """A problem with an input or a request, reported to the user in one line.

    ``path`` is the file, ``stream`` the log stream (``voltmeter``, ``au_temperature``, ...), ``where`` the time
    (``t_ns=...``) or row (``row 12``) or byte offset where it was found. Any of them may be empty.
    """

    def __init__(self, message: str, *, path: str | None = None, stream: str | None = None, where: str | None = None):
        self.message = message
        self.path = path
        self.stream = stream
        self.where = where
        super().__init__(self.one_line())

    def one_line(self) -> str:
        parts = [p for p in (self.path, self.stream, self.where) if p]
        head = ": ".join(parts)
        text = f"{head}: {self.message}" if head else self.message
        return " ".join(text.split())


class RunFormatError(ThermocalError):
    """A run file that cannot be read as a chamber run (truncated, corrupt, wrong schema, missing stream...)."""


class CalibrationError(ThermocalError):
    """A run that was read but cannot be calibrated (no plateau, too few positions...)."""


class RegistryError(ThermocalError):
    """A registry that cannot be written or fails its integrity check."""
