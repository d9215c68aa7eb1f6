"""The protobuf block encoding of MCAP runs: bit-exact round trips, the standard protobuf tooling reads our files and
we read its messages in every valid wire form, bad messages and schemas are named by file, topic and time."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import orjson
import pytest
from google.protobuf.descriptor_pb2 import FieldDescriptorProto, FileDescriptorSet
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory

from pipeline.errors import RunFormatError
from pipeline.io.codec_protobuf import (
    DESCRIPTOR_SET_FILE,
    PROTOBUF_CODEC,
    decode,
    descriptor_set_bytes,
    encode,
    message_class,
)
from pipeline.io.mcap import CODECS, JSON_CODEC, SCHEMA_NAMES, TOPICS, BlockMismatch, read_mcap, write_mcap
from pipeline.io.runs import read_run, write_run
from pipeline.run import Run, make_frame
from pipeline.simulate.chamber import SimConfig, simulate

from .test_io import META, T0_NS, assert_same_run, make_run

REPO = Path(__file__).resolve().parents[2]


def _with_infinities(run: Run) -> Run:
    """``run`` with +-inf samples too (protobuf keeps them; JSON turns them into NaN)."""
    u = {c: run.voltmeter[c].to_numpy().copy() for c in ("ux", "uy", "uz")}
    u["uy"][[10, 11]] = (np.inf, -np.inf)
    volt = make_frame("voltmeter", {"t_ns": run.voltmeter["t_ns"].to_numpy(), **u})
    return Run(
        meta=run.meta, voltmeter=volt, au_temperature=run.au_temperature, chamber=run.chamber, fixture=run.fixture
    )


def test_protobuf_mcap_round_trip_is_bit_exact(tmp_path):
    run = _with_infinities(make_run(n=7777, seed=5))
    for block_samples in (1000, 1, 333):
        path = write_mcap(run, tmp_path / f"b{block_samples}.mcap", encoding="protobuf", block_samples=block_samples)
        got = read_run(path)
        assert_same_run(run, got)
        assert got.warnings == []
    assert np.isposinf(got.voltmeter["uy"][10]) and np.isneginf(got.voltmeter["uy"][11])


def test_protobuf_file_is_standard_mcap_protobuf(tmp_path):
    """Channels say protobuf / protobuf with the FileDescriptorSet of schemas/; the mcap-protobuf-support decoder
    reads every message to the same values."""
    run = make_run(n=2500, seed=1)
    path = write_mcap(run, tmp_path / "r.mcap", encoding="protobuf")
    seen: dict[str, dict[str, list]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _, msg in reader.iter_decoded_messages():
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            assert schema.data == DESCRIPTOR_SET_FILE.read_bytes()
            assert schema.name == msg.DESCRIPTOR.full_name
            cols = seen.setdefault(channel.topic, {})
            for field, value in msg.ListFields():
                cols.setdefault(field.name, []).extend(value if field.is_repeated else [value])
    assert set(seen) == set(TOPICS.values())
    for stream, topic in TOPICS.items():
        df = run.stream(stream)
        for name in df.columns:
            want = df[name].to_list() if name == "position" else df[name].to_numpy()
            got = seen[topic][name] if name == "position" else np.array(seen[topic][name])
            if name == "position":
                assert got == want
            else:
                np.testing.assert_array_equal(got.view(np.int64), np.asarray(want).view(np.int64))


def test_descriptor_set_matches_the_proto_file():
    """schemas/thermocal.binpb is the compiled schemas/thermocal.proto: same messages, fields, numbers, types."""
    files = FileDescriptorSet.FromString(descriptor_set_bytes()).file
    assert [f.name for f in files] == ["thermocal.proto"] and files[0].package == "thermocal"
    proto_text = (REPO / "schemas" / "thermocal.proto").read_text()
    types = {
        FieldDescriptorProto.TYPE_DOUBLE: "double",
        FieldDescriptorProto.TYPE_SFIXED64: "sfixed64",
        FieldDescriptorProto.TYPE_STRING: "string",
    }
    for m in files[0].message_type:
        assert f"message {m.name} {{" in proto_text
        for f in m.field:
            repeated = "repeated " if f.label == FieldDescriptorProto.LABEL_REPEATED else ""
            assert f"{repeated}{types[f.type]} {f.name} = {f.number};" in proto_text
    assert sorted(m.name for m in files[0].message_type) == sorted(n.split(".")[1] for n in SCHEMA_NAMES.values())


def test_encoding_is_what_the_protobuf_serializer_writes():
    rng = np.random.default_rng(2)
    n = 17
    cols = {
        "t_ns": T0_NS + np.arange(n, dtype=np.int64),
        "ux": rng.normal(size=n),
        "uy": rng.normal(size=n),
        "uz": np.full(n, np.nan),
    }
    assert encode("voltmeter", cols) == message_class("voltmeter")(**cols).SerializeToString()
    event = {"t_ns": np.array([T0_NS]), "position": np.array(["VP3"], dtype=object)}
    assert encode("fixture", event) == message_class("fixture")(t_ns=T0_NS, position="VP3").SerializeToString()
    back = decode("voltmeter", encode("voltmeter", cols))
    for name, values in cols.items():
        np.testing.assert_array_equal(back[name].view(np.int64), values.view(np.int64))


def _tag(number: int, wire: int) -> bytes:
    return bytes([number << 3 | wire])


def _packed(number: int, values: np.ndarray) -> bytes:
    raw = values.tobytes()
    assert len(raw) < 128
    return _tag(number, 2) + bytes([len(raw)]) + raw


def test_every_valid_wire_form_is_read():
    """Fields in any order, split over several records, unpacked, with unknown fields between: all read alike."""
    t = T0_NS + np.arange(3, dtype=np.int64)
    x = np.array([1.5, -2.25, 3e-300])
    want = {"t_ns": t, "temp_c": x}
    forms = {
        "reordered": _packed(2, x) + _packed(1, t),
        "split": _packed(1, t[:1]) + _packed(2, x[:2]) + _packed(1, t[1:]) + _packed(2, x[2:]),
        "unknown fields": _tag(9, 0)
        + b"\x96\x01"
        + _packed(1, t)
        + _tag(10, 2)
        + b"\x02ab"
        + _packed(2, x)
        + _tag(11, 5)
        + b"\x00\x00\x80\x3f"
        + _tag(12, 1)
        + bytes(8),
        "unpacked": b"".join(_tag(1, 1) + v.tobytes() for v in t) + b"".join(_tag(2, 1) + v.tobytes() for v in x),
    }
    for form, data in forms.items():
        got = decode("au_temperature", data)
        assert set(got) == set(want), form
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=form)
    empty = decode("au_temperature", b"")  # proto3 leaves empty arrays out: a block of no samples
    assert empty["t_ns"].dtype == np.int64 and empty["t_ns"].size == empty["temp_c"].size == 0


@pytest.mark.parametrize(
    "data, fragment",
    [
        (orjson.dumps({"t_ns": [1], "ux": [0.1], "uy": [0.1], "uz": [0.1]}), "not a protobuf thermocal.VoltageBlock"),
        (_packed(1, np.arange(3, dtype=np.int64)) + _packed(2, np.zeros(3)), "unequal length"),  # a TemperatureBlock
        (_packed(1, np.arange(3, dtype=np.int64))[:-5], "runs past the end"),
        (_tag(2, 2) + b"\x07" + bytes(7), "not a whole number of 8-byte values"),
        (b"\x0a\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff\x01", "varint longer than 10 bytes"),
        (b"\x0a", "ends inside a field"),
    ],
)
def test_invalid_block_is_a_mismatch(data, fragment):
    with pytest.raises(BlockMismatch, match=fragment):
        decode("voltmeter", data)


def _write_file(
    path: Path,
    voltmeter_messages: list[tuple[int, bytes]],
    *,
    encoding: str = "protobuf",
    schema_data: bytes | None = None,
    schema_encoding: str = "protobuf",
) -> Path:
    """A run file with one good /au/temperature block (protobuf) and the given raw /voltmeter messages."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        pb = w.register_schema(SCHEMA_NAMES["au_temperature"], "protobuf", descriptor_set_bytes())
        temp = w.register_channel(TOPICS["au_temperature"], "protobuf", pb)
        vs = w.register_schema(
            SCHEMA_NAMES["voltmeter"], schema_encoding, descriptor_set_bytes() if schema_data is None else schema_data
        )
        volt = w.register_channel(TOPICS["voltmeter"], encoding, vs)
        w.add_metadata("run", META.to_strings())
        w.add_message(
            temp, T0_NS, encode("au_temperature", {"t_ns": np.array([T0_NS]), "temp_c": np.array([20.0])}), T0_NS
        )
        for t, data in voltmeter_messages:
            w.add_message(volt, t, data, t)
        w.finish()
    return path


def _block(t0: int, n: int = 4) -> dict[str, np.ndarray]:
    return {
        "t_ns": t0 + np.arange(n, dtype=np.int64) * 1_000_000,
        "ux": 1.0 + 1e-3 * np.arange(n),  # V: live channels (one value throughout is a dead channel, refused)
        "uy": 1e-3 * np.arange(n),
        "uz": -1.0 - 1e-3 * np.arange(n),
    }


def test_mixed_and_invalid_messages_name_file_topic_and_time(tmp_path):
    good = encode("voltmeter", _block(T0_NS))
    t_bad = T0_NS + 5_000_000
    cases = {
        "json-in-protobuf": JSON_CODEC.encode("voltmeter", _block(t_bad)),
        "temperature-block": encode("au_temperature", {"t_ns": np.array([t_bad]), "temp_c": np.array([1.0])}),
        "truncated": encode("voltmeter", _block(t_bad))[:-3],
    }
    for name, bad in cases.items():
        path = _write_file(tmp_path / f"{name}.mcap", [(T0_NS, good), (t_bad, bad)])
        with pytest.raises(RunFormatError) as info:
            read_run(path)
        text = str(info.value)
        for fragment in (
            str(path),
            "/voltmeter",
            f"t_ns={t_bad}",
            "message 1 of the topic",
            "does not match schema thermocal.VoltageBlock",
        ):
            assert fragment in text, (name, text)


def test_channels_of_both_encodings_in_one_file(tmp_path):
    """Each channel is decoded by its own message encoding: JSON /voltmeter beside protobuf /au/temperature."""
    block = _block(T0_NS, 10)
    path = _write_file(
        tmp_path / "mixed.mcap",
        [(T0_NS, JSON_CODEC.encode("voltmeter", block))],
        encoding="json",
        schema_data=JSON_CODEC.schema_data("voltmeter"),
        schema_encoding="jsonschema",
    )
    run = read_run(path)
    np.testing.assert_array_equal(run.voltmeter["t_ns"].to_numpy(), block["t_ns"])
    np.testing.assert_array_equal(run.voltmeter["uz"].to_numpy(), block["uz"])
    assert run.au_temperature["temp_c"].to_list() == [20.0]


def _schema_with(change) -> bytes:
    fds = FileDescriptorSet.FromString(descriptor_set_bytes())
    msg = next(m for m in fds.file[0].message_type if m.name == "VoltageBlock")
    change(msg)
    return fds.SerializeToString()


@pytest.mark.parametrize(
    "schema_data, schema_encoding, fragment",
    [
        (
            _schema_with(lambda m: setattr(m.field[1], "type", FieldDescriptorProto.TYPE_FLOAT)),
            "protobuf",
            "field 'ux' is not repeated double",
        ),
        (_schema_with(lambda m: setattr(m.field[3], "number", 7)), "protobuf", "field 'uz' has number 7, expected 4"),
        (_schema_with(lambda m: m.field.pop()), "protobuf", "no field 'uz'"),
        (b"\xff\xff", "protobuf", "not a protobuf FileDescriptorSet"),
        (b"{}", "jsonschema", "schema encoding is 'jsonschema', expected 'protobuf'"),
    ],
)
def test_unreadable_protobuf_schema_is_refused(tmp_path, schema_data, schema_encoding, fragment):
    path = _write_file(
        tmp_path / "s.mcap",
        [(T0_NS, encode("voltmeter", _block(T0_NS)))],
        schema_data=schema_data,
        schema_encoding=schema_encoding,
    )
    with pytest.raises(RunFormatError) as info:
        read_mcap(path)
    text = str(info.value)
    assert "/voltmeter" in text and "unreadable schema" in text and fragment in text, text


def test_schema_with_added_fields_is_read(tmp_path):
    """A newer schema with more fields still reads (unknown fields are skipped)."""

    def add(m):
        f = m.field.add(name="gain_code", number=9, type=FieldDescriptorProto.TYPE_INT32)
        f.label = FieldDescriptorProto.LABEL_OPTIONAL

    data = encode("voltmeter", _block(T0_NS)) + _tag(9, 0) + b"\x05"
    run = read_mcap(_write_file(tmp_path / "new.mcap", [(T0_NS, data)], schema_data=_schema_with(add)))
    assert run.voltmeter.height == 4


def test_codec_is_registered():
    assert CODECS["protobuf"] is PROTOBUF_CODEC and CODECS["json"] is JSON_CODEC


@pytest.mark.slow  # the console script in a subprocess
def test_cli_simulate_writes_protobuf_that_all_readers_take(tmp_path):
    """``thermocal simulate --encoding protobuf`` writes protobuf channels holding the same run as the JSON form."""

    def sim(name: str, encoding: str) -> Path:
        out = tmp_path / name
        subprocess.run(
            [
                sys.executable,
                "-m",
                "flows.cli",
                "simulate",
                "--out",
                str(out),
                "--program",
                "short",
                "--rate-hz",
                "2",
                "--encoding",
                encoding,
                "--json",
            ],
            check=True,
            capture_output=True,
            cwd=REPO,
        )
        return out

    pb, js = sim("pb.mcap", "protobuf"), sim("js.mcap", "json")
    with open(pb, "rb") as f:
        summary = make_reader(f).get_summary()
    assert {c.message_encoding for c in summary.channels.values()} == {"protobuf"}
    assert_same_run(read_run(js), read_run(pb))
    assert pb.stat().st_size < js.stat().st_size
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "flows.cli",
            "simulate",
            "--out",
            str(tmp_path / "x.mcap"),
            "--program",
            "short",
            "--rate-hz",
            "2",
            "--encoding",
            "cbor",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert bad.returncode != 0 and "unknown message encoding 'cbor'" in bad.stderr


def test_simulated_run_reads_identically_from_protobuf_and_parquet(tmp_path):
    run = simulate(SimConfig(program="short", rate_hz=2.0)).run
    assert_same_run(
        read_run(write_run(run, tmp_path / "r.mcap", encoding="protobuf")),
        read_run(write_run(run, tmp_path / "r", "parquet")),
    )
