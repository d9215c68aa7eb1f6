"""Memory and time of ``thermocal inspect`` on the hostile inputs of issue 26 (item 3), side by side with the size
the file declares and the samples it decodes to, and with a clean run of the same command.

    .venv/bin/python benchmarks/memory_bounds.py [--cap-gb 4] [--out /tmp/thermocal-bounds]

Makes each input under ``--out`` (not in git; the sparse file takes no disk blocks), then runs ``thermocal inspect``
on it in a fresh child whose address space is capped with ``RLIMIT_AS`` (``--cap-gb``; 0: no cap) and reports the
child's peak RSS (``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` of a wrapper process that runs only that
command), its exit status, wall and CPU seconds and the first line of its stderr:

- ``declared-3GiB``: the issue's 837-byte MCAP whose zstd chunk declares 3 GiB uncompressed;
- ``lz4-1.1GB``: an MCAP whose 4.4 MB lz4 chunk expands to ~1.1 GB of valid messages;
- ``constant-104M``: 104 M identical voltmeter rows in ~2 MB of Parquet (3.3 GB decoded);
- ``zeros-8GB``: an MCAP cut after its header and extended with 8 GB of zeros (sparse);
- ``clean-10Hz``: sample_data's standard_short.mcap, the baseline of the command itself.

The machine's load average is printed with the table (wall seconds vary with it; CPU seconds much less).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

WRAPPER = r"""
import json, resource, subprocess, sys, time
cap = int(sys.argv[1])
def limit():
    if cap:
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
t0 = time.perf_counter()
p = subprocess.run(sys.argv[2:], preexec_fn=limit, capture_output=True, text=True)
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"rc": p.returncode, "wall_s": time.perf_counter() - t0, "cpu_s": ru.ru_utime + ru.ru_stime,
                  "peak_rss_bytes": ru.ru_maxrss * 1024, "stderr": p.stderr.strip().splitlines()[:1]}))
"""


def inputs(out: Path) -> list[tuple[str, Path, int, int]]:
    """(name, path, bytes the file declares its data expands to, bytes of decoded samples) of each input, made if
    missing."""
    from tests.io.hostile_runs import constant_rows_parquet, declared_chunk_mcap, lz4_chunk_mcap, zero_filled_mcap

    out.mkdir(parents=True, exist_ok=True)
    made = []
    p = out / "declared-3GiB.mcap"
    if not p.exists():
        declared_chunk_mcap(p, declared=3 << 30)
    made.append(("declared-3GiB", p, 3 << 30, 4 * 4 * 8))
    p = out / "lz4-1.1GB.mcap"
    if not p.exists():
        lz4_chunk_mcap(p, uncompressed=1_100_000_000)
    made.append(("lz4-1.1GB", p, 1_100_000_000, 0))
    p = out / "constant-104M"
    if not p.exists():
        constant_rows_parquet(p, rows=104_000_000, group=8 << 20)
    made.append(("constant-104M", p, 104_000_000 * 32, 104_000_000 * 32))
    p = out / "zeros-8GB.mcap"
    if not p.exists():
        zero_filled_mcap(p, size=8 << 30)
    made.append(("zeros-8GB", p, 8 << 30, 0))
    clean = REPO / "sample_data" / "standard_short.mcap"
    made.append(("clean-10Hz", clean, clean.stat().st_size, 0))
    return made


def on_disk(path: Path) -> int:
    files = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
    return sum(f.stat().st_blocks * 512 for f in files)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cap-gb", type=float, default=4.0, help="RLIMIT_AS of the command, GB (0: none)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/thermocal-bounds"))
    args = ap.parse_args()
    cap = int(args.cap_gb * (1 << 30))
    exe = str(Path(sys.executable).parent / "thermocal")
    rows = []
    for name, path, declared, _ in inputs(args.out):
        env = {**os.environ, "POLARS_MAX_THREADS": "2"}
        t0 = time.perf_counter()
        p = subprocess.run(
            [sys.executable, "-c", WRAPPER, str(cap), exe, "inspect", str(path)],
            capture_output=True,
            text=True,
            env=env,
        )
        r = json.loads(p.stdout)
        r.update(name=name, on_disk=on_disk(path), declared=declared, total_s=time.perf_counter() - t0)
        rows.append(r)
    print(f"load average {os.getloadavg()[0]:.1f}, RLIMIT_AS {args.cap_gb:g} GB (0: none)\n")
    print("| input | on disk | declared | exit | peak RSS | wall s | CPU s | stderr |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        line = (r["stderr"] or [""])[0]
        line = line if len(line) < 160 else line[:157] + "..."
        print(
            f"| {r['name']} | {r['on_disk'] / 1e6:.3g} MB | {r['declared'] / 1e9:.3g} GB | {r['rc']} | "
            f"{r['peak_rss_bytes'] / 1e6:.0f} MB | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {line} |"
        )


if __name__ == "__main__":
    main()
