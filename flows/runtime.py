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
    import logging

    for k, v in _DEFAULTS.items():
        os.environ.setdefault(k, v)
    # "EventsWorker - Still processing items" at exit is Prefect draining its event queue, not a problem of ours
    logging.getLogger("EventsWorker").setLevel(logging.ERROR)


@contextlib.contextmanager
def flow_settings():
    """Settings in force while a flow runs: no heartbeat thread (it costs ~1 s per flow run)."""
    prefect_defaults()
    from prefect.settings import PREFECT_FLOWS_HEARTBEAT_FREQUENCY, temporary_settings

    with temporary_settings({PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
        yield


@contextlib.contextmanager
def quiet_task_failures():
    """A failed task or flow run makes Prefect log the exception with its traceback; the command line reports a
    ThermocalError in one line itself, so Prefect's run loggers are held at CRITICAL meanwhile (the flow's
    warnings are part of the command's own output)."""
    import logging

    loggers = [logging.getLogger(n) for n in ("prefect.task_runs", "prefect.flow_runs")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, lvl in zip(loggers, levels):
            lg.setLevel(lvl)
