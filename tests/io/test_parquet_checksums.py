"""Parquet page checksums: thermocal writes a CRC-32 in every page and checks it on read; bit-rot is a one-line error
naming the file and the column, never silently different values."""

from __future__ import annotations

import random
import shutil

import pyarrow.parquet as pq
import pytest

from pipeline.errors import RunFormatError
from pipeline.io.parquet import verify_page_checksums
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.large import simulate_run

STREAMS = ("voltmeter", "au_temperature", "chamber", "fixture")


@pytest.fixture(scope="module")
def parquet_run(tmp_path_factory):
    run = simulate_run(SimConfig(program="short", rate_hz=5.0, seed=3)).run
    return write_run(run, tmp_path_factory.mktemp("pq") / "run", "parquet")


def test_every_page_has_a_checksum_that_pyarrow_accepts(parquet_run):
    for stream in STREAMS:
        f = parquet_run / f"{stream}.parquet"
        meta = pq.ParquetFile(f).metadata
        assert verify_page_checksums(f, stream) >= meta.num_row_groups * meta.num_columns
        # the peer's check (pyarrow's own verifying reader) agrees that the checksums are right
        pq.read_table(f, page_checksum_verification=True)


def test_random_bit_flips_are_caught_naming_file_and_column(parquet_run, tmp_path):
    original = read_run(parquet_run)
    rng = random.Random(15)
    caught = 0
    flips = 20
    for k in range(flips):
        copy = tmp_path / f"flip{k}"
        shutil.copytree(parquet_run, copy)
        f = copy / "voltmeter.parquet"
        data = bytearray(f.read_bytes())
        pos = rng.randrange(4, len(data) - 4)  # anywhere in the file but the magic bytes
        data[pos] ^= 1 << rng.randrange(8)
        f.write_bytes(bytes(data))
        try:
            run = read_run(copy)
        except RunFormatError as exc:
            msg = str(exc)
            assert "\n" not in msg and str(f) in msg and "voltmeter" in msg, msg
            caught += 1
            continue
        # a flip the checksums cannot see (e.g. in unused footer statistics) must not change any value
        assert run.voltmeter.equals(original.voltmeter), f"flip at byte {pos} changed values silently"
    assert caught >= flips - 2, f"only {caught} of {flips} flips were caught"


def test_a_corrupted_page_names_the_column(parquet_run, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(parquet_run, copy)
    f = copy / "voltmeter.parquet"
    col = pq.ParquetFile(f).metadata.row_group(0).column(2)  # 'uy'
    data = bytearray(f.read_bytes())
    data[col.data_page_offset + col.total_compressed_size - 5] ^= 0x10  # inside the page's data
    f.write_bytes(bytes(data))
    with pytest.raises(RunFormatError, match=r"column 'uy': page checksum mismatch") as exc:
        read_run(copy)
    assert str(f) in str(exc.value) and "rows 0.." in str(exc.value)
    with pytest.raises(OSError, match="CRC"):  # pyarrow's own check agrees
        pq.read_table(f, page_checksum_verification=True)
