"""Nightly processing for real: a local Prefect server (SQLite in a temporary PREFECT_HOME, a free loopback port),
`thermocal serve` registering the cron deployment, one run triggered with `prefect deployment run --watch`, and the
inbox's run calibrated into the registry. Every wait is bounded; the processes started here are stopped at the end.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from pipeline.io.runs import write_run
from pipeline.simulate.chamber import SimConfig, simulate

pytestmark = pytest.mark.slow  # a real Prefect server and the nightly serve loop

BIN = Path(sys.executable).parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(what: str, check, timeout_s: float, proc: subprocess.Popen, log: Path):
    """Poll ``check()`` until it returns something truthy; fail (with the process's log) on timeout or exit."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            value = check()
        except httpx.HTTPError:
            value = None
        if value:
            return value
        if proc.poll() is not None:
            pytest.fail(f"{what}: process exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
        time.sleep(0.5)
    pytest.fail(f"{what}: not within {timeout_s} s:\n{log.read_text()[-3000:]}")


def _start(cmd: list[str], env: dict, log: Path) -> subprocess.Popen:
    return subprocess.Popen(cmd, env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: subprocess.Popen | None) -> None:
    """SIGINT (serve pauses its schedule and exits), then SIGKILL the process group if it lingers."""
    if proc is None or proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


def test_serve_nightly_deployment_processes_the_inbox(tmp_path):
    """... and, after the fleet, the trends flow reports the registry's planted drift in its table artifact."""
    from pipeline.simulate.history import FleetSpec, Plant, write_fleet

    inbox, registry = tmp_path / "inbox", tmp_path / "registry"
    plants = {"AU-1003": Plant(u0_rate_v_per_year=(1.2e-4, 0.0, 0.0))}  # +40 uV per 120 days
    write_fleet(registry, FleetSpec(units=10, versions=3, serial_format="AU-1{:03d}", plants=plants))
    res = simulate(SimConfig(unit_serial="AU-0301", unit_seed=301, program="short", rate_hz=2.0))
    write_run(res.run, inbox / "AU-0301.mcap", "mcap")
    (inbox / "broken.mcap").write_bytes(b"not an mcap file")

    port = _free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_LOGGING_LEVEL"}  # serve's own default: INFO
    env.update(
        {
            "PREFECT_HOME": str(tmp_path / "prefect-home"),
            "PREFECT_API_URL": api,
            "DO_NOT_TRACK": "1",
            "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
            "PREFECT_UI_ENABLED": "false",
            "PREFECT_RUNNER_POLL_FREQUENCY": "2",
        }
    )  # serve looks for due runs every 2 s (default 10 s)
    server = serve = None
    try:
        server = _start(
            [str(BIN / "prefect"), "server", "start", "--host", "127.0.0.1", "--port", str(port)],
            env,
            tmp_path / "server.log",
        )
        _wait_for(
            "prefect server health",
            lambda: httpx.get(f"{api}/health", timeout=5).status_code == 200,
            180,
            server,
            tmp_path / "server.log",
        )

        serve = _start(
            [
                str(BIN / "thermocal"),
                "serve",
                "--inbox",
                str(inbox),
                "--registry",
                str(registry),
                "--cron",
                "0 2 * * *",
                "--timezone",
                "Europe/Berlin",
            ],
            env,
            tmp_path / "serve.log",
        )
        deployment = _wait_for(
            "deployment registered",
            lambda: (
                (r := httpx.get(f"{api}/deployments/name/thermocal-fleet/nightly", timeout=5)).status_code == 200
                and r.json()
            ),
            120,
            serve,
            tmp_path / "serve.log",
        )
        (schedule,) = deployment["schedules"]
        assert schedule["schedule"]["cron"] == "0 2 * * *" and schedule["schedule"]["timezone"] == "Europe/Berlin"
        assert deployment["parameters"]["root"] == str(inbox.resolve())

        run = subprocess.run(
            [str(BIN / "prefect"), "deployment", "run", "thermocal-fleet/nightly", "--watch", "--watch-timeout", "240"],
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert run.returncode == 0, run.stdout + run.stderr + (tmp_path / "serve.log").read_text()[-3000:]

        flow_runs = httpx.post(
            f"{api}/flow_runs/filter",
            timeout=10,
            json={"limit": 10, "deployments": {"id": {"any_": [deployment["id"]]}}},
        ).json()
        assert [fr["state"]["type"] for fr in flow_runs] == ["COMPLETED"]
        passport = json.loads((registry / "units" / "AU-0301" / "v0001.json").read_text())
        assert passport["status"] == "pass"
        assert [Path(i["path"]).name for i in passport["provenance"]["inputs"]] == ["AU-0301.mcap"]
        # the flow run's table artifact lists the calibrated unit and the broken run with its reason
        arts = {
            a["key"]: a
            for a in httpx.post(
                f"{api}/artifacts/filter",
                timeout=10,
                json={"limit": 10, "flow_runs": {"id": {"any_": [flow_runs[0]["id"]]}}},
            ).json()
        }
        assert sorted(arts) == ["registry-head", "thermocal-fleet"]
        # the registry's signed head statement, for a later 'passport verify --against'
        assert '"AU-0301"' in arts["registry-head"]["data"] and '"signature"' in arts["registry-head"]["data"]
        art = arts["thermocal-fleet"]
        rows = json.loads(art["data"]) if isinstance(art["data"], str) else art["data"]
        assert {(r["unit"], r["outcome"]) for r in rows} == {("AU-0301", "done"), ("", "failed")}
        assert "not an MCAP file" in next(r["detail"] for r in rows if r["outcome"] == "failed")
        assert "AU-0301: v1 pass" in (tmp_path / "serve.log").read_text()  # the per-unit log line
        # then the trends flow (a subflow of the nightly run): its table names the planted drift, nothing else
        (trends,) = httpx.post(
            f"{api}/artifacts/filter", timeout=10, json={"artifacts": {"key": {"any_": ["thermocal-trends"]}}}
        ).json()
        rows = json.loads(trends["data"]) if isinstance(trends["data"], str) else trends["data"]
        assert [(r["kind"], r["unit"], r["constant"]) for r in rows] == [("drifting", "AU-1003", "U0.x")]
        assert "11 units" in (tmp_path / "serve.log").read_text()  # its log lines
    finally:
        _stop(serve)
        _stop(server)
