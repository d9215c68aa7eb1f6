"""What checking Parquet page checksums costs on read, side by side with the decode it protects.

    .venv/bin/python benchmarks/parquet_checksums.py [--rate-hz 100] [--repeat 3]

Writes a standard-program run at ``--rate-hz`` as a Parquet run directory (thermocal's writer: a CRC-32 in every
page) into a temporary folder, then times, per stream file and in total (best of ``--repeat``, wall and CPU):

- ``verify``: :func:`pipeline.io.parquet.verify_page_checksums` (page headers, ``zlib.crc32`` over the mapped pages);
- ``decode``: ``polars.read_parquet`` of the same file (the decode thermocal's reader does after the check);
- ``pyarrow+crc``: the peer, ``pyarrow.parquet.read_table(page_checksum_verification=True)`` (decode and check).

Prints a markdown table and the machine's load average (the machine may be shared: CPU seconds vary less).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from functools import partial
from pathlib import Path

import polars as pl
import pyarrow.parquet as pq

from pipeline.io.parquet import verify_page_checksums
from pipeline.io.runs import write_run
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.large import simulate_run


def best(fn, repeat: int) -> tuple[float, float]:
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return min(walls), min(cpus)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="thermocal-crc-") as tmp:
        run = simulate_run(SimConfig(rate_hz=args.rate_hz)).run
        d = write_run(run, Path(tmp) / "run", "parquet")
        del run
        print(f"standard program at {args.rate_hz:g} Hz; load average {os.getloadavg()[0]:.2f}\n")
        print("| file | MB | pages | verify s (CPU) | decode s (CPU) | verify / decode | pyarrow+crc s (CPU) |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        total = [0.0] * 6
        for f in sorted(d.glob("*.parquet")):
            pages = verify_page_checksums(f)
            v = best(partial(verify_page_checksums, f), args.repeat)
            r = best(partial(pl.read_parquet, f), args.repeat)
            p = best(partial(pq.read_table, f, page_checksum_verification=True), args.repeat)
            for k, x in enumerate((*v, *r, *p)):
                total[k] += x
            mb = f.stat().st_size / 1e6
            print(
                f"| {f.name} | {mb:.1f} | {pages} | {v[0]:.3f} ({v[1]:.3f}) | {r[0]:.3f} ({r[1]:.3f}) | "
                f"{v[0] / r[0]:.2f} | {p[0]:.3f} ({p[1]:.3f}) |"
            )
        print(
            f"| all | | | {total[0]:.3f} ({total[1]:.3f}) | {total[2]:.3f} ({total[3]:.3f}) | "
            f"{total[0] / total[2]:.2f} | {total[4]:.3f} ({total[5]:.3f}) |"
        )


if __name__ == "__main__":
    main()
