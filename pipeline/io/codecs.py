"""Block codecs of MCAP runs: how one message encoding writes and reads a block of samples.

A :class:`BlockCodec` per message encoding: ``json`` (schema encoding ``jsonschema``, here) and ``protobuf``
(:mod:`pipeline.io.codec_protobuf`). :mod:`pipeline.io.mcap` registers both in its table of codecs. The schema files
are the files of the repository's ``schemas/`` (:data:`SCHEMA_DIR`; in the wheel, ``pipeline/io/schemas/``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import orjson

from pipeline.errors import RunFormatError
from pipeline.run import STREAM_COLUMNS

SCHEMA_NAMES: dict[str, str] = {
    "voltmeter": "thermocal.VoltageBlock",
    "au_temperature": "thermocal.TemperatureBlock",
    "chamber": "thermocal.ChamberBlock",
    "fixture": "thermocal.FixtureEvent",
}


def _schema_dir() -> Path:
    """The schema files (JSON Schemas, the protobuf schema and its FileDescriptorSet): the repository's top-level
    ``schemas/`` in a source checkout (an editable install included), the data package ``pipeline/io/schemas/``
    that the wheel maps it to once installed."""
    here = Path(__file__).resolve().parent
    installed = here / "schemas"
    return installed if installed.is_dir() else here.parents[1] / "schemas"


#: Where the schema files are (one folder, see :func:`_schema_dir`).
SCHEMA_DIR = _schema_dir()


class BlockMismatch(ValueError):
    """A message that does not match its stream's schema (the reader adds the file, topic and time)."""


@dataclass(frozen=True)
class BlockCodec:
    """How the messages of one message encoding are written and read.

    ``encode(stream, columns)`` returns the message bytes of one block (for ``fixture``: one event) given the
    canonical columns as numpy arrays; ``decode(stream, data)`` returns ``{column: 1-D numpy array}`` (int64 ``t_ns``,
    float64 values, object array of str for ``position``) and raises :class:`BlockMismatch`. ``schema_data(stream)``
    is the schema record's content. ``check_schema(stream, schema_encoding, schema_data)``, if given, raises
    :class:`BlockMismatch` for a channel whose schema the decoder cannot read. The binary encoding
    (:mod:`pipeline.io.codec_protobuf`) is the other codec :mod:`pipeline.io.mcap` registers.
    """

    message_encoding: str
    schema_encoding: str
    schema_data: Callable[[str], bytes]
    encode: Callable[[str, dict[str, np.ndarray]], bytes]
    decode: Callable[[str, bytes | memoryview], dict[str, np.ndarray]]
    check_schema: Callable[[str, str, bytes], None] | None = None


@functools.cache
def _json_schema(stream: str) -> bytes:
    path = SCHEMA_DIR / f"{SCHEMA_NAMES[stream]}.json"
    try:
        return path.read_bytes()
    except OSError as exc:
        raise RunFormatError(f"schema file cannot be read ({exc.strerror})", path=str(path)) from None


def _json_encode(stream: str, columns: dict[str, np.ndarray]) -> bytes:
    if stream == "fixture":
        return orjson.dumps({"t_ns": int(columns["t_ns"][0]), "position": str(columns["position"][0])})
    # Numpy arrays go straight to orjson (shortest round-trip repr: floats read back bit-exact; NaN -> null).
    return orjson.dumps(columns, option=orjson.OPT_SERIALIZE_NUMPY)


def _json_decode(stream: str, data: bytes | memoryview) -> dict[str, np.ndarray]:
    try:
        obj = orjson.loads(data)
    except orjson.JSONDecodeError as exc:
        raise BlockMismatch(f"not valid JSON ({exc})") from None
    if type(obj) is not dict:
        raise BlockMismatch(f"a JSON {type(obj).__name__}, not an object")
    for name in STREAM_COLUMNS[stream]:
        if name not in obj:
            raise BlockMismatch(f"missing key {name!r}")
    if stream == "fixture":
        return _json_fixture_event(obj)
    columns = {
        name: (_int_array if name == "t_ns" else _float_array)(obj[name], name) for name in STREAM_COLUMNS[stream]
    }
    lengths = {len(a) for a in columns.values()}
    if len(lengths) > 1:
        raise BlockMismatch(
            "arrays of unequal length (" + ", ".join(f"{k}: {len(a)}" for k, a in columns.items()) + ")"
        )
    return columns


def _json_fixture_event(obj: dict) -> dict[str, np.ndarray]:
    t_ns, position = obj["t_ns"], obj["position"]
    if type(t_ns) is not int or not -(2**63) <= t_ns < 2**63:
        raise BlockMismatch(f"'t_ns' is not an int64 integer: {t_ns!r}")
    if type(position) is not str:
        raise BlockMismatch(f"'position' is not a string: {position!r}")
    return {"t_ns": np.array([t_ns], dtype=np.int64), "position": np.array([position], dtype=object)}


def _as_1d(values: object, name: str) -> np.ndarray:
    if type(values) is not list:
        raise BlockMismatch(f"{name!r} is not an array")
    try:
        arr = np.asarray(values)  # dtype inferred: float64 / int64, object if nulls or mixed types
    except (ValueError, OverflowError, TypeError):
        raise BlockMismatch(f"{name!r} is not an array of numbers") from None
    if arr.ndim != 1:
        raise BlockMismatch(f"{name!r} is not a flat array of numbers")
    return arr


def _float_array(values: object, name: str) -> np.ndarray:
    arr = _as_1d(values, name)
    kind = arr.dtype.kind
    if kind == "f":
        return arr.astype(np.float64, copy=False)
    if kind in "iu":
        return arr.astype(np.float64)
    if kind == "O":  # nulls (non-finite samples) among the numbers: read as NaN
        null = arr == None  # noqa: E711  (elementwise on an object array)
        rest = np.asarray(arr[~null].tolist())
        if rest.dtype.kind in "fiu" and rest.ndim == 1:
            out = np.full(len(arr), np.nan)
            out[~null] = rest
            return out
    raise BlockMismatch(f"{name!r} holds values that are not numbers (e.g. {_first_non_number(values)!r})")


def _int_array(values: object, name: str) -> np.ndarray:
    arr = _as_1d(values, name)
    if arr.dtype.kind == "i" or (arr.dtype.kind == "f" and arr.size == 0):
        return arr.astype(np.int64, copy=False)
    raise BlockMismatch(f"{name!r} holds values that are not int64 integers (e.g. {_first_non_integer(values)!r})")


def _first_non_number(values: object) -> object:
    assert isinstance(values, list)  # _as_1d has checked it
    return next((v for v in values if v is not None and type(v) not in (int, float)), None)


def _first_non_integer(values: object) -> object:
    assert isinstance(values, list)  # _as_1d has checked it
    return next((v for v in values if type(v) is not int or not -(2**63) <= v < 2**63), None)


JSON_CODEC = BlockCodec(
    message_encoding="json",
    schema_encoding="jsonschema",
    schema_data=_json_schema,
    encode=_json_encode,
    decode=_json_decode,
)
