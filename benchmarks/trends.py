"""``thermocal trends`` on a large registry, side by side with just listing and reading it.

    .venv/bin/python benchmarks/trends.py [--units 1000] [--versions 5] [--registry DIR] [--workers 2]
                                         [--read-workers N]

Writes (unless ``--registry`` names one already written by this script) a registry of ``--units`` simulated units
of seed 000's type with ``--versions`` passports each, 120 days apart, through the registry's one writing path
(:func:`pipeline.simulate.history.write_fleet`: signed, hash-chained; ``--workers`` processes, units split between
them), with two units drifting and one outlier planted. Then times (wall and CPU seconds, best of ``--repeat``):

- ``list+read``: the floor: list the units, read every version file's bytes and parse its JSON;
- ``verified read, cold cache``: every unit's versions after the registry's verification (the verification trends
  relies on: hashes, signature, parent link, content), as :func:`pipeline.passport.trends.read_fleet`
  (``--read-workers`` processes; default its own choice: one per CPU from 200 units), with an empty cache of
  verified files (:mod:`pipeline.passport.verified_cache`, a new temporary folder each time);
- ``verified read, warm cache``: the same again with the cache the cold read filled (what a second run reads);
- ``analyse``: drift, unsteady and outlier tests on what was read (:func:`pipeline.passport.trends.analyse`);
- ``trends``: the whole of :func:`pipeline.passport.trends.fleet_trends` (what the command runs), warm cache;
- ``thermocal trends --json``, the command itself (a new process: start, imports, read, analysis, output), first
  with an empty cache (a registry read for the first time, or after a trusted key or the checks changed), then again
  with the cache that run filled (every later run).

CPU seconds include the worker processes' (their start too) and the command's. Prints a markdown table, what was
found, and the machine's load average before and after (the machine may be shared).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import resource
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from pipeline.passport.registry import Registry
from pipeline.passport.trends import analyse, fleet_trends, read_fleet
from pipeline.passport.verified_cache import CACHE_ENV
from pipeline.simulate.history import FleetSpec, Plant, write_fleet

PLANTS = {
    "AU-0017": Plant(u0_rate_v_per_year=(1.2e-4, 0.0, 0.0)),
    "AU-0101": Plant(gain_rate_rel_per_year=(0.0, 0.0, 2e-4)),
    "AU-0333": Plant(u0_offset_v=(0.0, 0.06, 0.0)),
}


def _write(root: str, spec: FleetSpec, serials: list[str]) -> int:
    return sum(write_fleet(root, spec, only=set(serials)).values())


def make_registry(root: Path, units: int, versions: int, workers: int) -> float:
    """Write the registry (units split between ``workers`` spawned processes); returns the wall seconds."""
    spec = FleetSpec(units=units, versions=versions, plants=PLANTS)
    serials = spec.serials()
    chunks = [serials[i::workers] for i in range(workers)]
    t = time.perf_counter()
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        written = sum(pool.map(_write, [str(root)] * workers, [spec] * workers, chunks))
    assert written == units * versions, written
    return time.perf_counter() - t


def list_and_read(root: Path) -> int:
    reg = Registry(root)
    n = 0
    for unit in reg.units():
        for path in sorted(reg.unit_dir(unit).glob("v*.json")):
            json.loads(path.read_bytes())
            n += 1
    return n


def _cpu_s() -> float:
    """CPU seconds of this process and of its ended child processes (the read's worker processes)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def command(root: Path, cache: str) -> bytes:
    """``thermocal trends --registry root --json`` in a new process with the cache folder ``cache``; its output."""
    run = [sys.executable, "-c", "from flows.console import main; main()", "trends", "--registry", str(root), "--json"]
    return subprocess.run(run, env={**os.environ, CACHE_ENV: cache}, capture_output=True, check=True).stdout


def best(fn, repeat: int):
    walls, cpus, out = [], [], None
    for _ in range(repeat):
        w, c = time.perf_counter(), _cpu_s()
        out = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(_cpu_s() - c)
    return min(walls), min(cpus), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=1000)
    ap.add_argument("--versions", type=int, default=5)
    ap.add_argument("--registry", type=Path, default=None, help="a registry this script wrote before (reused)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument(
        "--read-workers", type=int, default=None, help="processes reading the registry (default: read_fleet's)"
    )
    args = ap.parse_args()
    root = args.registry or Path(tempfile.mkdtemp(prefix="trends-bench-")) / "registry"
    if not root.is_dir():
        wrote = make_registry(root, args.units, args.versions, args.workers)
        print(f"wrote {args.units} units x {args.versions} versions in {wrote:.0f} s ({root})", flush=True)
    from scipy import stats  # noqa: F401  (loaded before timing: the command loads it when it analyses)

    load_before = os.getloadavg()[0]
    rows = []
    w, c, n = best(lambda: list_and_read(root), args.repeat)
    rows.append(("list+read (floor)", w, c))

    def cold():
        os.environ[CACHE_ENV] = tempfile.mkdtemp(prefix="trends-bench-cache-")
        return read_fleet(Registry(root), workers=args.read_workers)

    w, c, fleet = best(cold, args.repeat)
    rows.append(("verified read, cold cache", w, c))
    w, c, warm = best(lambda: read_fleet(Registry(root), workers=args.read_workers), args.repeat)
    assert warm == fleet, "a warm read must give the cold read's histories"
    rows.append(("verified read, warm cache", w, c))
    w, c, _ = best(lambda: analyse(fleet), args.repeat)
    rows.append(("analyse", w, c))
    w, c, result = best(lambda: fleet_trends(root, workers=args.read_workers), args.repeat)
    rows.append(("trends (warm verified read + analyse)", w, c))
    caches: list[str] = []

    def first_run() -> bytes:
        caches.append(tempfile.mkdtemp(prefix="trends-bench-cache-"))
        return command(root, caches[-1])

    w, c, out = best(first_run, args.repeat)
    rows.append(("`thermocal trends --json`, empty cache", w, c))
    w, c, again = best(lambda: command(root, caches[-1]), args.repeat)
    assert again == out, "the command's output must not depend on the cache"
    rows.append(("`thermocal trends --json`, filled cache", w, c))
    load = f"load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after"
    print(f"\n{len(fleet)} units, {n} versions; best of {args.repeat}; {load}\n")
    print("| step | wall s | CPU s | x floor (wall) | x floor (CPU) |\n|---|---:|---:|---:|---:|")
    floor_w, floor_c = rows[0][1], rows[0][2]
    for name, w, c in rows:
        print(f"| {name} | {w:.2f} | {c:.2f} | {w / floor_w:.1f} | {c / floor_c:.1f} |")
    r = result.report
    print("\nfound:", {k: [(e["unit"], e["constant"]) for e in r[k]] for k in ("drifting", "unsteady", "outliers")})


if __name__ == "__main__":
    main()
