"""Many units in one chamber run (issue 22): 16 units at 100 Hz over the standard program in one file, calibrated
by ``thermocal calibrate`` (one passport per unit), side by side with the time to just decode the same file and
with the same 16 units as 16 single-unit runs through ``thermocal fleet``.

    .venv/bin/python benchmarks/multiunit.py [--units 16] [--rate-hz 100] [--encoding protobuf|json]
                                             [--steps decode,calibrate,fleet] [--dir /tmp/thermocal-bench]
                                             [--repeat 1]

Makes the runs once (``pipeline.simulate.units.simulate_units``) under ``--dir`` (not in git: ~2-3 GB): the
16-unit file and the 16 single-unit files of the same units (same samples). Then each step in a fresh Python
process, so that its peak RSS (``ru_maxrss``) is its own:

- decode: ``pipeline.io.runs.read_units`` of the 16-unit file (every unit's streams decoded, the shared ones once):
  the floor;
- floor-mcap: the ``mcap`` library's message iteration plus the plainest decode of each block (``numpy.frombuffer``
  of the packed fields, as ``ingest_1khz.py``'s floor; ``--encoding protobuf`` only) and one concatenation per
  column: the floor a plain reader of the same file has;
- calibrate: the Prefect calibrate flow on the 16-unit file (``flows.calibrate.run_calibrate``, as ``thermocal
  calibrate RUN``: read once, hashed once, segmented once, 16 passports into a fresh registry), after a warm-up
  flow has started thermocal's local server (as the command finds it once any earlier command has started it);
- fleet: the fleet flow over the folder of 16 single-unit runs (``flows.fleet.run_fleet``, as ``thermocal fleet``,
  2 worker processes), after the same warm-up.

CPU seconds are the step process's and its children's (``RUSAGE_CHILDREN``: the calibrate's figure workers, the
fleet's workers), from the end of the step's imports (a command's job process has them done; the decode floor's too);
thermocal's local server (Prefect's API, on the same cores: the flow's task runs, logs and artifacts) in a column of
its own; peak RSS is the step process's plus the sum of its children's own peaks (``VmHWM``, sampled every
second: an upper bound of what they held at once).

Prints the load average, and a markdown table: wall and CPU seconds, peak RSS against the decoded samples
(t_ns + 3 voltages, 8 bytes each, of every unit), the wall and CPU ratios to the decode floor (on a shared machine
the CPU ratio is the steadier one), and chamber hours per unit. ``--repeat N``: N rounds of the steps, alternating
(decode, calibrate, decode, calibrate, ...: on a shared machine the decode floor alone moves 10-16 s between
sittings); the table gives each step's median and a line the ratio of each round.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # ingest_1khz's floor decoder


def make(directory: Path, units: int, rate_hz: float, encoding: str) -> tuple[Path, Path]:
    """The multi-unit file and the folder of single-unit files (made once)."""
    multi = directory / f"units{units}-{rate_hz:g}hz-{encoding}.mcap"
    singles = directory / f"singles{units}-{rate_hz:g}hz-{encoding}"
    if multi.exists() and singles.is_dir() and len(list(singles.glob("*.mcap"))) == units:
        return multi, singles
    import dataclasses

    from pipeline.io.runs import write_run
    from pipeline.simulate.chamber import SimConfig
    from pipeline.simulate.units import simulate_units

    t = time.perf_counter()
    runs, _ = simulate_units(SimConfig(unit_serial="AU-1001", rate_hz=rate_hz), units)
    print(f"simulated {units} units in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    t = time.perf_counter()
    write_run(runs, multi, "mcap", encoding=encoding)
    print(f"wrote {multi} ({multi.stat().st_size / 1e9:.2f} GB) in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    singles.mkdir(parents=True, exist_ok=True)
    for serial, run in runs.units.items():
        meta = dataclasses.replace(run.meta, run_id=f"{run.meta.run_id}-{serial}")
        write_run(dataclasses.replace(run, meta=meta, source=""), singles / f"{serial}.mcap", "mcap", encoding=encoding)
    print(f"wrote {units} single-unit runs in {singles}", file=sys.stderr)
    return multi, singles


def _warm_prefect() -> float:
    """A first flow recorded where the measured flow will be (``flow_settings``: thermocal's local server, started
    here as the first thermocal command on a machine starts it), so that the step measures the command, not the
    server's start (~10-12 s here, once per machine; the server stays up for the next command)."""
    from prefect import flow as prefect_flow

    from flows.runtime import flow_settings

    t = time.perf_counter()
    with flow_settings(True):
        prefect_flow(name="warm-up")(lambda: None)()
    return time.perf_counter() - t


def step_decode(path: Path) -> dict:
    from pipeline.io.runs import read_units

    _start_clock()  # the imports outside the clock, as the calibrate's and the fleet's (~0.5 CPU s)
    got = read_units(path)
    return {"units": len(got.units), "samples": sum(r.voltmeter.height for r in got.units.values())}


def step_calibrate(path: Path) -> dict:
    from flows.calibrate import run_calibrate
    from pipeline.calibrate.settings import CalibrationSettings

    warm = _warm_prefect()
    _start_clock()
    with tempfile.TemporaryDirectory() as registry:
        r = run_calibrate([str(path)], registry, CalibrationSettings(), method="auto")
    return {
        "units": len(r["units"]),
        "passed": sum(u["status"] == "pass" for u in r["units"]),
        "failed": len(r["failed"]),
        "prefect_warm_up_s": round(warm, 2),
    }


def step_fleet(folder: Path) -> dict:
    from flows.fleet import run_fleet
    from pipeline.calibrate.settings import CalibrationSettings

    warm = _warm_prefect()
    _start_clock()
    with tempfile.TemporaryDirectory() as registry:
        r = run_fleet(str(folder), registry, CalibrationSettings(), workers=2, pool="process", method="auto")
    return {
        "units": len(r["done"]),
        "passed": sum(u["status"] == "pass" for u in r["done"]),
        "failed": len(r["failed"]),
        "prefect_warm_up_s": round(warm, 2),
    }


def step_floor_mcap(path: Path) -> dict:
    import numpy as np
    from ingest_1khz import _packed_fields
    from mcap.reader import make_reader

    _start_clock()  # the imports outside the clock, as the decode's
    parts: dict[str, dict[int, list]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.topic == "/fixture":
                continue
            cols = parts.setdefault(channel.topic, {})
            for field, values in _packed_fields(message.data, np):
                cols.setdefault(field, []).append(values)
    out = {topic: {k: np.concatenate(v) for k, v in cols.items()} for topic, cols in parts.items()}
    volts = [cols for topic, cols in out.items() if topic.endswith("/voltmeter")]
    return {"units": len(volts), "samples": sum(len(c[1]) for c in volts)}


def _server_cpu_s() -> float | None:
    """CPU seconds so far of thermocal's local server (the Prefect API the flow records its runs on: another
    process on the same cores, not a child), or None when none is running."""
    from flows.localserver import read_state

    state = read_state()
    try:
        fields = Path(f"/proc/{state['pid']}/stat").read_text().rsplit(")", 1)[1].split()  # type: ignore[index]
    except (OSError, TypeError, KeyError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _start_clock() -> None:
    server = _server_cpu_s()
    _CLOCK.update(wall=time.perf_counter(), usage=resource.getrusage(resource.RUSAGE_SELF), server=server)


STEPS = {"decode": step_decode, "floor-mcap": step_floor_mcap, "calibrate": step_calibrate, "fleet": step_fleet}
_CLOCK: dict = {}


def _children_peaks(peaks: dict[int, int], stop) -> None:
    """Until ``stop`` is set: every second, the peak RSS (``VmHWM``, kB) of each live child process of this one (the
    calibrate's figure workers, the fleet's worker processes), into ``peaks`` by pid. ``RUSAGE_CHILDREN``'s
    ``ru_maxrss`` cannot tell it: a child started by fork or vfork then exec counts the parent's pages at its exec."""
    me = os.getpid()
    while not stop.wait(1.0):
        for proc in Path("/proc").glob("[0-9]*"):
            try:
                if int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1]) != me:
                    continue
                status = (proc / "status").read_text()
            except OSError:
                continue
            hwm = [line.split()[1] for line in status.splitlines() if line.startswith("VmHWM:")]
            if hwm:
                peaks[int(proc.name)] = max(peaks.get(int(proc.name), 0), int(hwm[0]))


def child(step: str, path: Path) -> None:
    import threading

    peaks: dict[int, int] = {}
    stop = threading.Event()
    watch = threading.Thread(target=_children_peaks, args=(peaks, stop), daemon=True)
    watch.start()
    _CLOCK.update(wall=time.perf_counter(), usage=resource.getrusage(resource.RUSAGE_SELF), server=None)
    out = STEPS[step](path)
    server = _server_cpu_s() if _CLOCK["server"] is not None else None
    stop.set()
    watch.join()
    wall = time.perf_counter() - _CLOCK["wall"]
    r0, r1 = _CLOCK["usage"], resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    out.update(
        wall_s=round(wall, 2),
        cpu_s=round(r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime + kids.ru_utime + kids.ru_stime, 1),
        children_cpu_s=round(kids.ru_utime + kids.ru_stime, 1),
        server_cpu_s=round(server - _CLOCK["server"], 1) if server is not None else 0.0,
        peak_rss_gb=round(r1.ru_maxrss / 2**20, 2),
        peak_child_rss_gb=round(kids.ru_maxrss / 2**20, 2),
        children=len(peaks),
        children_peak_sum_gb=round(sum(peaks.values()) / 2**20, 2),
    )
    if step in ("calibrate", "fleet"):
        from flows.localserver import stop_server

        stop_server()  # the step's own local server (its Prefect home is removed after the run)
    print(json.dumps(out))


def measure(step: str, path: Path, prefect_home: Path) -> dict:
    """One step in a fresh process (its own Prefect home: its own local server, started by the warm-up flow)."""
    env = dict(os.environ, PREFECT_HOME=str(prefect_home / step))
    proc = subprocess.run(
        [sys.executable, __file__, "--child", step, str(path)], capture_output=True, text=True, env=env
    )
    if proc.returncode:
        raise SystemExit(f"{step} failed:\n{proc.stderr[-3000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"{step}: {json.dumps(out)} (1-min load {os.getloadavg()[0]:.1f})", file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=16)
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--encoding", default="protobuf", choices=("protobuf", "json"))
    ap.add_argument("--steps", default="decode,calibrate,fleet")
    ap.add_argument("--dir", type=Path, default=Path("/tmp/thermocal-bench"))
    ap.add_argument(
        "--repeat", type=_rounds, default=1, help="rounds of the steps, alternating; the table gives each step's median"
    )
    ap.add_argument("--child", nargs=2, metavar=("STEP", "PATH"))
    args = ap.parse_args()
    if args.child:
        child(args.child[0], Path(args.child[1]))
        return
    from pipeline.simulate.program import get_program

    hours = get_program("standard").timetable().duration_s / 3600
    args.dir.mkdir(parents=True, exist_ok=True)
    multi, singles = make(args.dir, args.units, args.rate_hz, args.encoding)
    load0 = os.getloadavg()
    rounds: list[dict[str, dict]] = []
    for _ in range(args.repeat):  # alternating: a slower spell of the shared machine falls on every step alike
        with tempfile.TemporaryDirectory(prefix="prefect-", dir=args.dir) as homes:
            rounds.append(
                {s: measure(s, singles if s == "fleet" else multi, Path(homes)) for s in args.steps.split(",")}
            )
    load1 = os.getloadavg()
    results = _medians(rounds)
    samples = results.get("decode", {}).get("samples") or args.units * int(hours * 3600 * args.rate_hz)
    decoded_gb = samples * 4 * 8 / 2**30
    floor = results.get("decode", {}).get("wall_s")
    floor_cpu = results.get("decode", {}).get("cpu_s")
    print(
        f"\n{args.units} units x {samples // args.units} voltmeter samples ({args.rate_hz:g} Hz, standard program "
        f"{hours:.1f} h), MCAP {args.encoding} {multi.stat().st_size / 1e9:.2f} GB; decoded samples "
        f"{decoded_gb:.2f} GB; 1-min load {load0[0]:.1f} at the start, {load1[0]:.1f} at the end; "
        f"{os.cpu_count()} CPUs\n"
    )
    print(
        "| step | units (pass) | wall s | CPU s | local server CPU s | peak RSS GB | peak / decoded | wall / decode | "
        "CPU / decode | chamber h per unit |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    n_units = args.units
    names = {
        "decode": f"decode the {n_units}-unit file (floor)",
        "floor-mcap": f"mcap library + frombuffer, the {n_units}-unit file",
        "calibrate": f"calibrate the {n_units}-unit file (flow)",
        "fleet": f"fleet of {n_units} single-unit runs (flow, 2 workers)",
    }
    for step, r in results.items():
        peak = r["peak_rss_gb"] + r.get("children_peak_sum_gb", 0.0)
        n = r.get("units", args.units)
        per_unit = hours / args.units if step != "fleet" else hours
        print(
            f"| {names[step]} | {n} ({r.get('passed', '-')}) | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
            f"{r.get('server_cpu_s', 0.0):.1f} | {peak:.2f} | "
            f"{peak / decoded_gb:.2f} | {r['wall_s'] / floor if floor else float('nan'):.2f} | "
            f"{r['cpu_s'] / floor_cpu if floor_cpu else float('nan'):.2f} | {per_unit:.2f} |"
        )
    if len(rounds) > 1 and "decode" in results:
        for step in results:
            if step != "decode":
                each = ", ".join(f"{r[step]['wall_s'] / r['decode']['wall_s']:.2f}" for r in rounds)
                print(f"\n{step} / decode in wall, round by round: {each}")
    print("\n" + json.dumps(results))


def _rounds(text: str) -> int:
    """``--repeat``: a whole number of rounds, at least one."""
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError("at least 1 round")
    return n


def _medians(rounds: list[dict[str, dict]]) -> dict[str, dict]:
    """Each step's figures over the rounds: the median of every number (counts: the lower median; one round: that
    round's)."""
    import statistics

    def median(values: list):
        if all(isinstance(v, int) for v in values):
            return statistics.median_low(values)
        return round(statistics.median(values), 3)

    out: dict[str, dict] = {}
    for step in rounds[0]:
        runs = [r[step] for r in rounds]
        out[step] = {k: median([r[k] for r in runs]) if isinstance(v, (int, float)) else v for k, v in runs[0].items()}
    return out


if __name__ == "__main__":
    main()
