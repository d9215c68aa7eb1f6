"""Latency of one ``thermocal calibrate`` of a 10 Hz standard run, each in a fresh process, and where it goes.

    .venv/bin/python benchmarks/cli_latency.py [--repeat 3] [--no-server]

Measured (the fastest of ``--repeat`` fresh processes each):

- Python start-up alone, and the imports: the CLI module (what ``inspect`` / ``simulate`` pay), ``prefect``, and
  the flow module (Prefect plus the pipeline);
- the computation alone, without Prefect (ingest, segment, fit, verify, write the passport), in-process time;
- ``thermocal calibrate`` end to end, local ephemeral Prefect with this benchmark's Prefect home (the usual case);
- the same with a fresh, empty ``PREFECT_HOME`` (the first run on a machine: Prefect creates its database);
- the same with ``PREFECT_API_URL`` pointing at a running ``prefect server`` (started by this script, not timed):
  no ephemeral start-up; the script checks that the flow run was recorded on that server.

The run is made by :mod:`make_runs` (``benchmarks/out/std_10hz_json.mcap``). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from make_runs import OUT, make_runs  # noqa: E402

COMPUTE = """
import json, sys, tempfile, time
t0 = time.perf_counter()
from pipeline.calibrate import tilt
from pipeline.calibrate.publish import publish
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.io.runs import read_run
t1 = time.perf_counter()
s = CalibrationSettings()
with tempfile.TemporaryDirectory() as reg:
    publish(reg, tilt.calibrate([read_run(sys.argv[1])], s), input_paths=[sys.argv[1]], settings=s)
print(json.dumps({"import_s": t1 - t0, "compute_s": time.perf_counter() - t1}))
"""


def timed(cmd: list[str], env: dict, repeat: int) -> tuple[float, str]:
    """Least wall time of ``repeat`` runs of ``cmd`` (which must succeed) and the last one's stdout."""
    best, out = float("inf"), ""
    for _ in range(repeat):
        t = time.perf_counter()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t
        if proc.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
        best, out = min(best, wall), proc.stdout
    return best, out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def api(url: str, path: str, body: dict | None = None) -> object:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url + path, data=data, headers={"Content-Type": "application/json"},
                                 method="GET" if body is None else "POST")
    with urllib.request.urlopen(req, timeout=10) as resp:
        return json.loads(resp.read())


def start_server(env: dict, home: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    url = f"http://127.0.0.1:{port}/api"
    proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port",
                             str(port)], env=dict(env, PREFECT_HOME=str(home)), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        try:
            api(url, "/health")
            return proc, url
        except OSError:
            time.sleep(1)
    stop_server(proc)
    raise SystemExit("prefect server did not start within 180 s")


def stop_server(proc: subprocess.Popen) -> None:
    """Stop the server this script started (its own process group: the server and its workers)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        os.killpg(proc.pid, signal.SIGKILL)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--no-server", action="store_true", help="skip the PREFECT_API_URL measurement")
    args = ap.parse_args()
    run = str(make_runs(10, args.out)["mcap-json"])
    py = sys.executable
    home = args.out / "prefect-home"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(PREFECT_HOME=str(home), PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1")
    calibrate = [py, "-m", "flows.cli", "calibrate", run, "--json", "--registry"]
    rows: list[tuple[str, float, str]] = []

    def add(name: str, cmd: list[str], env_: dict = env, repeat: int = args.repeat, note: str = "") -> str:
        wall, out = timed(cmd, env_, repeat)
        rows.append((name, wall, note))
        print(f"  {name}: {wall:.2f} s", file=sys.stderr)
        return out

    add("python start-up", [py, "-c", "pass"])
    add("import flows.cli (CLI, no Prefect)", [py, "-c", "import flows.cli"])
    add("import prefect", [py, "-c", "import prefect"])
    add("import flows.calibrate (Prefect + pipeline)", [py, "-c", "import flows.calibrate"])
    figures = json.loads(add("compute only, no Prefect (process)", [py, "-c", COMPUTE, run]).strip().splitlines()[-1])
    rows[-1] = (rows[-1][0], rows[-1][1], f"in-process: imports {figures['import_s']:.2f} s, ingest..write "
                                          f"{figures['compute_s']:.2f} s")
    with tempfile.TemporaryDirectory() as reg:
        add("thermocal calibrate, ephemeral Prefect", calibrate + [reg])
    fresh_home = Path(tempfile.mkdtemp(prefix="prefect-fresh-"))
    try:
        with tempfile.TemporaryDirectory() as reg:
            add("thermocal calibrate, ephemeral Prefect, fresh PREFECT_HOME", calibrate + [reg],
                dict(env, PREFECT_HOME=str(fresh_home)), repeat=1)
    finally:
        shutil.rmtree(fresh_home, ignore_errors=True)
    if not args.no_server:
        server_home = Path(tempfile.mkdtemp(prefix="prefect-server-"))
        proc, url = start_server(env, server_home)
        try:
            before = api(url, "/flow_runs/count", {})
            with tempfile.TemporaryDirectory() as reg:
                add("thermocal calibrate, PREFECT_API_URL (running server)", calibrate + [reg],
                    dict(env, PREFECT_API_URL=url))
            after = api(url, "/flow_runs/count", {})
            rows[-1] = (rows[-1][0], rows[-1][1], f"flow runs recorded on that server: {before} -> {after}")
        finally:
            stop_server(proc)
            shutil.rmtree(server_home, ignore_errors=True)

    print(f"\n10 Hz standard run ({run}); {os.cpu_count()} CPUs, 1-min load average {os.getloadavg()[0]:.1f}\n")
    print("| step | wall s | note |\n|---|---:|---|")
    for name, wall, note in rows:
        print(f"| {name} | {wall:.2f} | {note} |")


if __name__ == "__main__":
    main()
