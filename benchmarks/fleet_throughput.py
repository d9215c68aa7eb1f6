"""Fleet throughput: units per minute for a fleet of simulated units of the standard program, by where the unit
tasks run, with the Prefect overhead per unit; and the single-run latency of ``thermocal calibrate``.

    .venv/bin/python benchmarks/fleet_throughput.py [--units 50] [--rate-hz 10] [--workers N] [--cli-runs 3]
        [--modes plain,pool,thread1,thread,process,dask,cli,cli-ephemeral] [--encoding json|protobuf]
        [--keep DIR] [--json-out FILE]

The runs are simulated into a temporary folder (MCAP, one 16.5 h standard run per unit, distinct units and noise;
about 17 MB each at 10 Hz; ``--encoding``: JSON blocks, the default, or protobuf) and deleted at the end unless
``--keep`` names a folder (reused when it holds them: wrap runs in ``flock`` when other jobs share the machine).
Every mode calibrates the whole fleet into a fresh registry:

- ``plain``:   :func:`pipeline.calibrate.fleet.calibrate_group` in a loop, no Prefect (the compute baseline);
- ``pool``:    what the flow's ``pool="process"`` does, without Prefect: :func:`pipeline.calibrate.fleet.plan_fleet`,
  then ``calibrate_group`` on a spawn process pool of ``--workers`` warmed by ``prepare_worker`` (the parallel
  baseline: ``process`` wall / ``pool`` wall - 1 is Prefect's share);
- ``thread1``: the fleet flow with one worker thread: its wall time minus the compute measured inside the tasks is
  Prefect's own cost (flow run, planning, task runs, artifact), given per unit;
- ``thread``, ``process``: the flow on a local pool of ``--workers`` (default: CPU count) threads / processes;
- ``dask``:    the flow on a dask LocalCluster (``--workers`` single-threaded worker processes on 127.0.0.1) through
  ``--dask-address``; the cluster start is timed apart;
- ``cli``:     ``thermocal fleet FOLDER --registry R --json --workers N`` in a fresh process, end to end (Python
  start, imports, flow, pool, planning), with ``PREFECT_API_URL`` set to the running local API (as nightly runs
  under ``thermocal serve`` or with a server); ``cli-ephemeral``: the fleet flow in a fresh Python process
  without ``PREFECT_API_URL`` (``run_fleet(..., local_server=False)``), so it starts its own temporary API
  (Prefect home made once before, untimed: the usual case after the first command on a machine).

Columns: wall time, units per minute, the mean compute per unit measured inside the tasks (it grows when workers
compete for the cores), the overhead per unit = (workers x wall - sum of in-task compute) / units: the worker
time per unit not spent calibrating (Prefect, planning, pool start-up, idle tail), the same as a share of the
workers' wall time (1 - sum of in-task compute / (workers x wall)), and the CPU seconds per unit, split into the
finished children (pool and dask workers; in the ``cli`` modes the command and everything it started), this
process (the flow, planning and Prefect's client side; the calibration itself in the thread modes) and the
Prefect API server: unlike wall time, CPU time hardly depends on what else runs on the machine. The Prefect API is
a local temporary server started once before the modes (its start-up is reported apart); the load average is
printed (it counts this benchmark's own threads too), since other work on the machine slows everything.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

MODES = ("plain", "pool", "thread1", "thread", "process", "dask", "cli", "cli-ephemeral")
#: the fleet flow over FOLDER into REGISTRY on WORKERS (``python -c ... FOLDER REGISTRY WORKERS``) in Prefect's own
#: ephemeral mode, its summary as JSON on stdout
EPHEMERAL_FLEET = (
    "import json, sys; from flows.fleet import run_fleet; s = run_fleet(sys.argv[1], sys.argv[2], "
    "workers=int(sys.argv[3]), method='auto', local_server=False); print(json.dumps(s, default=str))"
)
#: the calibrate flow of RUN into REGISTRY (``python -c ... RUN REGISTRY``) in Prefect's own ephemeral mode
EPHEMERAL_CALIBRATE = (
    "import sys; from flows.calibrate import run_calibrate; from pipeline.calibrate.settings import "
    "CalibrationSettings; run_calibrate([sys.argv[1]], sys.argv[2], CalibrationSettings(), 'auto', local_server=False)"
)


def _make_unit(args: tuple[Path, int, float, str, str]) -> str:
    out, k, rate_hz, program, encoding = args
    from pipeline.io.runs import write_run
    from pipeline.simulate.chamber import SimConfig, simulate

    path = out / f"AU-{k:04d}.mcap"
    if not path.exists():
        res = simulate(
            SimConfig(unit_serial=f"AU-{k:04d}", unit_seed=1000 + k, seed=k, program=program, rate_hz=rate_hz)
        )
        write_run(res.run, path, "mcap", encoding=encoding)
    return str(path)


def process_pool(workers: int, **options) -> ProcessPoolExecutor:
    """A pool of ``workers`` processes started by *spawn*, never *fork*: a child forked after polars, pyarrow or
    numpy have started their thread pools in this process (any Parquet written or read before) can wait forever
    on a lock one of those threads held at the fork."""
    import multiprocessing

    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), **options)


def make_fleet(out: Path, units: int, rate_hz: float, program: str, workers: int, encoding: str = "json") -> list[str]:
    """``units`` simulated units (one ``program`` run each at ``rate_hz``) in ``out``, made on ``workers``
    spawned processes; a unit whose file exists is kept."""
    out.mkdir(parents=True, exist_ok=True)
    with process_pool(workers) as pool:
        return list(pool.map(_make_unit, [(out, k, rate_hz, program, encoding) for k in range(1, units + 1)]))


def run_plain(paths: list[str], registry: Path) -> dict:
    from pipeline.calibrate.fleet import calibrate_group, read_run_meta

    t0 = time.perf_counter()
    outcomes = [calibrate_group(read_run_meta(p).unit_serial, [p], registry) for p in paths]
    wall = time.perf_counter() - t0
    failed = [f for o in outcomes for f in o.failed]
    return {
        "wall_s": wall,
        "compute_s": sum(o.compute_s for o in outcomes),
        "workers": 1,
        "units": len(outcomes),
        "done": sum(o.result is not None for o in outcomes),
        "failed": len(failed),
        "runner": "none (no Prefect)",
    }


def run_pool(folder: Path, registry: Path, workers: int) -> dict:
    from pipeline.calibrate.fleet import calibrate_group, plan_fleet, prepare_worker
    from pipeline.calibrate.settings import CalibrationSettings

    t0 = time.perf_counter()
    plan = plan_fleet(folder, registry)
    t_plan = time.perf_counter() - t0
    with process_pool(workers, initializer=prepare_worker) as pool:
        futures = [
            pool.submit(calibrate_group, g.unit, g.runs, str(registry), CalibrationSettings(), True, g.digests)
            for g in plan.groups
        ]
        outcomes = [f.result() for f in futures]
    wall = time.perf_counter() - t0
    failed = [f for o in outcomes for f in o.failed]
    return {
        "wall_s": wall,
        "compute_s": sum(o.compute_s for o in outcomes),
        "workers": workers,
        "units": len(outcomes),
        "done": sum(o.result is not None for o in outcomes),
        "failed": len(failed),
        "runner": f"ProcessPoolExecutor({workers}), no Prefect",
        "plan_s": t_plan,
    }


def run_flow(folder: Path, registry: Path, workers: int, **options) -> dict:
    from flows.fleet import run_fleet

    t0 = time.perf_counter()
    summary = run_fleet(str(folder), str(registry), workers=workers, **options)
    wall = time.perf_counter() - t0
    t = summary["timing"]
    return {
        "wall_s": wall,
        "compute_s": t["compute_s"],
        "workers": workers,
        "units": t["units"],
        "done": len(summary["done"]),
        "failed": len(summary["failed"]),
        "runner": t["runner"],
        "flow_wall_s": t["wall_s"],
        "plan_s": t["plan_s"],
    }


def run_cli(folder: Path, registry: Path, workers: int, api_url: str | None, home: Path) -> dict:
    """``thermocal fleet`` in a fresh process (see the module doc), with ``api_url``; or else the fleet flow in a
    fresh Python process with its own temporary API using the Prefect home ``home`` (``run_fleet(...,
    local_server=False)``: Prefect's per-process ephemeral mode; thermocal's default is its local server)."""
    env = dict(os.environ, PREFECT_HOME=str(home))
    env.pop("PREFECT_API_URL", None)
    if api_url:
        env["PREFECT_API_URL"] = api_url
        cmd = [str(Path(sys.executable).parent / "thermocal"), "fleet", str(folder), "--registry", str(registry)]
        cmd += ["--json", "--workers", str(workers)]
    else:
        cmd = [sys.executable, "-c", EPHEMERAL_FLEET, str(folder), str(registry), str(workers)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600)
    wall = time.perf_counter() - t0
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"thermocal fleet failed: {proc.stderr.strip()[-2000:]}")
    summary = json.loads(proc.stdout)
    t = summary["timing"]
    return {
        "wall_s": wall,
        "compute_s": t["compute_s"],
        "workers": workers,
        "units": t["units"],
        "done": len(summary["done"]),
        "failed": len(summary["failed"]),
        "runner": f"thermocal fleet, {'PREFECT_API_URL' if api_url else 'own temporary API'}: {t['runner']}",
        "flow_wall_s": t["wall_s"],
        "plan_s": t["plan_s"],
    }


def run_dask(folder: Path, registry: Path, workers: int) -> dict:
    from distributed import Client, LocalCluster

    t0 = time.perf_counter()
    with (
        LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=40,
        ) as cluster,
        Client(cluster) as client,
    ):
        client.wait_for_workers(workers, timeout=120)
        start_s = time.perf_counter() - t0
        out = run_flow(folder, registry, workers, dask_address=cluster.scheduler_address)
    out["cluster_start_s"] = start_s
    return out


def cli_latency(run: str, repeats: int, workdir: Path, api_url: str | None) -> list[float]:
    """Wall seconds of `thermocal calibrate RUN --registry <fresh> --json` with ``api_url``, or else of the calibrate
    flow in a fresh Python process in Prefect's ephemeral mode, ``repeats`` times."""
    exe = str(Path(sys.executable).parent / "thermocal")
    env = dict(os.environ)
    env.pop("PREFECT_API_URL", None)
    if api_url:
        env["PREFECT_API_URL"] = api_url
    times = []
    for k in range(repeats):
        reg = workdir / f"cli-reg-{'server' if api_url else 'ephemeral'}-{k}"
        t0 = time.perf_counter()
        proc = subprocess.run(
            [exe, "calibrate", run, "--registry", str(reg), "--json"]
            if api_url
            else [sys.executable, "-c", EPHEMERAL_CALIBRATE, run, str(reg)],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        times.append(time.perf_counter() - t0)
        if proc.returncode != 0:
            raise RuntimeError(f"thermocal calibrate failed: {proc.stderr.strip()}")
    return times


def start_local_api() -> tuple[str, float, int]:
    """Start (or find) this process's temporary Prefect server; its URL, the seconds it took, its pid."""
    os.environ.setdefault("PREFECT_HOME", tempfile.mkdtemp(prefix="thermocal-bench-prefect-"))
    from flows.runtime import prefect_defaults

    prefect_defaults()
    from prefect.server.api.server import SubprocessASGIServer

    t0 = time.perf_counter()
    server = SubprocessASGIServer()
    server.start()
    os.environ["PREFECT_API_URL"] = server.api_url  # the in-process flows record on it (not on a local server)
    return server.api_url, time.perf_counter() - t0, server.server_process.pid


def warm_up(path: str, registry: Path) -> None:
    """One unit calibrated, and one tiny flow run, before timing: imports, first figure, first flow run."""
    from flows.fleet import run_fleet
    from pipeline.calibrate.fleet import calibrate_group, read_run_meta

    calibrate_group(read_run_meta(path).unit_serial, [path], registry)
    empty = registry / "empty-inbox"
    empty.mkdir(parents=True, exist_ok=True)
    run_fleet(str(empty), str(registry))


class CpuClock:
    """CPU seconds (user + system) of this process (the flow, planning, Prefect's client side), of its waited-for
    children (pool and dask worker processes) and of the Prefect API server."""

    def __init__(self, server_pid: int | None):
        import psutil

        self.me = psutil.Process()
        self.server = psutil.Process(server_pid) if server_pid else None

    def __call__(self) -> dict[str, float]:
        t = self.me.cpu_times()
        out = {"flow": t.user + t.system, "workers": t.children_user + t.children_system, "api": 0.0}
        if self.server is not None:
            s = self.server.cpu_times()
            out["api"] = s.user + s.system
        return out


def table(results: dict[str, dict]) -> str:
    lines = [
        "| mode | runner | units | wall s | units/min | compute s/unit (in task) | overhead s/unit | "
        "overhead % of wall | CPU s/unit (workers + flow + API) | failed |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for mode, r in results.items():
        n = max(r["units"], 1)
        overhead = (r["workers"] * r["wall_s"] - r["compute_s"]) / n
        c = r["cpu"]
        lines.append(
            f"| {mode} | {r['runner']} | {r['units']} | {r['wall_s']:.1f} | "
            f"{60 * r['done'] / r['wall_s']:.1f} | {r['compute_s'] / n:.2f} | {overhead:.2f} | "
            f"{100 * overhead * n / (r['workers'] * r['wall_s']):.0f} | "
            f"{r['cpu_s'] / n:.2f} ({c['workers'] / n:.2f} + {c['flow'] / n:.2f} + {c['api'] / n:.2f}) | "
            f"{r['failed']} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=50)
    ap.add_argument("--rate-hz", type=float, default=10.0)
    ap.add_argument("--program", default="standard")
    ap.add_argument("--encoding", default="json", choices=("json", "protobuf"), help="MCAP message encoding")
    ap.add_argument("--workers", type=int, default=None, help="pool size (default: CPU count)")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--cli-runs", type=int, default=3, help="repetitions of the CLI latency (0: skip)")
    ap.add_argument("--keep", type=Path, default=None, help="folder for the simulated runs (kept)")
    ap.add_argument("--json-out", type=Path, default=None)
    args = ap.parse_args()
    modes = [m for m in args.modes.split(",") if m]
    unknown = set(modes) - set(MODES)
    if unknown:
        ap.error(f"unknown modes {sorted(unknown)}; choose from {', '.join(MODES)}")

    from flows.fleet import default_workers

    workers = args.workers or default_workers()
    work = Path(tempfile.mkdtemp(prefix="thermocal-fleet-bench-"))
    runs_dir = args.keep or work / "runs"
    print(
        f"# fleet throughput: {args.units} units, {args.program} program at {args.rate_hz:g} Hz, "
        f"{workers} workers, {os.cpu_count()} CPUs; load average at start {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    try:
        t0 = time.perf_counter()
        paths = make_fleet(runs_dir, args.units, args.rate_hz, args.program, workers, args.encoding)
        size_mb = sum(Path(p).stat().st_size for p in paths) / 1e6
        print(
            f"simulated and wrote {len(paths)} runs ({size_mb:.0f} MB) in {time.perf_counter() - t0:.1f} s", flush=True
        )
        api_url, api_s, api_pid = start_local_api()
        cpu = CpuClock(api_pid)
        print(f"local Prefect API started in {api_s:.1f} s ({api_url})", flush=True)
        warm_up(paths[0], work / "registry-warm-up")
        (work / "empty-inbox").mkdir()
        results: dict[str, dict] = {}
        for mode in modes:
            reg = work / f"registry-{mode}"
            t_mode, cpu0 = time.perf_counter(), cpu()
            if mode == "plain":
                results[mode] = run_plain(paths, reg)
            elif mode == "pool":
                results[mode] = run_pool(runs_dir, reg, workers)
            elif mode == "thread1":
                results[mode] = run_flow(runs_dir, reg, 1, pool="thread")
            elif mode in ("thread", "process"):
                results[mode] = run_flow(runs_dir, reg, workers, pool=mode)
            elif mode == "cli":
                results[mode] = run_cli(runs_dir, reg, workers, api_url, work / "prefect-home-cli")
            elif mode == "cli-ephemeral":
                home = work / "prefect-home-cli-ephemeral"
                run_cli(work / "empty-inbox", work / "registry-cli-warm-up", workers, None, home)  # creates its DB
                t_mode, cpu0 = time.perf_counter(), cpu()
                results[mode] = run_cli(runs_dir, reg, workers, None, home)
            else:
                results[mode] = run_dask(runs_dir, reg, workers)
            r = results[mode]
            cpu1 = cpu()
            r["cpu"] = {k: cpu1[k] - cpu0[k] for k in cpu1}
            r["cpu_s"] = sum(r["cpu"].values())
            extra = f", cluster start {r['cluster_start_s']:.1f} s" if "cluster_start_s" in r else ""
            if "flow_wall_s" in r:
                extra += f"; inside the flow {r['flow_wall_s']:.1f} s, of which planning {r['plan_s']:.1f} s"
            print(
                f"{mode}: {r['done']} units in {r['wall_s']:.1f} s ({time.perf_counter() - t_mode:.1f} s with "
                f"set-up{extra}); load {os.getloadavg()[0]:.2f}",
                flush=True,
            )
        print()
        print(table(results))
        if "pool" in results and "process" in results:
            p, f = results["pool"], results["process"]
            print(
                f"\nPrefect's share of the process mode's wall time (1 - pool wall / process wall): "
                f"{100 * (1 - p['wall_s'] / f['wall_s']):.1f} %"
            )
        if "plain" in results and "thread1" in results:
            p, f1 = results["plain"], results["thread1"]
            print(
                f"\nPrefect overhead per unit (thread1 wall - its in-task compute, / units): "
                f"{(f1['wall_s'] - f1['compute_s']) / f1['units'] * 1000:.0f} ms; "
                f"(thread1 wall - plain wall) / units: {(f1['wall_s'] - p['wall_s']) / f1['units'] * 1000:.0f} ms"
            )
        cli = {}
        if args.cli_runs:
            cli["ephemeral"] = cli_latency(paths[0], args.cli_runs, work, None)
            cli["server"] = cli_latency(paths[0], args.cli_runs, work, api_url)
            print(
                f"\n`thermocal calibrate` on one {args.rate_hz:g} Hz {args.program} run (fresh registry), median of "
                f"{args.cli_runs}: {statistics.median(cli['ephemeral']):.1f} s with the local temporary API "
                f"(started by the command), {statistics.median(cli['server']):.1f} s with PREFECT_API_URL set to "
                f"a running server; plain compute of that unit: "
                f"{results.get('plain', {}).get('compute_s', float('nan')) / max(args.units, 1):.1f} s (mean)"
            )
        print(f"load average at end {os.getloadavg()[0]:.2f}")
        if args.json_out:
            args.json_out.write_text(
                json.dumps(
                    {
                        "args": {k: str(v) for k, v in vars(args).items()},
                        "workers": workers,
                        "api_start_s": api_s,
                        "results": results,
                        "cli_s": cli,
                    },
                    indent=2,
                )
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
