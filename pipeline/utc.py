"""Times for people: ns since the Unix epoch (``t_ns``, the recordings' clock) as UTC text."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def _parts(t_ns: int) -> tuple[str, str]:
    t = _EPOCH + timedelta(microseconds=int(t_ns) // 1000)
    return t.strftime("%Y-%m-%d"), t.strftime("%H:%M:%S.") + f"{t.microsecond // 1000:03d}"


def utc_text(t_ns: int) -> str:
    """``t_ns`` (ns since the Unix epoch) as a UTC time to the millisecond: ``2026-11-01 00:00:00.000 UTC``."""
    day, clock = _parts(t_ns)
    return f"{day} {clock} UTC"


def utc_span(t0_ns: int, t1_ns: int) -> str:
    """The span ``t0_ns`` .. ``t1_ns`` (ns since the Unix epoch) in UTC, the date said once when both ends share
    it: ``2026-11-01 03:00:00.000 .. 04:30:00.000 UTC``."""
    (d0, c0), (d1, c1) = _parts(t0_ns), _parts(t1_ns)
    return f"{d0} {c0} .. {c1} UTC" if d0 == d1 else f"{d0} {c0} .. {d1} {c1} UTC"
