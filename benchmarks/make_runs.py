"""Make the benchmark runs: one simulated standard-program run written as Parquet, MCAP with JSON blocks, MCAP with
protobuf blocks, and MCAP with protobuf blocks in lz4 chunks instead of zstd (the same samples in all four).

    .venv/bin/python benchmarks/make_runs.py [--rate-hz 1000] [--out benchmarks/out] [--force]

At 1 kHz the run has about 59 M voltmeter samples (1.9 GB in memory); it is simulated in time chunks
(:func:`pipeline.simulate.large.simulate_chunked`) and takes a few minutes to make. Files that exist are kept
(``--force`` remakes them). ``benchmarks/out/`` is not committed.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"
#: file name (name.format(rate=...)), format and write_run options of each layout
LAYOUTS = {
    "parquet": ("std_{rate}hz_parquet", "parquet", {}),
    "mcap-json": ("std_{rate}hz_json.mcap", "mcap", {"encoding": "json"}),
    "mcap-protobuf": ("std_{rate}hz_protobuf.mcap", "mcap", {"encoding": "protobuf"}),
    "mcap-protobuf-lz4": ("std_{rate}hz_protobuf_lz4.mcap", "mcap", {"encoding": "protobuf", "compression": "lz4"}),
}


def run_paths(rate_hz: int, out: Path = OUT) -> dict[str, Path]:
    """The benchmark run of each layout (:data:`LAYOUTS`) at ``rate_hz``."""
    return {layout: out / name.format(rate=rate_hz) for layout, (name, _, _) in LAYOUTS.items()}


def make_runs(rate_hz: int, out: Path = OUT, force: bool = False, log=print) -> dict[str, Path]:
    """Simulate the standard program at ``rate_hz`` (seed 0, no effects) and write the missing layouts."""
    paths = run_paths(rate_hz, out)
    missing = {k: p for k, p in paths.items() if force or not p.exists()}
    if not missing:
        return paths
    from pipeline.io.runs import write_run
    from pipeline.simulate.chamber import SimConfig
    from pipeline.simulate.large import simulate_chunked

    t0 = time.perf_counter()
    run = simulate_chunked(SimConfig(rate_hz=float(rate_hz))).run
    log(f"simulated {run.voltmeter.height:,} voltmeter samples at {rate_hz} Hz in {time.perf_counter() - t0:.0f} s")
    for layout, path in missing.items():
        t0 = time.perf_counter()
        _, fmt, opts = LAYOUTS[layout]
        write_run(run, path, fmt, **opts)
        size = sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() else path.stat().st_size
        log(f"wrote {path} ({size / 1e9:.2f} GB) in {time.perf_counter() - t0:.0f} s")
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate-hz", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--force", action="store_true", help="remake files that exist")
    args = ap.parse_args()
    make_runs(args.rate_hz, args.out, args.force)


if __name__ == "__main__":
    main()
