"""The benchmarks' process pools start their children by spawn: a child forked after polars/pyarrow have started
their thread pools in the parent (the parent had just written Parquet) waited forever in a futex at 0 % CPU
(benchmarks/cli_latency.py's fleet step, 8 min with an empty output folder)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _modules_in_child() -> list[str]:
    """Run in a pool's child: which of the parent's thread-pool libraries it holds before importing anything."""
    return [m for m in ("polars", "pyarrow") if m in sys.modules]


def _fleet_throughput():
    if str(BENCHMARKS) not in sys.path:  # by name, so that a spawned child can unpickle its functions
        sys.path.insert(0, str(BENCHMARKS))
    import fleet_throughput

    return fleet_throughput


@pytest.mark.slow  # process pools
def test_benchmark_pools_spawn_after_parquet_was_written(tmp_path):
    import polars as pl

    pl.DataFrame({"t_ns": list(range(100_000))}).write_parquet(tmp_path / "x.parquet")  # polars' threads run
    ft = _fleet_throughput()
    with ft.process_pool(2) as pool:
        held = [pool.submit(_modules_in_child).result(timeout=120) for _ in range(2)]
    assert held == [[], []]  # a forked child would hold the parent's polars and pyarrow
    # the cli_latency fleet step itself, two units of the short program at a low rate, on two processes
    paths = ft.make_fleet(tmp_path / "fleet", 2, 0.5, "short", 2)
    assert [Path(p).name for p in paths] == ["AU-0001.mcap", "AU-0002.mcap"]
    assert all(Path(p).stat().st_size > 0 for p in paths)
