"""``thermocal server status|start|url|stop``: thermocal's local Prefect server
(:mod:`flows.localserver`)."""

from __future__ import annotations

import os

from .app import JsonFlag, emit, server_app


@server_app.command("status")
def server_status(as_json: JsonFlag = False):
    """Where Prefect state lives (PREFECT_HOME) and the local server's API URL, if it is running."""
    from ..localserver import LOG, read_state, use_prefect_home

    home = use_prefect_home()
    st = read_state(home) or {}
    obj = {
        "prefect_home": str(home),
        "running": bool(st),
        "api_url": st.get("api_url"),
        "ui_url": st.get("ui_url"),
        "pid": st.get("pid"),
        "idle_timeout_s": st.get("idle_s"),
        "log": str(home / LOG),
        "prefect_api_url_env": os.environ.get("PREFECT_API_URL"),
    }
    text = (
        f"PREFECT_HOME {home}\n"
        + (
            f"server running (pid {st['pid']}): API {st['api_url']}, UI {st['ui_url']}, "
            f"exits after {st['idle_s']:.0f} s without a command or an API request"
            if st
            else "server not running (starts with the next calibrate or fleet)"
        )
        + ("\nPREFECT_API_URL is set: flows are recorded there instead" if os.environ.get("PREFECT_API_URL") else "")
    )
    emit(obj, as_json, text)


@server_app.command("start")
def server_start():
    """Start the local server now (else the next calibrate or fleet starts it); print its API URL."""
    from ..localserver import ensure_server

    print(ensure_server()["api_url"])


@server_app.command("url")
def server_url():
    """The local server's API URL (starting it if needed), for `PREFECT_API_URL=$(thermocal server url) prefect
    flow-run ls` and the UI."""
    from ..localserver import ensure_server

    print(ensure_server()["api_url"])


@server_app.command("stop")
def server_stop():
    """Stop the local server (and its warm processes); commands running on it are interrupted."""
    from ..localserver import stop_server

    print("stopped" if stop_server() else "not running")
