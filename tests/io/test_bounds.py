"""Bounded resources (issue 26 item 3): the issue's hostile inputs end in one line and exit 2, quickly and without
allocating what the file declares, in a fresh ``thermocal inspect`` process whose address space is capped with
``RLIMIT_AS`` (4 GB: the command itself needs ~1.5 GB of it); only regular files are read (a FIFO is one line, and a
fleet skips it and says so). Memory figures: benchmarks/memory_bounds.py."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.errors import RunFormatError
from pipeline.io.limits import MAX_CHUNK_BYTES, ratio_limit
from pipeline.io.runs import read_run
from tests.io.hostile_runs import (
    constant_rows_parquet,
    declared_chunk_mcap,
    fifo_run,
    lz4_chunk_mcap,
    tiny_run,
    zero_filled_mcap,
)

EXE = str(Path(sys.executable).parent / "thermocal")
CAP_BYTES = 4 << 30


def inspect_capped(path: Path, cap: int = CAP_BYTES, timeout: float = 600.0) -> tuple[int, str, str, float]:
    """``thermocal inspect PATH`` in a child whose address space is capped at ``cap`` bytes: (exit status, stdout,
    stderr, seconds)."""

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    env = {**os.environ, "POLARS_MAX_THREADS": "2"}
    t0 = time.perf_counter()
    p = subprocess.run(
        [EXE, "inspect", str(path)], preexec_fn=limit, capture_output=True, text=True, timeout=timeout, env=env
    )
    return p.returncode, p.stdout, p.stderr, time.perf_counter() - t0


def _one_line(code: int, out: str, err: str, *fragments: str) -> None:
    assert code == 2 and out == "", (code, err[-2000:])
    assert err.count("\n") == 1 and err.startswith("thermocal: error: "), err[-2000:]
    for f in fragments:
        assert f in err, err


@pytest.mark.slow
def test_a_chunk_declaring_3_gib_is_refused_before_any_allocation(tmp_path):
    """The issue's 837-byte MCAP whose chunk declares 3 GiB: inspect allocated 3.25 GB before its error (under a
    4 GB cap: MemoryError, exit 3). Now the declared size is checked against what its zstd bytes can hold."""
    path = declared_chunk_mcap(tmp_path / "declared.mcap", declared=3 << 30)
    assert path.stat().st_size < 2000
    code, out, err, _ = inspect_capped(path)
    _one_line(code, out, err, "declares 3.22 GB uncompressed", "zstd", str(path))


@pytest.mark.slow
def test_an_lz4_chunk_beyond_the_chunk_limit_is_refused_unread(tmp_path):
    """The issue's lz4 chunk (4.4 MB expanding to ~1.1 GB: 2.3 GB of memory); here 1.2 MB expanding to 300 MB,
    beyond the chunk limit: refused from its header, in seconds, not decompressed."""
    path = lz4_chunk_mcap(tmp_path / "lz4.mcap", uncompressed=300 << 20)
    assert path.stat().st_size < 5 << 20
    code, out, err, seconds = inspect_capped(path)
    _one_line(code, out, err, "larger than this reader takes in one chunk", str(path))


def test_declared_sizes_against_what_the_codec_can_hold(tmp_path):
    """In process: a chunk declaring a little more than its codec can expand to is refused; the exact limits."""
    assert ratio_limit("zstd", 770) == 770 * 32768 and ratio_limit("lz4", 10) == 2550 and ratio_limit("", 5) == 5
    assert ratio_limit("brand-new-codec", 5) is None and MAX_CHUNK_BYTES == 256 << 20
    path = declared_chunk_mcap(tmp_path / "d.mcap", declared=786 * 32768 + 1)  # its zstd data: 786 bytes
    with pytest.raises(RunFormatError, match="more than that format can expand to"):
        read_run(path)


@pytest.mark.slow
def test_constant_rows_beyond_the_memory_cap_are_refused_from_the_footer(tmp_path):
    """The issue's 104 M constant rows in 1.9 MB of Parquet peaked at 11.1 GB (under a 4 GB cap: abort, exit 134).
    Here 40 M rows (1.3 GB decoded, more than a quarter of the 4 GB cap): refused from the footers, nothing
    decoded."""
    folder = constant_rows_parquet(tmp_path / "constant", rows=40_000_000, group=4 << 20)
    assert sum(f.stat().st_size for f in folder.iterdir()) < 20 << 20
    code, out, err, _ = inspect_capped(folder)
    _one_line(code, out, err, "1.28 GB of samples once decoded", "nothing was decoded", "voltmeter")


@pytest.mark.slow
def test_zero_filled_sparse_mcap_ends_at_the_zeros_at_once(tmp_path):
    """The issue: a zero-filled sparse MCAP cost ~20 s of CPU per GB, with no progress and a misleading "no footer".
    Now the first opcode-0 record ends the walk: 8 GB of zeros after the header is one line naming the zeros; with
    the samples before the zeros, the run is read with a warning (as a truncated file is)."""
    zeros = zero_filled_mcap(tmp_path / "zeros.mcap", size=8 << 30)
    t0 = time.process_time()
    with pytest.raises(RunFormatError) as info:
        read_run(zeros)
    assert time.process_time() - t0 < 5.0
    line = info.value.one_line()
    assert "opcode 0 record at byte" in line and "zeros" in line and "no 'run' metadata" in line
    kept = zero_filled_mcap(tmp_path / "kept.mcap", size=8 << 30, keep_data=True)
    run = read_run(kept)
    assert run.voltmeter.height == 20 and any("opcode 0 record" in w for w in run.warnings)


def test_only_regular_files_are_read(tmp_path, monkeypatch, capsys):
    """A FIFO where a run or a passport is expected hung inspect, fleet and serve forever; now one line (and a
    fleet skips it, saying so). Each call has a timeout: a hang fails the test."""
    from pipeline.calibrate.fleet import plan_fleet
    from pipeline.io.runs import write_run
    from tests.conftest import run_main

    inbox = tmp_path / "inbox"
    inbox.mkdir()
    fifo = fifo_run(inbox / "waiting.mcap")
    write_run(tiny_run(20, "AU-0903"), inbox / "good.mcap", "mcap")
    parquet = write_run(tiny_run(20, "AU-0904"), inbox / "pq", "parquet")
    (parquet / "chamber.parquet").unlink(missing_ok=True)
    os.mkfifo(parquet / "chamber.parquet")
    p = subprocess.run([EXE, "inspect", str(fifo)], capture_output=True, text=True, timeout=120)
    _one_line(p.returncode, p.stdout, p.stderr, "is a FIFO (named pipe), not a regular file: not read", str(fifo))
    with pytest.raises(RunFormatError, match="chamber.parquet: is a FIFO"):
        read_run(parquet)
    plan = plan_fleet(inbox, tmp_path / "reg")
    assert [s["why"] for s in plan.skipped if s["run"] == str(fifo)] == [
        "a FIFO (named pipe), not a regular file: not read"
    ]
    assert [g.unit for g in plan.groups] == ["AU-0903", "AU-0904"]  # (the Parquet run fails when it is read)
    passport = fifo_run(tmp_path / "passport.json")
    code, out, err = run_main(monkeypatch, capsys, "apply", str(passport), str(inbox / "good.mcap"), "--out", "x")
    _one_line(code, out, err, "is a FIFO (named pipe), not a regular file: not read")
