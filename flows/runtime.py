"""Embedded Prefect defaults: local ephemeral mode with no server to set up, no telemetry, no heartbeat thread.

Call :func:`prefect_defaults` before importing prefect. When ``PREFECT_API_URL`` is set (a running server), it is
used as is.
"""

from __future__ import annotations

import contextlib
import os

_DEFAULTS = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    # the ephemeral server starts in ~8-13 s here; give slow machines room
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120",
    "PREFECT_LOGGING_LEVEL": "WARNING",
}


def prefect_defaults() -> None:
    for k, v in _DEFAULTS.items():
        os.environ.setdefault(k, v)


@contextlib.contextmanager
def flow_settings():
    """Settings in force while a flow runs: no heartbeat thread (it costs ~1 s per flow run)."""
    prefect_defaults()
    from prefect.settings import PREFECT_FLOWS_HEARTBEAT_FREQUENCY, temporary_settings

    with temporary_settings({PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
        yield
