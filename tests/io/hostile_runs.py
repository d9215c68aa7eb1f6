"""Hostile runs of issue 26 item 3, made on demand (none is stored): files whose declared sizes would make a reader
allocate far more than the file holds, and files that are not regular files. Used by tests/io/test_bounds.py and
benchmarks/memory_bounds.py.

- :func:`declared_chunk_mcap`: a valid small MCAP whose one zstd chunk declares ``declared`` bytes uncompressed
  (the issue's 837-byte file declaring 3 GiB);
- :func:`lz4_chunk_mcap`: an MCAP whose one lz4 chunk holds ``uncompressed`` bytes of repeated valid messages
  (the issue's 4.4 MB chunk that decompressed to ~1.1 GB);
- :func:`constant_rows_parquet`: a Parquet run whose voltmeter holds ``rows`` constant rows (the issue's 104 M rows
  in 1.9 MB);
- :func:`zero_filled_mcap`: an MCAP cut after its header (or after ``keep`` bytes) and extended with zeros to
  ``size`` bytes, sparse (a logger's preallocated file);
- :func:`fifo_run`: a FIFO named like a run.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.mcap import MAGIC, write_mcap
from pipeline.run import Run, RunMeta, make_frame

_CHUNK, _FOOTER, _DATA_END = 6, 2, 15


def tiny_run(n: int = 20, unit: str = "AU-0901") -> Run:
    t = 1_793_491_200_000_000_000 + np.arange(n, dtype=np.int64) * 1_000_000_000
    odd = 1e-5 * (np.arange(n) % 2)  # V: every other sample differs (one value throughout is a dead channel)
    volt = make_frame("voltmeter", {"t_ns": t, "ux": odd, "uy": -odd, "uz": -0.55 + odd})
    temp = make_frame("au_temperature", {"t_ns": t, "temp_c": np.full(n, 20.0)})
    return Run(RunMeta(unit_serial=unit, run_id=f"hostile-{unit}"), volt, temp)


def _records(data: bytes, start: int):
    """(opcode, record offset, body offset, end) of the top-level records after the magic."""
    pos = start
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        yield op, pos, pos + 9, pos + 9 + length
        if op == _FOOTER:
            return
        pos += 9 + length


def declared_chunk_mcap(path: Path, declared: int = 3 << 30) -> Path:
    """A valid small MCAP (no summary) whose chunk's uncompressed_size field says ``declared``."""
    write_mcap(tiny_run(4), path, summary=False, block_samples=4)
    data = bytearray(path.read_bytes())
    op, pos, body, _ = next(r for r in _records(bytes(data), len(MAGIC)) if r[0] == _CHUNK)
    struct.pack_into("<Q", data, body + 16, declared)
    path.write_bytes(bytes(data))
    return path


def lz4_chunk_mcap(path: Path, uncompressed: int = 300 << 20) -> Path:
    """An MCAP whose single lz4 chunk holds ``uncompressed`` bytes of one valid voltmeter message repeated,
    compressed as it is built (the test process never holds the uncompressed chunk)."""
    import lz4.frame

    write_mcap(tiny_run(4), path, summary=False, block_samples=4, compression="lz4")
    data = path.read_bytes()
    recs = list(_records(data, len(MAGIC)))
    op, pos, body, end = next(r for r in recs if r[0] == _CHUNK)
    t0, t1, size, _crc = struct.unpack_from("<QQQI", data, body)
    n = struct.unpack_from("<I", data, body + 28)[0]
    comp_end = body + 32 + n
    (data_len,) = struct.unpack_from("<Q", data, comp_end)
    inner = lz4.frame.decompress(data[comp_end + 8 : comp_end + 8 + data_len])
    # the chunk's own records: schema, channel, message(s); repeat its messages to the size asked
    records = list(_records(inner, 0))
    messages = b"".join(inner[p:e] for o, p, _, e in records if o == 5)
    head = b"".join(inner[p:e] for o, p, _, e in records if o != 5)  # schemas and channels first
    reps = max(1, (uncompressed - len(head)) // len(messages))
    block = messages * max(1, (1 << 20) // len(messages))
    comp = lz4.frame.LZ4FrameCompressor()
    out, crc, total = [comp.begin(), comp.compress(head)], zlib.crc32(head), len(head)
    left = reps * len(messages)
    while left > 0:
        piece = block if left >= len(block) else messages * (left // len(messages))
        out.append(comp.compress(piece))
        crc, total, left = zlib.crc32(piece, crc), total + len(piece), left - len(piece)
    out.append(comp.flush())
    compressed = b"".join(out)
    chunk_body = (
        struct.pack("<QQQI", t0, t1, total, crc)
        + struct.pack("<I", 3)
        + b"lz4"
        + struct.pack("<Q", len(compressed))
        + compressed
    )
    rest = data[end:]
    path.write_bytes(data[:pos] + struct.pack("<BQ", _CHUNK, len(chunk_body)) + chunk_body + rest)
    return path


def constant_rows_parquet(folder: Path, rows: int = 104_000_000, group: int = 1 << 20) -> Path:
    """A Parquet run directory whose voltmeter holds ``rows`` identical rows (time included: the issue's constant
    rows, which compress to almost nothing), written a row group at a time (the test process holds one group)."""
    import orjson

    folder.mkdir(parents=True, exist_ok=True)
    t0 = 1_793_491_200_000_000_000
    schema = pa.schema([("t_ns", pa.int64()), ("ux", pa.float64()), ("uy", pa.float64()), ("uz", pa.float64())])
    const = {c: pa.array(np.full(group, v)) for c, v in (("ux", 0.0), ("uy", 0.0), ("uz", -0.55))}
    with pq.ParquetWriter(folder / "voltmeter.parquet", schema, compression="zstd") as w:
        for a in range(0, rows, group):
            n = min(group, rows - a)
            t = pa.array(np.full(n, t0, dtype=np.int64))
            w.write_table(pa.table({"t_ns": t, **{c: v.slice(0, n) for c, v in const.items()}}, schema=schema))
    span_s = rows // 1000 + 1
    tt = t0 + np.arange(span_s, dtype=np.int64) * 1_000_000_000
    pq.write_table(pa.table({"t_ns": tt, "temp_c": np.full(span_s, 20.0)}), folder / "au_temperature.parquet")
    (folder / "run.json").write_bytes(orjson.dumps({"unit_serial": "AU-0902", "run_id": "constant-rows"}))
    return folder


def zero_filled_mcap(path: Path, size: int, keep_data: bool = False) -> Path:
    """An MCAP cut after its header (``keep_data``: after its last chunk, so its samples are there) and extended
    with zeros to ``size`` bytes: sparse, no disk blocks for the zeros."""
    write_mcap(tiny_run(20), path, summary=False, block_samples=4)
    data = path.read_bytes()
    recs = list(_records(data, len(MAGIC)))
    cut = next(e for o, _, _, e in recs if o == 1) if not keep_data else max(e for o, _, _, e in recs if o == _CHUNK)
    with open(path, "r+b") as f:
        f.truncate(cut)
        f.truncate(size)
    return path


def fifo_run(path: Path) -> Path:
    os.mkfifo(path)
    return path
