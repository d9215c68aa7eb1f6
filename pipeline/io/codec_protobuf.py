"""Binary block messages for MCAP runs: protobuf with packed repeated fields (``schemas/thermocal.proto``).

MCAP message encoding ``protobuf``, schema encoding ``protobuf``; the schema data of every channel is the
FileDescriptorSet ``schemas/thermocal.binpb`` (the standard form, readable by any MCAP tool with protobuf support,
e.g. ``mcap_protobuf.decoder.DecoderFactory``). A block message is its packed arrays one after the other::

    [tag of field 1][byte length][t_ns as little-endian int64 ...][tag of field 2][byte length][ux as float64 ...]...

which is exactly what protobuf's own serializer writes for these messages. Reading takes each packed array straight
out of the message with ``numpy.frombuffer`` (a view, no per-sample objects); messages in any other valid protobuf
form (unpacked repeated fields, a field split over several records, unknown fields) are read too, the unusual ones
through the protobuf library. Floats are stored bit for bit (NaN and +-inf included), unlike JSON.

:mod:`pipeline.io.mcap` registers :data:`PROTOBUF_CODEC` in its table of codecs.
"""

from __future__ import annotations

import functools

import numpy as np
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import DecodeError, Message

from pipeline.errors import RunFormatError
from pipeline.io.codecs import SCHEMA_DIR, SCHEMA_NAMES, BlockCodec, BlockMismatch
from pipeline.run import STREAM_COLUMNS

DESCRIPTOR_SET_FILE = SCHEMA_DIR / "thermocal.binpb"
MESSAGE_ENCODING = "protobuf"
SCHEMA_ENCODING = "protobuf"

_INT64 = np.dtype("<i8")
_FLOAT64 = np.dtype("<f8")
#: protobuf field type expected for each column dtype of pipeline.run.STREAM_COLUMNS
_FIELD_TYPES = {
    "Int64": FieldDescriptor.TYPE_SFIXED64,
    "Float64": FieldDescriptor.TYPE_DOUBLE,
    "String": FieldDescriptor.TYPE_STRING,
}
_WIRE_VARINT, _WIRE_I64, _WIRE_LEN, _WIRE_I32 = 0, 1, 2, 5


@functools.cache
def descriptor_set_bytes() -> bytes:
    """The FileDescriptorSet of ``schemas/thermocal.proto`` (the schema data of every protobuf channel)."""
    try:
        return DESCRIPTOR_SET_FILE.read_bytes()
    except OSError as exc:
        raise RunFormatError(f"schema file cannot be read ({exc.strerror})", path=str(DESCRIPTOR_SET_FILE)) from None


@functools.cache
def message_class(stream: str) -> type[Message]:
    """The generated protobuf message class of ``stream`` (e.g. ``thermocal.VoltageBlock`` for ``voltmeter``)."""
    pool = descriptor_pool.DescriptorPool()
    for fd in FileDescriptorSet.FromString(descriptor_set_bytes()).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(SCHEMA_NAMES[stream]))


@functools.cache
def _layout(stream: str) -> dict[int, tuple[str, np.dtype]]:
    """Field number -> (column, little-endian dtype) of a block stream, checked against the canonical columns."""
    fields = {f.name: f for f in message_class(stream).DESCRIPTOR.fields}
    problems = _field_problems(stream, {name: (f.number, f.type, f.is_repeated) for name, f in fields.items()})
    if problems:  # the project's own schema file disagrees with pipeline.run: a broken installation
        raise RunFormatError(
            f"schema does not match the canonical columns: {'; '.join(problems)}",
            path=str(DESCRIPTOR_SET_FILE),
            stream=stream,
        )
    return {fields[name].number: (name, _INT64 if name == "t_ns" else _FLOAT64) for name in STREAM_COLUMNS[stream]}


def _field_problems(stream: str, fields: dict[str, tuple[int, int, bool]]) -> list[str]:
    """What keeps a message with ``fields`` (name -> (number, type, repeated)) from being read as ``stream``."""
    numbers = {f.name: f.number for f in message_class(stream).DESCRIPTOR.fields}
    problems = []
    for name, dtype in STREAM_COLUMNS[stream].items():
        have = fields.get(name)
        want_type = _FIELD_TYPES[str(dtype)]
        want_repeated = stream != "fixture"
        if have is None:
            problems.append(f"no field {name!r}")
        elif have[1] != want_type or have[2] != want_repeated:
            problems.append(f"field {name!r} is not {'repeated ' if want_repeated else ''}{_type_name(want_type)}")
        elif have[0] != numbers[name]:
            problems.append(f"field {name!r} has number {have[0]}, expected {numbers[name]}")
    return problems


def _type_name(field_type: int) -> str:
    return {
        FieldDescriptor.TYPE_SFIXED64: "sfixed64",
        FieldDescriptor.TYPE_DOUBLE: "double",
        FieldDescriptor.TYPE_STRING: "string",
    }[field_type]


# --- schema check ---------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=64)
def check_schema(stream: str, schema_encoding: str, schema_data: bytes) -> None:
    """Raise :class:`BlockMismatch` unless a channel's schema describes the message of ``stream`` with the field
    numbers and types of ``schemas/thermocal.proto`` (other fields may be added; they are skipped when reading)."""
    name = SCHEMA_NAMES[stream]
    if schema_encoding != SCHEMA_ENCODING:
        raise BlockMismatch(f"schema encoding is {schema_encoding!r}, expected {SCHEMA_ENCODING!r}")
    try:
        files = FileDescriptorSet.FromString(schema_data).file
    except DecodeError:
        raise BlockMismatch("schema data is not a protobuf FileDescriptorSet") from None
    package, _, short = name.rpartition(".")
    found = [m for fd in files if fd.package == package for m in fd.message_type if m.name == short]
    if not found:
        raise BlockMismatch(f"schema data does not define message {name}")
    fields = {f.name: (f.number, f.type, f.label == f.LABEL_REPEATED) for f in found[0].field}
    problems = _field_problems(stream, fields)
    if problems:
        raise BlockMismatch(f"schema {name} cannot be read as {stream}: {'; '.join(problems)}")


# --- encode -----------------------------------------------------------------------------------------------------


def _varint(value: int) -> bytes:
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


@functools.cache
def _tag(number: int, wire_type: int) -> bytes:
    return _varint(number << 3 | wire_type)


def encode(stream: str, columns: dict[str, np.ndarray]) -> bytes:
    """One block (``fixture``: one event) as protobuf bytes; packed arrays in field-number order."""
    if stream == "fixture":
        msg = message_class(stream)(t_ns=int(columns["t_ns"][0]), position=str(columns["position"][0]))
        return msg.SerializeToString()
    parts = []
    for number, (name, dtype) in _layout(stream).items():
        raw = np.ascontiguousarray(columns[name], dtype=dtype).tobytes()
        if raw:  # proto3 leaves an empty repeated field out
            parts += [_tag(number, _WIRE_LEN), _varint(len(raw)), raw]
    return b"".join(parts)


# --- decode -----------------------------------------------------------------------------------------------------


def decode(stream: str, data: bytes | memoryview) -> dict[str, np.ndarray]:
    """``{column: 1-D array}`` of one message; packed arrays are numpy views of ``data`` (no per-sample work).

    Raises :class:`BlockMismatch` for bytes that are not a message of the stream's schema.
    """
    if stream == "fixture":
        return _decode_fixture(data)
    layout = _layout(stream)
    spans: dict[int, list[tuple[int, int]]] = {}
    view = memoryview(data)
    n = len(view)
    p = 0
    try:
        while p < n:
            key, p = _read_varint(view, p)
            wire = key & 7
            if wire == _WIRE_LEN:
                length, p = _read_varint(view, p)
                end = p + length
                if end > n:
                    raise BlockMismatch(f"field {key >> 3} runs past the end of the {n}-byte message")
                if key >> 3 in layout:
                    spans.setdefault(key >> 3, []).append((p, end))
                p = end
            elif wire in (_WIRE_VARINT, _WIRE_I64, _WIRE_I32):
                if key >> 3 in layout:  # an unpacked repeated field: valid, unusual; the library reads it
                    return _decode_with_library(stream, view)
                p = _read_varint(view, p)[1] if wire == _WIRE_VARINT else p + (8 if wire == _WIRE_I64 else 4)
            else:
                raise BlockMismatch(
                    f"not a protobuf {SCHEMA_NAMES[stream]} message (wire type {wire} at byte "
                    f"{p - 1}, first bytes {bytes(view[:12])!r})"
                )
    except IndexError:
        raise BlockMismatch(f"message ends inside a field ({n} bytes)") from None
    if p > n:
        raise BlockMismatch(f"message ends inside a field ({n} bytes)")
    columns = {}
    for number, (name, dtype) in layout.items():
        arrays = [_packed(view, a, b, dtype, name) for a, b in spans.get(number, [])]
        columns[name] = (
            arrays[0] if len(arrays) == 1 else np.concatenate(arrays) if arrays else np.empty(0, dtype=dtype)
        )
    return _equal_lengths(columns)


def _read_varint(view: memoryview, p: int) -> tuple[int, int]:
    """The varint at ``p`` and the offset after it (IndexError past the end)."""
    b = view[p]
    if b < 0x80:
        return b, p + 1
    value, shift = b & 0x7F, 7
    while True:
        p += 1
        b = view[p]
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, p + 1
        shift += 7
        if shift > 63:
            raise BlockMismatch(f"varint longer than 10 bytes at byte {p}")


def _packed(view: memoryview, start: int, end: int, dtype: np.dtype, name: str) -> np.ndarray:
    if (end - start) % 8:
        raise BlockMismatch(f"packed field {name!r} holds {end - start} bytes, not a whole number of 8-byte values")
    return np.frombuffer(view, dtype=dtype, count=(end - start) // 8, offset=start)


def _equal_lengths(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if len({a.size for a in columns.values()}) > 1:
        raise BlockMismatch(
            "arrays of unequal length (" + ", ".join(f"{k}: {a.size}" for k, a in columns.items()) + ")"
        )
    return columns


def _parse(stream: str, data: bytes | memoryview):
    try:
        return message_class(stream).FromString(bytes(data))
    except DecodeError as exc:
        raise BlockMismatch(f"not a protobuf {SCHEMA_NAMES[stream]} message ({exc})") from None


def _decode_with_library(stream: str, data: bytes | memoryview) -> dict[str, np.ndarray]:
    msg = _parse(stream, data)
    return _equal_lengths({name: np.array(getattr(msg, name), dtype=dtype) for name, dtype in _layout(stream).values()})


def _decode_fixture(data: bytes | memoryview) -> dict[str, np.ndarray]:
    msg = _parse("fixture", data)
    return {"t_ns": np.array([msg.t_ns], dtype=np.int64), "position": np.array([msg.position], dtype=object)}


PROTOBUF_CODEC = BlockCodec(
    message_encoding=MESSAGE_ENCODING,
    schema_encoding=SCHEMA_ENCODING,
    schema_data=lambda stream: descriptor_set_bytes(),
    encode=encode,
    decode=decode,
    check_schema=check_schema,
)
