"""Run file I/O: MCAP and Parquet round trips, files without summary, truncated/corrupt/mismatched files."""

from __future__ import annotations

import itertools
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import orjson
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from pipeline.errors import RunFormatError
from pipeline.io.mcap import MAGIC, SCHEMA_NAMES, TOPICS, read_mcap, write_mcap
from pipeline.io.parquet import read_parquet_run, write_parquet_run
from pipeline.io.runs import read_run, run_format, write_run
from pipeline.run import STREAM_COLUMNS, Run, RunMeta, make_frame
from tests.conftest import DATA

T0_NS = 1_793_491_200_000_000_000  # 2026-11-01T00:00:00Z
META = RunMeta(
    unit_serial="AU-0007",
    run_id="2026-11-01-ch2-AU-0007",
    station="ch2",
    fixture="tilt-6",
    normal_temp_c=20.0,
    g_local_mps2=9.81234,
    started_utc="2026-11-01T00:00:00Z",
    nominal_gain_v_per_g=-0.55,
    extra={"operator": "Zoë"},
)


def make_run(n: int = 5000, seed: int = 0, optional: bool = True) -> Run:
    """A run of random values: 10 Hz voltmeter with awkward floats (NaN, -0.0, subnormal, the largest a sample
    may be: beyond it a value is treated as missing, pipeline.io.checks.PHYSICAL_RANGE), 1 Hz streams."""
    rng = np.random.default_rng(seed)
    t_v = T0_NS + np.arange(n, dtype=np.int64) * 100_000_000 + rng.integers(0, 1000, n)
    u = rng.normal(0.0, 0.6, (n, 3)) * 10.0 ** rng.uniform(-8, 2, (n, 3))
    u[[3, 50, 51], 0] = np.nan
    u[7] = (-0.0, 5e-324, np.nextafter(1e6, 0.0))
    m = n // 10
    t_1 = T0_NS + np.arange(m, dtype=np.int64) * 1_000_000_000
    temp = 20.0 + np.cumsum(rng.normal(0.0, 0.5, m))  # a thermosensor's walk (white noise of 30 C reads as glitches)
    temp[2] = np.nan
    frames = dict(
        voltmeter=make_frame("voltmeter", {"t_ns": t_v, "ux": u[:, 0], "uy": u[:, 1], "uz": u[:, 2]}),
        au_temperature=make_frame("au_temperature", {"t_ns": t_1, "temp_c": temp}),
    )
    if optional:
        frames["chamber"] = make_frame(
            "chamber", {"t_ns": t_1, "setpoint_c": np.round(temp, 0), "air_c": rng.normal(20.0, 30.0, m)}
        )
        k = max(2, n // 500)
        frames["fixture"] = make_frame(
            "fixture",
            {
                "t_ns": np.sort(rng.choice(t_v, k, replace=False)),
                "position": rng.choice(["TP1", "TP4", "VP3", "MOVING"], k),
            },
        )
    return Run(meta=META, **frames)


def assert_same_run(a: Run, b: Run) -> None:
    """Bit-exact equality of every stream (floats compared as bit patterns) and of the metadata."""
    assert a.meta == b.meta
    assert list(a.streams()) == list(b.streams())
    for name, df in a.streams().items():
        other = b.stream(name)
        assert other.schema == pl.Schema(STREAM_COLUMNS[name]), name
        assert df.height == other.height, name
        for col, dtype in STREAM_COLUMNS[name].items():
            x, y = df[col].to_numpy(), other[col].to_numpy()
            if dtype == pl.Float64:
                np.testing.assert_array_equal(x.view(np.int64), y.view(np.int64), err_msg=f"{name}.{col}")
            else:
                np.testing.assert_array_equal(x, y, err_msg=f"{name}.{col}")


# --- hand-made MCAP files ---------------------------------------------------------------------------------------


def write_raw_mcap(
    path: Path,
    messages: list[tuple[str, int, bytes]],
    meta: dict[str, str] | None,
    encoding: str = "json",
    **writer_opts,
) -> Path:
    """An MCAP file with the given (topic, log_time, data) messages, written with the mcap library."""
    with open(path, "wb") as f:
        w = Writer(f, **writer_opts)
        w.start()
        channels = {}
        for topic in dict.fromkeys(t for t, _, _ in messages):
            stream = next((s for s, tp in TOPICS.items() if tp == topic), None)
            schema = w.register_schema(SCHEMA_NAMES.get(stream, "other.Thing"), "jsonschema", b"{}")
            channels[topic] = w.register_channel(topic, encoding, schema)
        if meta is not None:
            w.add_metadata("run", meta)
        for topic, t, data in messages:
            w.add_message(channels[topic], t, data, t)
        w.finish()
    return path


def run_messages(n_blocks: int = 3, block: int = 10) -> list[tuple[str, int, bytes]]:
    """Valid voltmeter and temperature blocks."""
    out = []
    for k in range(n_blocks):
        t = T0_NS + (k * block + np.arange(block, dtype=np.int64)) * 100_000_000
        v = np.linspace(-1, 1, block)
        out.append(
            (
                "/voltmeter",
                int(t[0]),
                orjson.dumps({"t_ns": t, "ux": v, "uy": v, "uz": v}, option=orjson.OPT_SERIALIZE_NUMPY),
            )
        )
        out.append(("/au/temperature", int(t[0]), orjson.dumps({"t_ns": [int(t[0])], "temp_c": [20.0 + k]})))
    return out


def expect_error(path: Path, *fragments: str) -> str:
    with pytest.raises(RunFormatError) as info:
        read_run(path)
    text = str(info.value)
    assert str(path) in text
    for fragment in fragments:
        assert fragment in text, text
    assert "\n" not in text
    return text


# --- round trips ------------------------------------------------------------------------------------------------


def test_mcap_parquet_round_trip_is_bit_exact(tmp_path):
    run = make_run()
    mcap_path = write_run(run, tmp_path / "run.mcap", block_samples=97, chunk_size=20_000)
    first = read_run(mcap_path)
    assert first.warnings == []
    assert first.source == str(mcap_path)
    assert_same_run(run, first)
    assert np.isnan(first.voltmeter["ux"][3]) and np.signbit(first.voltmeter["ux"][7])
    assert first.voltmeter["uy"][7] == 5e-324

    pq_path = write_run(first, tmp_path / "run_parquet", fmt="parquet")
    second = read_run(pq_path)
    assert second.warnings == []
    assert_same_run(first, second)
    assert orjson.loads((pq_path / "run.json").read_bytes()) == META.to_strings()
    # ... and back to MCAP again.
    assert_same_run(run, read_run(write_run(second, tmp_path / "again.mcap")))
    # Written aside and renamed: no temporary files are left behind.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.mcap", "run.mcap", "run_parquet"]


def test_mcap_layout(tmp_path):
    run = make_run(n=3000)
    path = write_mcap(run, tmp_path / "run.mcap", block_samples=1000)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert [m.name for m in reader.iter_metadata()] == ["run"]
        assert next(reader.iter_metadata()).metadata == META.to_strings()
        assert {c.topic: c.message_encoding for c in summary.channels.values()} == {t: "json" for t in TOPICS.values()}
        assert {s.name: s.encoding for s in summary.schemas.values()} == {
            n: "jsonschema" for n in SCHEMA_NAMES.values()
        }
        assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
        schema = orjson.loads(next(s for s in summary.schemas.values() if s.name == "thermocal.VoltageBlock").data)
        assert schema["required"] == ["t_ns", "ux", "uy", "uz"]
        log_times, per_topic = [], {}
        for _, channel, message in reader.iter_messages(log_time_order=False):
            body = orjson.loads(message.data)
            t = body["t_ns"] if isinstance(body["t_ns"], list) else [body["t_ns"]]
            assert message.log_time == t[0]
            log_times.append(message.log_time)
            per_topic.setdefault(channel.topic, []).append(len(t))
    assert log_times == sorted(log_times)  # topics interleaved in time order
    assert per_topic["/voltmeter"] == [1000, 1000, 1000]
    assert per_topic["/au/temperature"] == [300]
    assert set(per_topic["/fixture"]) == {1}


def test_one_sample_blocks(tmp_path):
    run = make_run(n=400)
    assert_same_run(run, read_run(write_mcap(run, tmp_path / "one.mcap", block_samples=1, chunk_size=4096)))


@pytest.mark.parametrize("compression", ["none", "lz4"])
def test_other_compressions(tmp_path, compression):
    if compression == "lz4":
        pytest.importorskip("lz4")
    run = make_run(n=500)
    assert_same_run(run, read_run(write_mcap(run, tmp_path / "c.mcap", compression=compression)))


def test_empty_optional_stream_round_trips(tmp_path):
    run = make_run(n=200)
    run.chamber = run.chamber.clear()
    for fmt, name in (("mcap", "e.mcap"), ("parquet", "e_dir")):
        got = read_run(write_run(run, tmp_path / name, fmt=fmt))
        assert got.chamber is not None and got.chamber.height == 0
        assert_same_run(run, got)
    no_samples = Run(meta=run.meta, voltmeter=run.voltmeter, au_temperature=run.au_temperature.clear())
    with pytest.raises(RunFormatError, match="au_temperature: required stream has no samples"):
        read_run(write_run(no_samples, tmp_path / "n.mcap"))


def test_mcap_without_summary_reads_fully(tmp_path):
    run = make_run(n=4000)
    path = write_mcap(run, tmp_path / "nosummary.mcap", block_samples=100, chunk_size=10_000, summary=False)
    with open(path, "rb") as f:
        assert make_reader(f).get_summary() is None
    assert_same_run(run, read_run(path))


def test_unchunked_file_reads_fully(tmp_path):
    path = write_raw_mcap(tmp_path / "flat.mcap", run_messages(), META.to_strings(), use_chunking=False)
    run = read_run(path)
    assert run.voltmeter.height == 30 and run.au_temperature["temp_c"].to_list() == [20.0, 21.0, 22.0]


def test_padded_records_read(tmp_path):
    """Records longer than their known fields (MCAP lets writers pad them) are read by their length."""

    def record(op: int, body: bytes, pad: int = 0) -> bytes:
        return struct.pack("<BQ", op, len(body) + pad) + body + b"\0" * pad

    def s(text: str) -> bytes:
        return struct.pack("<I", len(text.encode())) + text.encode()

    def smap(d: dict[str, str]) -> bytes:
        body = b"".join(s(k) + s(v) for k, v in d.items())
        return struct.pack("<I", len(body)) + body

    out = [MAGIC, record(1, s("") + s("hand"), pad=5)]
    for cid, (topic, stream) in enumerate([("/voltmeter", "voltmeter"), ("/au/temperature", "au_temperature")], 1):
        out.append(
            record(
                3,
                struct.pack("<H", cid) + s(SCHEMA_NAMES[stream]) + s("jsonschema") + struct.pack("<I", 2) + b"{}",
                pad=3,
            )
        )
        out.append(record(4, struct.pack("<HH", cid, cid) + s(topic) + s("json") + smap({"k": "v"}), pad=7))
    out.append(record(12, s("run") + smap(META.to_strings()), pad=4))
    chunk_records = b""
    for topic, t, data in run_messages(n_blocks=2):
        cid = 1 if topic == "/voltmeter" else 2
        chunk_records += record(5, struct.pack("<HIQQ", cid, 0, t, t) + data)
    out.append(
        record(
            6,
            struct.pack("<QQQI", T0_NS, T0_NS, len(chunk_records), zlib.crc32(chunk_records))
            + s("")
            + struct.pack("<Q", len(chunk_records))
            + chunk_records,
            pad=11,
        )
    )
    out += [record(15, struct.pack("<I", 0), pad=2), record(2, struct.pack("<QQI", 0, 0, 0)), MAGIC]
    path = tmp_path / "padded.mcap"
    path.write_bytes(b"".join(out))
    run = read_run(path)
    assert run.voltmeter.height == 20 and run.au_temperature.height == 2 and run.meta == META


def test_unknown_topic_is_ignored_without_decoding(tmp_path):
    junk = [("/camera", T0_NS + k, b"\xff\xfe not json " * 50) for k in range(200)]
    no_summary = dict(
        repeat_channels=False,
        repeat_schemas=False,
        index_types=IndexType.NONE,
        use_statistics=False,
        use_summary_offsets=False,
    )
    for name, opts in (("indexed.mcap", {}), ("flat.mcap", no_summary)):
        path = write_raw_mcap(
            tmp_path / name,
            junk + run_messages(),
            META.to_strings(),
            chunk_size=2000,
            compression=CompressionType.NONE,
            **opts,
        )
        run = read_run(path)
        assert run.voltmeter.height == 30
        assert any("/camera" in w and "ignored" in w for w in run.warnings)
        # Damage a chunk holding only /camera messages: with the summary it is skipped unopened; without, the
        # reader must open it to learn what it holds, and finds it corrupt.
        data = bytearray(path.read_bytes())
        data[data.index(b" not json ", 3000)] = ord("X")
        path.write_bytes(bytes(data))
        if opts:
            expect_error(path, "corrupt chunk", "CRC mismatch")
        else:
            assert read_run(path).voltmeter.height == 30


def test_out_of_order_blocks_are_sorted_with_a_warning(tmp_path):
    msgs = run_messages(n_blocks=3)
    path = write_raw_mcap(
        tmp_path / "ooo.mcap", [msgs[2], msgs[3], msgs[0], msgs[1], msgs[4], msgs[5]], META.to_strings()
    )
    run = read_run(path)
    assert run.voltmeter["t_ns"].is_sorted() and run.au_temperature["t_ns"].is_sorted()
    assert any("out of time order" in w for w in run.warnings)


def test_a_clock_stepped_back_counts_every_sample_it_puts_out_of_order():
    """A logger's clock read 0..99 s, then stepped back to 70.5 s: the 29 readings until it passes 99 s again are
    out of order (said was 1: the one step), and the warning says how far back they went."""
    from pipeline.io.checks import check_stream

    t = np.concatenate((np.arange(100.0), np.arange(70.5, 130.0)))
    df = make_frame("au_temperature", {"t_ns": (T0_NS + t * 1e9).astype(np.int64), "temp_c": np.full(t.size, 20.0)})
    warnings: list[str] = []
    got = check_stream("au_temperature", df, path="x.mcap", warnings=warnings)
    assert got["t_ns"].is_sorted() and got.height == df.height
    [w] = [w for w in warnings if "out of time order" in w]
    assert w.startswith("au_temperature: 29 samples were out of time order (first at row 100: ")
    assert "up to 28.5 s before an earlier row's time" in w


def _stepped_back_run_file(
    tmp_path: Path, fmt: str, stream: str, back_s: float, name: str = "stepped"
) -> tuple[Path, np.ndarray]:
    """A 100-s run (voltmeter 10 Hz, thermosensor 1 Hz) whose ``stream``'s clock is set back ``back_s`` at 50 s,
    written as the logger would (rows in the order taken) as ``fmt``; and that stream's times as written."""
    t_v = T0_NS + np.arange(1000, dtype=np.int64) * 100_000_000
    t_1 = T0_NS + np.arange(100, dtype=np.int64) * 1_000_000_000
    times = {"voltmeter": t_v, "au_temperature": t_1}
    times[stream] = np.where(times[stream] >= T0_NS + 50 * 10**9, times[stream] - round(back_s * 1e9), times[stream])
    v = np.linspace(-0.55, 0.55, 1000)  # every sample differs from every other
    frames = {
        "voltmeter": {"t_ns": times["voltmeter"], "ux": v, "uy": -v, "uz": v / 2},
        "au_temperature": {"t_ns": times["au_temperature"], "temp_c": np.linspace(20.0, 21.0, 100)},
    }
    if fmt == "mcap":
        msgs = [
            (
                TOPICS[stream_name],
                int(cols["t_ns"][k]),
                orjson.dumps({c: a[k : k + 10] for c, a in cols.items()}, option=orjson.OPT_SERIALIZE_NUMPY),
            )
            for stream_name, cols in frames.items()
            for k in range(0, cols["t_ns"].size, 10)
        ]
        return write_raw_mcap(tmp_path / f"{name}.mcap", msgs, META.to_strings()), times[stream]
    path = tmp_path / name
    path.mkdir()
    for stream_name, cols in frames.items():
        pl.DataFrame(cols).write_parquet(path / f"{stream_name}.parquet")
    (path / "run.json").write_bytes(orjson.dumps(META.to_strings()))
    return path, times[stream]


@pytest.mark.parametrize("fmt", ["mcap", "parquet"])
@pytest.mark.parametrize(
    ("stream", "back_s", "row", "interval_s"),
    [
        ("voltmeter", 2.0, 500, 0.1),
        ("voltmeter", 30.0, 500, 0.1),
        ("voltmeter", 0.3, 500, 0.1),
        ("au_temperature", 3.0, 50, 1.0),
        ("au_temperature", 1.0, 50, None),
    ],
)
def test_a_clock_set_back_whole_sample_intervals_is_refused_naming_the_step(
    tmp_path, fmt, stream, back_s, row, interval_s
):
    """A logger's clock set back by a whole number of its sample intervals (a leap second, an NTP step on a logger
    stamping on a grid) puts samples on times already taken by others, with other values. That stays a refusal, but
    the line says where the times went back and by how much the clock was set back, in s and sample intervals
    (said was only "two different samples at the same time", which reads as a corrupt file; then the gap between
    the two stamps, one interval short of the set-back: 1.9 s for 2 s at 10 Hz, 1 s for 2 s at 1 Hz); a step that
    is no whole number of intervals is sorted with a warning."""
    path, t = _stepped_back_run_file(tmp_path, fmt, stream, back_s)
    with pytest.raises(RunFormatError) as info:
        read_run(path)
    first = T0_NS + 50 * 10**9 - round(back_s * 1e9)  # the first time taken twice
    due = t[row - 1] + round(interval_s * 1e9) if interval_s is not None else 0
    why = (
        f"the times go back at row {row} (t_ns={t[row]} after t_ns={t[row - 1]}, where t_ns={due} was due at the "
        f"stream's {interval_s:g}-s interval): a clock set back {back_s:g} s ({back_s / interval_s:g} sample "
        "intervals), or a block written again with other values"
        if interval_s is not None  # a step of one interval leaves the times in order: one time twice
        else f"the time does not advance at row {row} (t_ns={t[row]} twice): stamps coarser than the sampling, or a "
        "clock held back"
    )
    assert str(info.value) == f"{path}: {stream}: t_ns={first}: two different samples at the same time: {why}"
    odd, _ = _stepped_back_run_file(tmp_path, fmt, stream, back_s + 0.05, name="odd")
    got = read_run(odd)
    assert got.stream(stream).height == t.size and got.stream(stream)["t_ns"].is_sorted()
    assert any(w.startswith(f"{stream}: ") and "out of time order" in w for w in got.warnings)


def test_null_samples_read_as_nan(tmp_path):
    body = b'{"t_ns": [%d, %d, %d], "ux": [1.5, null, 2], "uy": [0, 0, 1], "uz": [null, 0.5, 0.25]}' % (
        T0_NS,
        T0_NS + 1,
        T0_NS + 2,
    )
    path = write_raw_mcap(
        tmp_path / "nulls.mcap", [("/voltmeter", T0_NS, body)] + run_messages()[1:2], META.to_strings()
    )
    run = read_run(path)
    np.testing.assert_array_equal(run.voltmeter["ux"].to_numpy(), [1.5, np.nan, 2.0])
    np.testing.assert_array_equal(run.voltmeter["uz"].to_numpy(), [np.nan, 0.5, 0.25])
    assert run.voltmeter["ux"].null_count() == 0 and run.voltmeter["uz"].null_count() == 0


# --- bad MCAP files ---------------------------------------------------------------------------------------------


def test_truncated_file_keeps_complete_chunks(tmp_path):
    run = make_run(n=20_000)
    path = write_mcap(run, tmp_path / "full.mcap", block_samples=200, chunk_size=30_000)
    data = path.read_bytes()
    cut = int(len(data) * 0.6)
    short = tmp_path / "short.mcap"
    short.write_bytes(data[:cut])
    got = read_run(short)
    warning = next(w for w in got.warnings if "truncated" in w)
    assert f"truncated at byte {cut}" in warning and "chunk record at byte" in warning
    n = got.voltmeter.height
    assert 0.4 * 20_000 < n < 0.75 * 20_000  # the complete chunks before the cut (the summary is ~10%)
    assert_same_run(
        Run(meta=run.meta, voltmeter=run.voltmeter[:n], au_temperature=run.au_temperature[: got.au_temperature.height]),
        Run(meta=got.meta, voltmeter=got.voltmeter, au_temperature=got.au_temperature),
    )
    assert str(got.voltmeter["t_ns"].max()) in warning


def test_truncated_before_any_data_is_an_error(tmp_path):
    data = write_mcap(make_run(n=1000), tmp_path / "full.mcap").read_bytes()
    for cut in (5, 100, 600):
        short = tmp_path / f"cut{cut}.mcap"
        short.write_bytes(data[:cut])
        expect_error(short, f"truncated at byte {cut}")


def test_corrupt_chunk_crc(tmp_path):
    path = write_mcap(make_run(n=3000), tmp_path / "run.mcap", compression="none", chunk_size=50_000)
    data = bytearray(path.read_bytes())
    i = data.index(b'"ux":[', len(data) // 2) + 7
    data[i] = ord("7") if data[i] != ord("7") else ord("3")
    path.write_bytes(bytes(data))
    expect_error(path, "corrupt chunk", "CRC mismatch", "chunk at byte", "t_ns")


def test_corrupt_compressed_chunk(tmp_path):
    path = write_mcap(make_run(n=3000), tmp_path / "run.mcap", chunk_size=50_000)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 64] = bytes(64)
    path.write_bytes(bytes(data))
    expect_error(path, "corrupt chunk")


@pytest.mark.parametrize(
    "body, fragment",
    [
        (b'{"t_ns": [1, 2], "ux": [0.1, 0.2], "uy": [0.1, 0.2]}', "missing key 'uz'"),
        (b'{"t_ns": [1, 2], "ux": [0.1, 0.2], "uy": [0.1], "uz": [0.1, 0.2]}', "unequal length"),
        (
            b'{"t_ns": [1, 2], "ux": [0.1, "0.2"], "uy": [0.1, 0.2], "uz": [0.1, 0.2]}',
            "'ux' holds values that are not numbers (e.g. '0.2')",
        ),
        (
            b'{"t_ns": [1, 2.5], "ux": [0.1, 0.2], "uy": [0.1, 0.2], "uz": [0.1, 0.2]}',
            "'t_ns' holds values that are not int64 integers (e.g. 2.5)",
        ),
        (b'{"t_ns": [1, 2], "ux": [0.1, 0.2], "uy": [[0.1], [0.2]], "uz": [0.1, 0.2]}', "'uy' is not a flat array"),
        (b'{"t_ns": 1, "ux": 0.1, "uy": 0.1, "uz": 0.1}', "'t_ns' is not an array"),
        (b"[1, 2, 3]", "not an object"),
        (b'{"t_ns": [1, 2], "ux": [0.1, 0.2], ', "not valid JSON"),
    ],
)
def test_schema_mismatch_names_topic_and_time(tmp_path, body, fragment):
    bad_t = T0_NS + 10**12
    msgs = run_messages() + [("/voltmeter", bad_t, body)]
    path = write_raw_mcap(tmp_path / "bad.mcap", msgs, META.to_strings())
    expect_error(path, "/voltmeter", f"t_ns={bad_t}", "does not match schema thermocal.VoltageBlock", fragment)


@pytest.mark.parametrize(
    "event, fragment",
    [
        (b'{"t_ns": 5, "position": "TP9"}', "unknown fixture position 'TP9'"),
        (b'{"t_ns": 5, "position": 3}', "'position' is not a string"),
        (b'{"t_ns": "5", "position": "TP1"}', "'t_ns' is not an int64 integer"),
        (b'{"position": "TP1"}', "missing key 't_ns'"),
    ],
)
def test_bad_fixture_event(tmp_path, event, fragment):
    path = write_raw_mcap(tmp_path / "fix.mcap", run_messages() + [("/fixture", 5, event)], META.to_strings())
    expect_error(path, fragment)


def test_missing_stream_and_metadata(tmp_path):
    only_v = [m for m in run_messages() if m[0] == "/voltmeter"]
    expect_error(
        write_raw_mcap(tmp_path / "a.mcap", only_v, META.to_strings()), "au_temperature", "required stream is missing"
    )
    expect_error(write_raw_mcap(tmp_path / "b.mcap", run_messages(), None), "no run metadata")
    bad_meta = {k: v for k, v in META.to_strings().items() if k != "unit_serial"}
    expect_error(write_raw_mcap(tmp_path / "c.mcap", run_messages(), bad_meta), "metadata", "'unit_serial'")
    expect_error(
        write_raw_mcap(tmp_path / "d.mcap", run_messages(), {**META.to_strings(), "normal_temp_c": "warm"}),
        "'normal_temp_c' is not a number",
    )
    expect_error(
        write_raw_mcap(tmp_path / "e.mcap", run_messages(), META.to_strings(), encoding="cdr"),
        "unsupported message encoding 'cdr'",
        "/voltmeter",
    )


def test_not_mcap_files(tmp_path):
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    expect_error(empty, "empty file")
    text = tmp_path / "notes.mcap"
    text.write_text("unit AU-0001 was fine\n" * 10)
    expect_error(text, "not an MCAP file")
    lfs = tmp_path / "pointer.mcap"
    lfs.write_text("version https://git-lfs.github.com/spec/v1\noid sha256:00\nsize 75\n")
    expect_error(lfs, "Git LFS pointer")
    expect_error(tmp_path / "absent.mcap", "no such file")
    other = tmp_path / "run.csv"
    other.write_text("t_ns,ux\n")
    expect_error(other, "expected a .mcap file or a Parquet run directory")
    assert run_format(write_mcap(make_run(n=100), tmp_path / "ok.MCAP")) == "mcap"
    assert run_format(tmp_path) == "parquet"


def test_shared_conformance_files_are_refused():
    """Every file of the MCAP conformance corpus opens without a crash and is refused as not a run.

    (In a checkout without Git LFS the corpus holds LFS pointer files; those are refused as such.)
    """
    root = DATA / "mcap-conformance"
    files = sorted(p for p in root.rglob("*") if p.is_file())
    for path in files:
        with pytest.raises(RunFormatError) as info:
            read_mcap(path)
        text = str(info.value)
        assert str(path) in text
        if path.parent != root:  # the scenario folders; beside them are README.md and LICENSE (text)
            assert "no run topics or run metadata found" in text or "Git LFS pointer" in text, text
    assert len(files) > 400


def _conformance_like_variants():
    """Writer option combinations like the corpus's (chunked, indexes, repeats, statistics, summary offsets)."""
    for chunked, index, repeat, stats, offsets in itertools.product(
        (True, False), (IndexType.ALL, IndexType.NONE), (True, False), (True, False), (True, False)
    ):
        yield dict(
            use_chunking=chunked,
            index_types=index,
            repeat_channels=repeat,
            repeat_schemas=repeat,
            use_statistics=stats,
            use_summary_offsets=offsets,
            compression=CompressionType.ZSTD if chunked else CompressionType.NONE,
        )


@pytest.mark.parametrize("content", ["NoData", "OneMessage", "OneSchemalessMessage", "OneMetadata", "OneAttachment"])
def test_generated_conformance_variants_are_refused(tmp_path, content):
    for k, opts in enumerate(_conformance_like_variants()):
        path = tmp_path / f"{content}-{k}.mcap"
        with open(path, "wb") as f:
            w = Writer(f, **opts)
            w.start(profile="", library="")
            if content == "OneMessage":
                sid = w.register_schema("Example", "c", b"\x04\x05\x06")
                cid = w.register_channel("example", "a", sid, {"foo": "bar"})
                w.add_message(cid, 2, b"\x01\x02\x03", 1, 10)
            elif content == "OneSchemalessMessage":
                cid = w.register_channel("example", "a", 0)
                w.add_message(cid, 2, b"\x01\x02\x03", 1, 10)
            elif content == "OneMetadata":
                w.add_metadata("myMetadata", {"foo": "bar"})
            elif content == "OneAttachment":
                w.add_attachment(1, 2, "myFile", "application/octet-stream", b"\x01\x02\x03")
            w.finish()
        with pytest.raises(RunFormatError, match="no run topics or run metadata found"):
            read_run(path)


# --- Parquet ----------------------------------------------------------------------------------------------------


def test_parquet_layout_and_replace(tmp_path):
    run = make_run(n=1000)
    d = write_parquet_run(run, tmp_path / "run")
    assert sorted(p.name for p in d.iterdir()) == [
        "au_temperature.parquet",
        "chamber.parquet",
        "fixture.parquet",
        "run.json",
        "voltmeter.parquet",
    ]
    assert pq.ParquetFile(d / "voltmeter.parquet").metadata.row_group(0).column(1).compression == "ZSTD"
    # An existing run directory is replaced; a run without optional streams leaves no stale files.
    bare = make_run(n=500, seed=3, optional=False)
    assert_same_run(bare, read_run(write_parquet_run(bare, d)))
    assert not (d / "chamber.parquet").exists()
    other = tmp_path / "mydata"
    other.mkdir()
    (other / "precious.txt").write_text("keep me")
    with pytest.raises(RunFormatError, match="not a Parquet run directory"):
        write_parquet_run(run, other)
    assert (other / "precious.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mydata", "run"]


def _parquet_dir(tmp_path: Path, voltmeter: pa.Table) -> Path:
    d = write_parquet_run(make_run(n=100, optional=False), tmp_path / "r")
    pq.write_table(voltmeter, d / "voltmeter.parquet")
    return d


def test_parquet_safe_casts(tmp_path):
    n = 50
    t = (np.arange(n) * 100).astype(np.int32)
    x = np.linspace(-1, 1, n).astype(np.float32)
    d = _parquet_dir(
        tmp_path, pa.table({"t_ns": t, "ux": x, "uy": x, "uz": np.arange(n, dtype=np.int16), "extra": ["a"] * n})
    )
    run = read_parquet_run(d)
    assert run.voltmeter.schema == pl.Schema(STREAM_COLUMNS["voltmeter"])
    np.testing.assert_array_equal(run.voltmeter["ux"].to_numpy(), x.astype(np.float64))
    np.testing.assert_array_equal(run.voltmeter["uz"].to_numpy(), np.arange(n))
    # Timestamps are taken as nanoseconds since the epoch; nulls in values become NaN.
    ts = pa.array(T0_NS + np.arange(n, dtype=np.int64), type=pa.timestamp("ns", tz="UTC"))
    ux = pa.array([None] + [0.5, 0.25] * ((n - 1) // 2) + [0.5], type=pa.float64())
    run = read_parquet_run(_parquet_dir(tmp_path / "b", pa.table({"t_ns": ts, "ux": ux, "uy": x, "uz": x})))
    assert run.voltmeter["t_ns"][0] == T0_NS and np.isnan(run.voltmeter["ux"][0])


@pytest.mark.parametrize(
    "table, fragments",
    [
        (
            pa.table({"t_ns": [1, 2], "ux": ["0.1", "0.2"], "uy": [0.1, 0.2], "uz": [0.1, 0.2]}),
            ("column 'ux' has type String, expected Float64",),
        ),
        (
            pa.table({"t_ns": [1.0, 2.0], "ux": [0.1, 0.2], "uy": [0.1, 0.2], "uz": [0.1, 0.2]}),
            ("column 't_ns' has type Float64, expected Int64",),
        ),
        (pa.table({"t_ns": [1, 2], "ux": [0.1, 0.2], "uz": [0.1, 0.2]}), ("column 'uy' is missing",)),
        (
            pa.table({"t_ns": [1, None], "ux": [0.1, 0.2], "uy": [0.1, 0.2], "uz": [0.1, 0.2]}),
            ("t_ns is missing", "row 1"),
        ),
    ],
)
def test_parquet_bad_columns_name_file_and_column(tmp_path, table, fragments):
    d = _parquet_dir(tmp_path, table)
    with pytest.raises(RunFormatError) as info:
        read_run(d)
    text = str(info.value)
    assert "voltmeter" in text
    for fragment in fragments:
        assert fragment in text, text


def test_parquet_bad_directories(tmp_path):
    d = write_parquet_run(make_run(n=100), tmp_path / "r")
    (d / "fixture.parquet").write_bytes(b"PAR1 garbage")
    with pytest.raises(RunFormatError, match="fixture.parquet: fixture: not a readable Parquet file"):
        read_run(d)
    (d / "fixture.parquet").unlink()
    (d / "au_temperature.parquet").unlink()
    with pytest.raises(RunFormatError, match="required stream file au_temperature.parquet is missing"):
        read_run(d)
    (d / "run.json").write_text('{"unit_serial": "AU-1", "run_id": ["x"]}')
    with pytest.raises(RunFormatError, match="'run_id' must be a string"):
        read_run(d)
    (d / "run.json").unlink()
    with pytest.raises(RunFormatError, match="run.json is missing"):
        read_run(d)


def test_parquet_unsorted_rows_are_sorted_with_a_warning(tmp_path):
    run = make_run(n=300, optional=False)
    d = write_parquet_run(run, tmp_path / "r")
    shuffled = run.voltmeter.sample(fraction=1.0, shuffle=True, seed=1)
    shuffled.write_parquet(d / "voltmeter.parquet")
    got = read_run(d)
    assert_same_run(run, got)
    assert any("voltmeter" in w and "out of time order" in w for w in got.warnings)


def test_write_refuses_bad_runs(tmp_path):
    run = make_run(n=100, optional=False)
    backwards = Run(meta=run.meta, voltmeter=run.voltmeter.reverse(), au_temperature=run.au_temperature)
    with pytest.raises(RunFormatError, match="not in time order"):
        write_run(backwards, tmp_path / "x.mcap")
    with pytest.raises(RunFormatError, match="unknown run format"):
        write_run(run, tmp_path / "x.h5", fmt="hdf5")
    assert list(tmp_path.iterdir()) == []


def test_io_modules_do_not_import_prefect_or_matplotlib():
    code = (
        "import sys, pipeline.io.runs, pipeline.io.mcap, pipeline.io.parquet, pipeline.inspect; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('prefect', 'matplotlib')]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
