"""Latency of the ``thermocal`` command, whole processes side by side in one run: ``inspect``, ``calibrate`` of a
10 Hz standard run with the embedded default (thermocal's local Prefect server, flows/localserver.py: its first
call on a fresh Prefect home, which starts the server, and later calls), ``calibrate`` against a running
``prefect server`` (``PREFECT_API_URL``), ``calibrate`` in Prefect's own ephemeral mode (``THERMOCAL_PREFECT=
ephemeral``: the default before the local server), and a no-op ``fleet`` of 200 runs (all already calibrated).

    .venv/bin/python benchmarks/cli_latency.py [--repeat 3] [--fleet-runs 200] [--fleet-program short]
        [--fleet-rate-hz 2] [--no-ephemeral]

Each figure is the least wall time of ``--repeat`` fresh processes (one for the first call and the ephemeral mode),
started the way a user starts them (the ``thermocal`` console script). The script checks that every embedded
calibrate and the fleet were recorded on the local server (its flow-run count), and stops every server it started.
The runs are made by :mod:`make_runs` (``benchmarks/out/std_10hz_json.mcap``) and, for the fleet, simulated into
``benchmarks/out/fleet_<program>_<rate>hz_<n>/`` (kept for the next time) and calibrated once before timing.
Prints a markdown table.
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

THERMOCAL = str(Path(sys.executable).parent / "thermocal")


def timed(cmd: list[str], env: dict, repeat: int = 1, ok=(0,)) -> tuple[float, str]:
    """Least wall time of ``repeat`` runs of ``cmd`` (whose exit status must be in ``ok``) and its stdout."""
    best, out = float("inf"), ""
    for _ in range(repeat):
        t = time.perf_counter()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t
        if proc.returncode not in ok:
            raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
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
    with urllib.request.urlopen(req, timeout=30) as resp:
        return json.loads(resp.read())


def start_prefect_server(env: dict, home: Path) -> tuple[subprocess.Popen, str]:
    """A user's own ``prefect server start`` on a free loopback port (its own session)."""
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
            time.sleep(0.5)
    stop_process_group(proc)
    raise SystemExit("prefect server did not start within 180 s")


def stop_process_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        os.killpg(proc.pid, signal.SIGKILL)


def make_fleet_runs(n: int, program: str, rate_hz: float, out: Path) -> Path:
    """``n`` simulated units (one run each) in a kept folder, made on two spawned processes."""
    from fleet_throughput import make_fleet

    folder = out / f"fleet_{program}_{rate_hz:g}hz_{n}"
    make_fleet(folder, n, rate_hz, program, 2)
    return folder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--fleet-runs", type=int, default=200)
    ap.add_argument("--fleet-program", default="short")
    ap.add_argument("--fleet-rate-hz", type=float, default=2.0)
    ap.add_argument("--no-ephemeral", action="store_true", help="skip Prefect's ephemeral mode (~10-30 s)")
    args = ap.parse_args()
    run = str(make_runs(10, args.out)["mcap-json"])
    fleet_dir = make_fleet_runs(args.fleet_runs, args.fleet_program, args.fleet_rate_hz, args.out)
    work = Path(tempfile.mkdtemp(prefix="thermocal-cli-latency-"))
    home = work / "prefect-home"  # the embedded default's Prefect home, fresh
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "THERMOCAL_PREFECT")}
    env.update(PREFECT_HOME=str(home), PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1")
    rows: list[tuple[str, float, str]] = []
    k = iter(range(10**6))

    def calibrate(env_: dict, repeat: int) -> tuple[float, str]:
        return timed([THERMOCAL, "calibrate", run, "--json", "--registry", str(work / f"reg{next(k)}")], env_, repeat)

    def add(name: str, wall: float, note: str = "") -> None:
        rows.append((name, wall, note))
        print(f"  {name}: {wall:.2f} s {note}", file=sys.stderr, flush=True)

    own = None
    try:
        add("python start-up", timed([sys.executable, "-c", "pass"], env, args.repeat)[0])
        inspect_s = timed([THERMOCAL, "inspect", run, "--json"], env, args.repeat)[0]
        add("thermocal inspect (no Prefect)", inspect_s)
        first = calibrate(env, 1)[0]
        from flows.localserver import read_state

        st = read_state(home)
        add("thermocal calibrate, embedded: first call (fresh PREFECT_HOME: starts the local server)", first,
            f"{first / inspect_s:.1f}x inspect")
        later = calibrate(env, args.repeat)[0]
        n_flow_runs = api(st["api_url"], "/flow_runs/count", {})
        add("thermocal calibrate, embedded: later calls (local server running)", later,
            f"{later / inspect_s:.1f}x inspect; flow runs recorded on it: {n_flow_runs} of {1 + args.repeat}")
        t0 = time.perf_counter()
        timed([THERMOCAL, "fleet", str(fleet_dir), "--registry", str(work / "fleet-reg"), "--json", "--no-figures"],
              env, 1, ok=(0, 1))
        first_fleet = time.perf_counter() - t0
        wall, out = timed([THERMOCAL, "fleet", str(fleet_dir), "--registry", str(work / "fleet-reg"), "--json"],
                          env, args.repeat, ok=(0, 1))
        s = json.loads(out)
        add(f"thermocal fleet, no-op over {args.fleet_runs} runs ({args.fleet_program} program, "
            f"{args.fleet_rate_hz:g} Hz), embedded", wall,
            f"{len(s['skipped'])} skipped, {len(s['done'])} done (calibrating them first took {first_fleet:.0f} s)")
        own_home = work / "own-server-home"
        own, url = start_prefect_server(env, own_home)
        before = api(url, "/flow_runs/count", {})
        wall = calibrate(dict(env, PREFECT_API_URL=url), args.repeat)[0]
        after = api(url, "/flow_runs/count", {})
        add("thermocal calibrate, PREFECT_API_URL (a running prefect server, in-process)", wall,
            f"{wall / inspect_s:.1f}x inspect; flow runs recorded on that server: {before} -> {after}")
        if not args.no_ephemeral:
            eph_home = work / "ephemeral-home"
            calibrate(dict(env, PREFECT_HOME=str(eph_home), THERMOCAL_PREFECT="ephemeral"), 1)  # creates its DB
            wall = calibrate(dict(env, PREFECT_HOME=str(eph_home), THERMOCAL_PREFECT="ephemeral"), 1)[0]
            add("thermocal calibrate, THERMOCAL_PREFECT=ephemeral (Prefect's per-process server: the old default)",
                wall, f"{wall / inspect_s:.1f}x inspect")
    finally:
        if own is not None:
            stop_process_group(own)
        subprocess.run([THERMOCAL, "server", "stop"], env=env, capture_output=True, timeout=60)
        shutil.rmtree(work, ignore_errors=True)

    print(f"\n10 Hz standard run ({Path(run).name}); {os.cpu_count()} CPUs, 1-min load average "
          f"{os.getloadavg()[0]:.1f}\n")
    print("| command | wall s | note |\n|---|---:|---|")
    for name, wall, note in rows:
        print(f"| {name} | {wall:.2f} | {note} |")


if __name__ == "__main__":
    main()
