"""Nightly processing: the fleet flow as a Prefect deployment on a cron schedule over an inbox folder.

``thermocal serve --inbox DIR --registry R --cron "0 2 * * *"`` registers the deployment ``thermocal-fleet/<name>``
with a running Prefect server and stays in the foreground executing its runs (``prefect.serve``: no work pool or
worker to set up). Each run is ``fleet_flow(root=DIR, registry=R, trends=True, ...)``: new runs in the inbox are
calibrated, runs already processed are skipped by content hash, so the inbox may keep its old runs; then the trends
flow (:mod:`flows.trends`) reports the registry's drifting constants and outliers in its table artifact.

It needs a Prefect server with its scheduler, reachable through ``PREFECT_API_URL``: ``prefect server start``
(SQLite under ``PREFECT_HOME`` by default; for production set ``PREFECT_API_DATABASE_CONNECTION_URL`` to a
``postgresql+asyncpg://...`` URL before starting the server). thermocal's local server (``flows.localserver``,
where ``calibrate`` and ``fleet`` record their runs by default) runs without the scheduler, so ``serve`` refuses to
start without ``PREFECT_API_URL``.
"""

from __future__ import annotations

import os
from pathlib import Path
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import ThermocalError

DEPLOYMENT_NAME = "nightly"


def require_server() -> str:
    """The API URL of the Prefect server to register with; ThermocalError (one line) if none is configured."""
    url = os.environ.get("PREFECT_API_URL", "")
    if not url:
        from .runtime import prefect_defaults

        prefect_defaults()
        from prefect.settings import PREFECT_API_URL

        url = PREFECT_API_URL.value() or ""
    if not url:
        raise ThermocalError(
            "serve needs a running Prefect server: start one with `prefect server start` and set "
            "PREFECT_API_URL=http://127.0.0.1:4200/api (see README, nightly)"
        )
    import httpx

    try:
        httpx.get(f"{url.rstrip('/')}/health", timeout=10).raise_for_status()
    except httpx.HTTPError as exc:
        raise ThermocalError(
            f"cannot reach the Prefect server at PREFECT_API_URL={url} ({exc}); is `prefect server start` running?"
        ) from None
    return url


def nightly_deployment(
    inbox: str,
    registry: str,
    *,
    cron: str = "0 2 * * *",
    timezone: str = "UTC",
    name: str = DEPLOYMENT_NAME,
    settings: CalibrationSettings = CalibrationSettings(),
    dask_address: str | None = None,
    workers: int | None = None,
):
    """The deployment object: the fleet flow over ``inbox`` on a cron schedule, one run at a time."""
    from prefect.deployments.runner import EntrypointType
    from prefect.schedules import Cron

    from .fleet import fleet_flow

    try:
        ZoneInfo(timezone)
    except (ValueError, ZoneInfoNotFoundError):
        raise ThermocalError(
            f"unknown time zone {timezone!r} (IANA name, e.g. Europe/Berlin)", where="--timezone"
        ) from None
    try:
        schedule = Cron(cron, timezone=timezone)
    except ValueError as exc:
        raise ThermocalError(f"not a valid cron schedule: {' '.join(str(exc).split())[:200]}", where="--cron") from None
    parameters = {
        "root": str(Path(inbox).resolve()),
        "registry": str(Path(registry).resolve()),
        "settings": settings.to_dict(),
        "dask_address": dask_address,
        "workers": workers,
        "trends": True,
    }
    return fleet_flow.to_deployment(
        name=name,
        schedule=schedule,
        parameters=parameters,
        concurrency_limit=1,
        description=f"thermocal fleet over the inbox {inbox} into the registry {registry}, cron {cron!r} ({timezone})",
        tags=["thermocal", "nightly"],
        entrypoint_type=EntrypointType.MODULE_PATH,
    )


def serve_nightly(inbox: str, registry: str, **options) -> None:
    """Register the nightly deployment and execute its runs until interrupted (blocks)."""
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO")  # per-unit log lines reach the server's UI
    require_server()
    Path(inbox).mkdir(parents=True, exist_ok=True)
    from prefect import serve

    serve(nightly_deployment(inbox, registry, **options), limit=1)
