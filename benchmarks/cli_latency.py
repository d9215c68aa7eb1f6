"""Latency of the ``thermocal`` command, whole processes side by side in one run: ``inspect``, ``calibrate`` of a
10 Hz standard run with the embedded default (thermocal's local Prefect server, flows/localserver.py: its first
call on a fresh Prefect home, which starts the server, and later calls), ``calibrate`` against a running
``prefect server`` (``PREFECT_API_URL``), the calibrate flow in Prefect's own ephemeral mode (a Python process
calling :func:`flows.calibrate.run_calibrate` with ``local_server=False``: the default before the local server),
and a no-op ``fleet`` of 200 runs (all already calibrated).

    .venv/bin/python benchmarks/cli_latency.py [--repeat 5] [--fleet-runs 200] [--fleet-program short]
        [--fleet-rate-hz 2] [--no-ephemeral]

``inspect`` and the warm embedded ``calibrate`` are timed in turn (inspect, calibrate, inspect, ...: the same load
for both), ``--repeat`` times each after one warm-up call each; their rows give the median wall time (min-max), the
ratio of the medians and the median of the pairwise ratios, and the CPU seconds of every process a call used: the
command itself and, for ``calibrate``, its job process (forked by the local server's forkserver) and the local
server's share (Prefect's API runs in it; from /proc: robust to other jobs on the machine, unlike wall time).
``calibrate`` back to back (no inspect between the calls) is timed too. The other rows are single or
least-of-``--repeat`` figures, started the way a user starts them (the ``thermocal`` console script). The script
checks that every embedded calibrate and the fleet were recorded on the local server (its flow-run count), and
stops every server it started. The runs are made by :mod:`make_runs` (``benchmarks/out/std_10hz_json.mcap``) and,
for the fleet, simulated into ``benchmarks/out/fleet_<program>_<rate>hz_<n>/`` (kept for the next time) and
calibrated once before timing. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import socket
import statistics
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
#: the calibrate flow of RUN into REGISTRY (``python -c ... RUN REGISTRY``) in Prefect's own ephemeral mode
EPHEMERAL_CALIBRATE = (
    "import sys; from flows.calibrate import run_calibrate; from pipeline.calibrate.settings import "
    "CalibrationSettings; run_calibrate([sys.argv[1]], sys.argv[2], CalibrationSettings(), 'auto', local_server=False)"
)


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


def proc_cpu_s(pid: int, children: bool = False) -> float:
    """CPU seconds (user + system) of a process from /proc, or of its reaped children with ``children``."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    ticks = int(fields[13]) + int(fields[14]) if children else int(fields[11]) + int(fields[12])
    return ticks / os.sysconf("SC_CLK_TCK")


def own_children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


class Sample:
    """Wall and CPU seconds of calls of one command (``cpu_s``: every process the call used that can be counted)."""

    def __init__(self):
        self.wall_s: list[float] = []
        self.cpu_s: list[float] = []

    def line(self) -> str:
        w = self.wall_s
        return f"{statistics.median(w):.2f} ({min(w):.2f}-{max(w):.2f})"

    @property
    def median_s(self) -> float:
        return statistics.median(self.wall_s)

    @property
    def cpu_median_s(self) -> float:
        return statistics.median(self.cpu_s)


def call(cmd: list[str], env: dict, sample: Sample, server: dict | None = None, ok=(0,)) -> str:
    """One timed call of ``cmd``; ``server``: the local server's processes (``server`` pid, its ``forkserver``),
    whose CPU spent meanwhile (the job process the forkserver forked and reaped, the server's) is counted too."""

    def server_cpu_s() -> float:
        return proc_cpu_s(server["forkserver"], children=True) + proc_cpu_s(server["server"]) if server else 0.0

    c0, s0 = own_children_cpu_s(), server_cpu_s()
    t = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if proc.returncode not in ok:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    if server:  # the job process ends (and is reaped by the forkserver) a moment after the client has its answer
        deadline = time.monotonic() + 60
        while children_of(server["forkserver"]) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.25)
    sample.wall_s.append(wall)
    sample.cpu_s.append(own_children_cpu_s() - c0 + server_cpu_s() - s0)
    return proc.stdout


def children_of(pid: int) -> list[int]:
    kids = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        kids.append(int(d))
            except (OSError, ValueError, IndexError):
                continue
    return kids


def local_server_processes(state: dict) -> dict:
    """The pids of the local server (Prefect's API runs in it) and of its forkserver (which forks the jobs)."""
    for pid in children_of(state["pid"]):
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            if b"multiprocessing.forkserver" in f.read():
                return {"server": state["pid"], "forkserver": pid}
    raise SystemExit("the local server has no forkserver")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def api(url: str, path: str, body: dict | None = None) -> object:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        url + path, data=data, headers={"Content-Type": "application/json"}, method="GET" if body is None else "POST"
    )
    with urllib.request.urlopen(req, timeout=30) as resp:
        return json.loads(resp.read())


def start_prefect_server(env: dict, home: Path) -> tuple[subprocess.Popen, str]:
    """A user's own ``prefect server start`` on a free loopback port (its own session)."""
    port = free_port()
    url = f"http://127.0.0.1:{port}/api"
    proc = subprocess.Popen(
        [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
        env=dict(env, PREFECT_HOME=str(home)),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
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
    ap.add_argument("--repeat", type=int, default=5)
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
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(PREFECT_HOME=str(home), PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1")
    rows: list[tuple[str, float, str]] = []
    load0 = os.getloadavg()[0]
    k = iter(range(10**6))

    def calibrate(env_: dict, repeat: int) -> tuple[float, str]:
        return timed([THERMOCAL, "calibrate", run, "--json", "--registry", str(work / f"reg{next(k)}")], env_, repeat)

    def add(name: str, wall: float, note: str = "") -> None:
        rows.append((name, wall, note))
        print(f"  {name}: {wall:.2f} s {note}", file=sys.stderr, flush=True)

    own = None
    try:
        add("python start-up", timed([sys.executable, "-c", "pass"], env, args.repeat)[0])
        first = calibrate(env, 1)[0]
        from flows.localserver import read_state

        st = read_state(home)
        local = local_server_processes(st)
        ins, cal, b2b = Sample(), Sample(), Sample()
        call([THERMOCAL, "inspect", run, "--json"], env, Sample())  # warm-up calls
        call([THERMOCAL, "calibrate", run, "--json", "--registry", str(work / f"reg{next(k)}")], env, Sample(), local)
        for _ in range(args.repeat):  # in turn: the same load
            call([THERMOCAL, "inspect", run, "--json"], env, ins)
            call([THERMOCAL, "calibrate", run, "--json", "--registry", str(work / f"reg{next(k)}")], env, cal, local)
        for _ in range(args.repeat):
            call([THERMOCAL, "calibrate", run, "--json", "--registry", str(work / f"reg{next(k)}")], env, b2b, local)
        pair = statistics.median(c / i for c, i in zip(cal.wall_s, ins.wall_s))
        inspect_s = ins.median_s
        add("thermocal inspect (no Prefect)", inspect_s, f"median (min-max) {ins.line()}; CPU s {ins.cpu_median_s:.2f}")
        add(
            "thermocal calibrate, embedded: first call (fresh PREFECT_HOME: starts the local server)",
            first,
            f"{first / inspect_s:.1f}x inspect",
        )
        n_flow_runs = api(st["api_url"], "/flow_runs/count", {})
        add(
            "thermocal calibrate, embedded: later calls (local server running), in turn with inspect",
            cal.median_s,
            f"median (min-max) {cal.line()}: **{cal.median_s / inspect_s:.2f}x inspect** (median of the pairwise "
            f"ratios {pair:.2f}); CPU s {cal.cpu_median_s:.2f} (command, job process, Prefect server), "
            f"{cal.cpu_median_s / ins.cpu_median_s:.2f}x inspect's",
        )
        add(
            "thermocal calibrate, embedded: later calls back to back",
            b2b.median_s,
            f"median (min-max) {b2b.line()}: {b2b.median_s / inspect_s:.2f}x inspect; CPU s {b2b.cpu_median_s:.2f}; "
            f"flow runs recorded on the local server: {n_flow_runs} of {2 + 2 * args.repeat}",
        )
        t0 = time.perf_counter()
        timed(
            [THERMOCAL, "fleet", str(fleet_dir), "--registry", str(work / "fleet-reg"), "--json", "--no-figures"],
            env,
            1,
            ok=(0, 1),
        )
        first_fleet = time.perf_counter() - t0
        wall, out = timed(
            [THERMOCAL, "fleet", str(fleet_dir), "--registry", str(work / "fleet-reg"), "--json"],
            env,
            args.repeat,
            ok=(0, 1),
        )
        s = json.loads(out)
        add(
            f"thermocal fleet, no-op over {args.fleet_runs} runs ({args.fleet_program} program, "
            f"{args.fleet_rate_hz:g} Hz), embedded, least of {args.repeat}",
            wall,
            f"{len(s['skipped'])} skipped, {len(s['done'])} done (calibrating them first took {first_fleet:.0f} s)",
        )
        own_home = work / "own-server-home"
        own, url = start_prefect_server(env, own_home)
        before = api(url, "/flow_runs/count", {})
        wall = calibrate(dict(env, PREFECT_API_URL=url), args.repeat)[0]
        after = api(url, "/flow_runs/count", {})
        add(
            f"thermocal calibrate, PREFECT_API_URL (a running prefect server, in-process), least of {args.repeat}",
            wall,
            f"{wall / inspect_s:.1f}x inspect; flow runs recorded on that server: {before} -> {after}",
        )
        if not args.no_ephemeral:
            eph_env = dict(env, PREFECT_HOME=str(work / "ephemeral-home"))
            eph = [sys.executable, "-c", EPHEMERAL_CALIBRATE, run]
            timed([*eph, str(work / f"reg{next(k)}")], eph_env)  # creates its database
            wall = timed([*eph, str(work / f"reg{next(k)}")], eph_env)[0]
            add(
                "calibrate flow in Prefect's own ephemeral mode (run_calibrate(local_server=False): the old default)",
                wall,
                f"{wall / inspect_s:.1f}x inspect",
            )
    finally:
        if own is not None:
            stop_process_group(own)
        subprocess.run([THERMOCAL, "server", "stop"], env=env, capture_output=True, timeout=60)
        shutil.rmtree(work, ignore_errors=True)

    print(
        f"\n10 Hz standard run ({Path(run).name}); {os.cpu_count()} CPUs, 1-min load average "
        f"{load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end\n"
    )
    print("| command | wall s | note |\n|---|---:|---|")
    for name, wall, note in rows:
        print(f"| {name} | {wall:.2f} | {note} |")


if __name__ == "__main__":
    main()
