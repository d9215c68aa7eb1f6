"""Ingest and calibration of a 1 kHz standard-program run (about 59 M samples), side by side with the floor.

    .venv/bin/python benchmarks/ingest_1khz.py [--rate-hz 1000] [--repeat 2] [--only parquet,mcap-json,...]
                                               [--steps floor,ingest,calibrate] [--flow] [--out benchmarks/out]

Makes the run first if it is missing (:mod:`make_runs`: Parquet, MCAP with JSON blocks, MCAP with protobuf blocks in
zstd and in lz4 chunks; a few minutes at 1 kHz), then measures each step in a fresh Python process, so that every
peak memory figure (``ru_maxrss``, which sees numpy and polars memory and mapped file pages) belongs to that step:

- the floor of each layout: ``pyarrow.parquet.read_table`` of the run's Parquet files; for MCAP the ``mcap``
  library's message iteration plus the plainest decode of each message (``orjson.loads`` and ``numpy.asarray`` per
  column for JSON, ``numpy.frombuffer`` of the packed fields for protobuf) and one concatenation per column;
- thermocal's ingest (``pipeline.io.runs.read_run``);
- the whole calibration without Prefect: ingest, segmentation and averaging (``observe_run``), fit, verification,
  and writing the passport into a fresh registry (``pipeline.calibrate.publish.publish``: hashes the input, draws the
  figure);
- with ``--flow``, the same through the Prefect flow (``flows.calibrate.run_calibrate``) after a warm-up flow has
  started Prefect, so that the figure does not include Prefect's start-up.

Prints a markdown table: wall and CPU seconds, throughput, peak RSS against the decoded samples (8 bytes per
number), and the ratio to the layout's floor. The machine's load average is printed with it: on a shared machine
the wall times vary with it (CPU seconds much less).
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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from make_runs import OUT, make_runs  # noqa: E402

RUN_TOPICS = ("/voltmeter", "/au/temperature", "/chamber", "/fixture")


# --- measured steps (each in a fresh process) -------------------------------------------------------------------


def floor_parquet(path: Path) -> dict:
    import pyarrow.parquet as pq

    tables = {f.stem: pq.read_table(f) for f in sorted(path.glob("*.parquet"))}
    return {
        "samples": tables["voltmeter"].num_rows,
        "numbers": _numbers({s: (t.num_rows, t.num_columns) for s, t in tables.items()}),
    }


def floor_mcap(path: Path) -> dict:
    """``mcap`` library iteration plus the plainest decode of the message encoding; one concatenation per column."""
    import numpy as np
    import orjson
    from mcap.reader import make_reader

    parts: dict[str, dict[str, list]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=list(RUN_TOPICS)):
            if channel.topic == "/fixture":
                continue
            cols = parts.setdefault(channel.topic, {})
            if channel.message_encoding == "json":
                for name, values in orjson.loads(message.data).items():
                    cols.setdefault(name, []).append(np.asarray(values))
            else:
                for name, values in _packed_fields(message.data, np):
                    cols.setdefault(name, []).append(values)
    out = {topic: {name: np.concatenate(a) for name, a in cols.items()} for topic, cols in parts.items()}
    rows = {topic: len(next(iter(cols.values()))) for topic, cols in out.items()}  # (JSON: by key, protobuf: number)
    return {"samples": rows["/voltmeter"], "numbers": _numbers({t: (rows[t], len(c)) for t, c in out.items()})}


def _packed_fields(data: bytes, np):
    """(field number, array) of a protobuf block: [1-byte tag][varint length][8-byte values] repeated."""
    p, n = 0, len(data)
    while p < n:
        tag = data[p]
        length, shift, p = 0, 0, p + 1
        while True:
            b = data[p]
            p += 1
            length |= (b & 0x7F) << shift
            shift += 7
            if b < 0x80:
                break
        yield tag >> 3, np.frombuffer(data, dtype="<i8" if tag >> 3 == 1 else "<f8", count=length // 8, offset=p)
        p += length


def ingest(path: Path) -> dict:
    from pipeline.io.runs import read_run

    run = read_run(path)
    return _run_counts(run)


def calibrate(path: Path) -> dict:
    """The calibration steps of the flow, without Prefect; each step timed."""
    from pipeline.calibrate import tilt
    from pipeline.calibrate.publish import publish
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.io.runs import read_run

    settings = CalibrationSettings()
    stages = {}
    t = time.perf_counter()
    run = read_run(path)
    stages["ingest"] = _lap(t)
    t = time.perf_counter()
    observed = tilt.observe(run, settings)
    stages["segment"] = _lap(t)
    t = time.perf_counter()
    result = tilt.calibrate_observed([observed], settings)
    stages["fit+verify"] = _lap(t)
    t = time.perf_counter()
    with tempfile.TemporaryDirectory() as registry:
        publish(registry, result, input_paths=[str(path)], settings=settings)
    stages["write"] = _lap(t)
    return {**_run_counts(run), "stages": stages, "status": result.status, "plateaus": len(result.fit.per_plateau)}


def flow(path: Path) -> dict:
    """The Prefect calibrate flow on the run, timed after a trivial warm-up flow has started Prefect."""
    from prefect import flow as prefect_flow

    from flows.calibrate import run_calibrate
    from pipeline.calibrate.settings import CalibrationSettings

    t = time.perf_counter()
    prefect_flow(name="warm-up")(lambda: None)()
    warm_up = _lap(t)
    _start_clock()
    with tempfile.TemporaryDirectory() as registry:
        result = run_calibrate([str(path)], registry, CalibrationSettings())
    return {"samples": None, "status": result["status"], "prefect_warm_up_s": warm_up}


STEPS = {"floor": None, "ingest": ingest, "calibrate": calibrate, "flow": flow}
_CLOCK: dict = {}


def _start_clock() -> None:
    """(Re)start the wall and CPU clocks of the step (a step may exclude its set-up)."""
    _CLOCK.update(wall=time.perf_counter(), usage=resource.getrusage(resource.RUSAGE_SELF))


def _lap(t: float) -> float:
    return round(time.perf_counter() - t, 3)


def _numbers(shapes: dict[str, tuple[int, int]]) -> int:
    return sum(rows * cols for rows, cols in shapes.values())


def _run_counts(run) -> dict:
    numeric = {s: (df.height, sum(1 for c in df.columns if c != "position")) for s, df in run.streams().items()}
    return {"samples": run.voltmeter.height, "numbers": _numbers(numeric)}


def child(step: str, layout: str, path: Path) -> None:
    """Run one step in this (fresh) process and print its figures as one JSON line."""
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    _start_clock()
    if step == "floor":
        out = floor_parquet(path) if layout == "parquet" else floor_mcap(path)
    else:
        out = STEPS[step](path)
    wall = time.perf_counter() - _CLOCK["wall"]
    r0, r1 = _CLOCK["usage"], resource.getrusage(resource.RUSAGE_SELF)
    out.update(
        wall_s=round(wall, 3),
        cpu_s=round(r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime, 2),
        sys_s=round(r1.ru_stime - r0.ru_stime, 2),
        peak_rss_mb=r1.ru_maxrss // 1024,
        base_rss_mb=base_rss // 1024,
    )
    print(json.dumps(out))


# --- driver -------------------------------------------------------------------------------------------------------


def measure(step: str, layout: str, path: Path, env: dict) -> dict:
    """One fresh-process run of one step."""
    proc = subprocess.run(
        [sys.executable, __file__, "--child", step, layout, str(path)], env=env, capture_output=True, text=True
    )
    if proc.returncode:
        raise SystemExit(f"{step} {layout} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def table(results: list[tuple[str, str, dict]]) -> str:
    floors = {layout: r for step, layout, r in results if step == "floor"}
    lines = [
        "| layout | step | wall s | CPU s (sys) | M samples/s | peak RSS GB | peak / decoded | wall / floor |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for step, layout, r in results:
        floor = floors.get(layout)
        numbers = r.get("numbers") or (floor or {}).get("numbers")
        samples = r.get("samples") or (floor or {}).get("samples")
        rate = f"{samples / r['wall_s'] / 1e6:.1f}" if samples else ""
        decoded = f"{r['peak_rss_mb'] * 2**20 / (8 * numbers):.2f}" if numbers else ""
        ratio = f"{r['wall_s'] / floor['wall_s']:.2f}" if floor and step != "floor" else ""
        name = {
            "floor": "floor",
            "ingest": "ingest (read_run)",
            "calibrate": "calibration, no Prefect",
            "flow": "calibrate flow (Prefect warm)",
        }[step]
        lines.append(
            f"| {layout} | {name} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} ({r['sys_s']:.1f}) | {rate} | "
            f"{r['peak_rss_mb'] / 1024:.2f} | {decoded} | {ratio} |"
        )
        if "stages" in r:
            lines.append(
                "| | &nbsp;&nbsp;stages | " + ", ".join(f"{k} {v:.1f}" for k, v in r["stages"].items()) + " | | | | | |"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--child", nargs=3, metavar=("STEP", "LAYOUT", "PATH"), help=argparse.SUPPRESS)
    ap.add_argument("--rate-hz", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument(
        "--repeat", type=int, default=2, help="runs of floor and ingest, alternating (the fastest of each is shown)"
    )
    ap.add_argument("--only", default="parquet,mcap-json,mcap-protobuf,mcap-protobuf-lz4", help="layouts to measure")
    ap.add_argument("--steps", default="floor,ingest,calibrate", help="steps to measure (also: flow)")
    ap.add_argument("--flow", action="store_true", help="also measure the Prefect flow (Parquet only)")
    args = ap.parse_args()
    if args.child:
        step, layout, path = args.child
        child(step, layout, Path(path))
        return
    paths = make_runs(args.rate_hz, args.out)
    env = dict(
        os.environ,
        PREFECT_HOME=os.environ.get("PREFECT_HOME", str(args.out / "prefect-home")),
        PREFECT_SERVER_ANALYTICS_ENABLED="false",
        DO_NOT_TRACK="1",
    )
    steps = args.steps.split(",")
    results = []
    load = [os.getloadavg()[0]]
    for layout in args.only.split(","):
        # floor and ingest alternate, so that both see the same machine load; the fastest of each is kept
        best: dict[str, dict] = {}
        for k in range(args.repeat):
            for step in steps:
                if k and step not in ("floor", "ingest"):
                    continue
                res = measure(step, layout, paths[layout], env)
                print(f"  {layout} {step}: {res}", file=sys.stderr)
                load.append(os.getloadavg()[0])
                if step not in best or res["wall_s"] < best[step]["wall_s"]:
                    best[step] = res
        results += [(step, layout, best[step]) for step in steps]
    if args.flow:
        results.append(("flow", "parquet", measure("flow", "parquet", paths["parquet"], env)))
        load.append(os.getloadavg()[0])
    samples = max(r.get("samples") or 0 for _, _, r in results)
    print(
        f"\n{args.rate_hz} Hz standard run, {samples:,} voltmeter samples; "
        f"{os.cpu_count()} CPUs, 1-min load average during the runs {min(load):.1f}-{max(load):.1f}\n"
    )
    print(table(results))


if __name__ == "__main__":
    main()
