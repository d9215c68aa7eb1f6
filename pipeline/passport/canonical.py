"""Canonical JSON of registry records (passport versions, approvals, head statements) and the hashes over it.

One encoding for everything that is hashed or signed: keys sorted, 2-space indent, ASCII, a final newline, no NaN or
infinity (docs/contract.md). A record's ``content_sha256`` and its ``signature`` cover the same bytes: the canonical
JSON of the record without those two fields (:func:`signed_body`).

Reading a record back (:func:`read_sealed`) is the inverse, and strict: the bytes must parse as one JSON object
without duplicate keys or non-finite numbers, and must BE its canonical encoding (a file that says the same in other
bytes, e.g. a duplicate ``"status"`` that one parser reads first and another last, is refused).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass
from json.encoder import encode_basestring_ascii as _ascii
from typing import Any

import orjson

from pipeline.jsonable import json_default

#: Fields of a record that are not part of what is hashed and signed.
SEAL_FIELDS = ("content_sha256", "signature")


def canonical_json(obj: Any) -> bytes:
    """The canonical bytes of a JSON document: sorted keys, indent 2, ASCII, a final newline, no NaN/inf.

    Floats are written with Python's shortest round-trip repr, so load -> canonical_json gives the same bytes.
    Raises ValueError (non-finite number) or TypeError (not JSON-able).
    """
    return (_encode(obj, "\n") + "\n").encode("ascii")


def _dumps(obj: Any) -> str:
    """The canonical text by :func:`json.dumps` (the definition; CPython encodes ``indent`` in pure Python)."""
    return json.dumps(obj, sort_keys=True, indent=2, ensure_ascii=True, allow_nan=False, default=json_default)


class _Other(Exception):
    """A value :func:`_fast` does not write itself (anything but JSON's own types)."""


#: JSON's scalars as json.dumps writes them (floats here even when not finite: :data:`_NON_FINITE` finds those)
_SCALARS: dict[type, Any] = {
    str: _ascii,
    float: float.__repr__,
    int: int.__repr__,
    bool: {True: "true", False: "false"}.__getitem__,
    type(None): lambda _: "null",
}
#: a bare inf/nan where a value starts (a string's text is quoted): the repr of a non-finite float in _fast's text
#: (after indentation or ": ", or the whole text)
_NON_FINITE = re.compile(r"(?:^ *|: )-?(?:inf|nan)(?:,|$)", re.MULTILINE)


def _fast(value: Any, indent: str) -> str:
    """``json.dumps(value, sort_keys=True, indent=2, ensure_ascii=True)`` for exactly JSON's types (dict with str
    keys, list, str, int, float, bool, None), its nested lines starting with ``indent`` (a newline and spaces): the
    same text, built by joins instead of the pure-Python encoder's generator chain. Non-finite floats come out as
    ``inf``/``nan`` (:func:`_encode` looks for them). :class:`_Other` for any other type (a subclass, a tuple)."""
    scalar = _SCALARS.get(type(value))
    if scalar is not None:
        return scalar(value)
    inner = indent + "  "
    get = _SCALARS.get
    if type(value) is dict:
        if not value:
            return "{}"
        items = [  # sorted(): TypeError for keys of mixed types, _ascii(): TypeError for a non-str key
            _ascii(k) + ": " + (f(v) if (f := get(type(v := value[k]))) is not None else _fast(v, inner))
            for k in sorted(value)
        ]
        return "{" + inner + ("," + inner).join(items) + indent + "}"
    if type(value) is list:
        if not value:
            return "[]"
        items = [f(v) if (f := get(type(v))) is not None else _fast(v, inner) for v in value]
        return "[" + inner + ("," + inner).join(items) + indent + "]"
    raise _Other


def _encode(value: Any, indent: str) -> str:
    """:func:`_fast`, else (another type, a non-finite float, keys that do not sort) :func:`json.dumps` itself, so
    every value gets json.dumps' text and every error json.dumps' error."""
    try:
        text = _fast(value, indent)
        if not (("inf" in text or "nan" in text) and _NON_FINITE.search(text)):  # (a bare inf too: no space)
            return text
    except (_Other, TypeError, RecursionError):  # (a circular or very deep value: json.dumps says which)
        pass
    text = _dumps(value)
    return text if indent == "\n" else text.replace("\n", indent)  # no JSON string holds a raw newline


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
    from pipeline.io.files import open_regular

    h = hashlib.sha256()
    with open_regular(path) as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def signed_body(record: dict) -> bytes:
    """The bytes a record's ``content_sha256`` hashes and its ``signature`` signs: its canonical JSON without
    the fields in :data:`SEAL_FIELDS`."""
    return canonical_json({k: v for k, v in record.items() if k not in SEAL_FIELDS})


def content_sha256(record: dict) -> str:
    """The self-hash stored in a record: sha256 of :func:`signed_body`."""
    return sha256_bytes(signed_body(record))


# ---------------------------------------------------------------------------------------------------------------
# reading a record back


class NotCanonical(ValueError):
    """Bytes that are not one canonical JSON record; the message is a phrase (``duplicate key "status" ...``)."""


@dataclass(frozen=True)
class Sealed:
    """A record read back by :func:`read_sealed`: the object, and the bytes its seal covers (:func:`signed_body`)."""

    record: dict
    body: bytes

    @property
    def body_sha256(self) -> str:
        return sha256_bytes(self.body)


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set[str] = set()
        dup = next(k for k, _ in pairs if k in seen or seen.add(k))  # type: ignore[func-returns-value]
        raise NotCanonical(f"duplicate key {json.dumps(dup)} (parsers disagree on which value counts)")
    return out


def _no_constant(name: str) -> float:
    raise NotCanonical(f"non-finite number {name} (JSON has none)")


def parse_record(data: bytes) -> dict:
    """The JSON object in ``data``, refusing what would let two readers see different records: duplicate keys,
    NaN/Infinity, text that is not UTF-8, a document that is not an object, nesting too deep to read. NotCanonical
    (a phrase) otherwise."""
    try:
        doc = json.loads(data, object_pairs_hook=_no_duplicates, parse_constant=_no_constant)
    except NotCanonical:
        raise
    except RecursionError:
        raise NotCanonical("nested too deeply to read") from None
    except UnicodeDecodeError:
        raise NotCanonical("not UTF-8 text") from None
    except ValueError as exc:
        raise NotCanonical(f"unparsable JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise NotCanonical(f"not a JSON object (a {type(doc).__name__})")
    return doc


def _member(key: str, value: Any) -> str:
    """One member of a top-level object as :func:`canonical_json` writes it (its nested lines indented once)."""
    return f"  {json.dumps(key)}: " + _encode(value, "\n  ")


def _object(members: list[str]) -> bytes:
    return (("{\n" + ",\n".join(members) + "\n}") if members else "{}").encode("ascii") + b"\n"


def _read_canonical(data: bytes) -> Sealed | None:
    """:func:`read_sealed`'s answer for canonical bytes, parsed by the plain (C) parser, else None. Canonical bytes
    have no duplicate key, no NaN and are an object, so the strict parse would give this record: the bytes are
    compared with the record's encoding either way."""
    try:
        doc = json.loads(data)
        if type(doc) is not dict:
            return None
        members = {k: _member(k, doc[k]) for k in sorted(doc)}
    except (TypeError, ValueError, RecursionError):
        return None
    if _object(list(members.values())) != data:
        return None
    return Sealed(doc, _object([m for k, m in members.items() if k not in SEAL_FIELDS]))


#: orjson's writing closest to the canonical form: 2-space indent, sorted keys, a final newline
_ORJSON_LAYOUT = orjson.OPT_INDENT_2 | orjson.OPT_SORT_KEYS | orjson.OPT_APPEND_NEWLINE
#: where orjson writes a float otherwise than Python's repr (:func:`_python_floats`), at the end of a line of indented
#: JSON text (so never inside a string: a string holds no raw newline): a one-digit negative exponent (``1e-7``,
#: repr ``1e-07``) and the decade 1e-5 written out (``0.000012``, repr ``1.2e-05``)
_SHORT_EXPONENT = re.compile(rb"e-(?=[1-9],?\n)")
_FIFTH_DECADE = re.compile(rb"0\.0000([1-9])([0-9]*)(?=,?\n)")


def _fifth_decade(m: re.Match) -> bytes:
    """``0.0000dd...`` as repr writes it (``d.d...e-05``), when it is a whole number (not the tail of ``10.00001``)."""
    if m.string[m.start() - 1] not in b" -":
        return m[0]
    return m[1] + (b"." + m[2] if m[2] else b"") + b"e-05"


def _python_floats(text: bytes) -> bytes:
    """orjson's indented text with its floats in Python's repr: orjson writes the same shortest digits as repr and
    the same form except in the two cases of :data:`_SHORT_EXPONENT` and :data:`_FIFTH_DECADE` (checked once per
    process: :func:`_orjson_floats_are_python`)."""
    if b"e-" in text:
        text = _SHORT_EXPONENT.sub(b"e-0", text)  # (a literal replacement: no Python call per match)
    return _FIFTH_DECADE.sub(_fifth_decade, text) if b"0.0000" in text else text


@functools.cache
def _orjson_floats_are_python() -> bool:
    """Whether this orjson writes floats as :func:`_python_floats` expects (each decade's edges and neighbours,
    the smallest and largest doubles) and reads repr's text back exactly: else :func:`_read_by_orjson` is not
    used (another orjson version, another float writer)."""
    values = [5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, 0.0, 1.5, 9007199254740993.0]
    for e in range(-30, 31):
        edge = float(f"1e{e}")
        values += [edge, math.nextafter(edge, 0.0), math.nextafter(edge, math.inf), 1.2345678901234567 * edge]
    values += [-v for v in values]
    text = orjson.dumps(values, option=_ORJSON_LAYOUT)
    return _python_floats(text) == canonical_json(values) and orjson.loads(canonical_json(values)) == values


def _read_by_orjson(data: bytes) -> dict | None:
    """The record in ``data`` when the bytes are its canonical encoding as orjson reads and writes them, else None
    (then the exact path decides: :func:`_read_canonical`, the strict parse). orjson parses the bytes and writes the
    record in its indented, key-sorted layout, which is the canonical layout; where orjson's text differs from
    canonical_json's, the bytes are refused here or orjson's text is rewritten: a non-ASCII character or DEL
    (orjson writes them raw, canonical_json escapes them) -> None; floats in Python's repr (:func:`_python_floats`);
    integers beyond 64 bits, lone surrogates, nesting beyond orjson's limit or duplicate keys give an error or
    other bytes -> None."""
    if not _orjson_floats_are_python():
        return None
    try:
        doc = orjson.loads(data)
        if type(doc) is not dict:
            return None
        text = orjson.dumps(doc, option=_ORJSON_LAYOUT)
    except (ValueError, TypeError):  # (orjson.JSONDecodeError, orjson.JSONEncodeError)
        return None
    if not text.isascii() or b"\x7f" in text:
        return None
    return doc if _python_floats(text) == data else None


#: every digit as 0: with it, a number orjson may read as a float though it is an integer (beyond 64 bits: from 20
#: digits, or from 19 with a minus sign) shows as a space or a minus and that many zeros (a float's repr never has
#: 17 digits before its point)
_DIGITS_AS_ZERO = bytes.maketrans(b"123456789", b"000000000")
_WIDE_INTEGERS = (b" " + b"0" * 20, b"-" + b"0" * 19)


def parse_canonical(data: bytes) -> dict:
    """The record in bytes that passed :func:`read_sealed` before (a cached file: exactly those bytes), as
    ``json.loads`` reads it: by orjson (about a tenth of json.loads' time) unless the bytes may hold an integer
    beyond 64 bits (:data:`_WIDE_INTEGERS`: orjson reads it as a float) or a lone surrogate (orjson refuses it)."""
    if _orjson_floats_are_python():
        digits = data.translate(_DIGITS_AS_ZERO)
        if not any(wide in digits for wide in _WIDE_INTEGERS):
            try:
                return orjson.loads(data)
            except ValueError:
                pass
    return json.loads(data)


def _body_of(data: bytes, record: dict) -> bytes:
    """The body (:func:`signed_body`) of canonical bytes ``data`` of ``record``: the bytes without the top-level
    members named in :data:`SEAL_FIELDS` (a top-level member starts a line with exactly two spaces and a quote;
    nested lines are indented further and strings hold no raw newline)."""
    if not any(k in record for k in SEAL_FIELDS):
        return data
    members = [m[:-1] if m.endswith(b",") else m for m in data[1:-3].split(b'\n  "')[1:]]
    seals = tuple(f'{k}": '.encode("ascii") for k in SEAL_FIELDS)
    kept = [m for m in members if not m.startswith(seals)]
    return b'{\n  "' + b',\n  "'.join(kept) + b"\n}\n" if kept else b"{}\n"


def read_sealed(data: bytes) -> Sealed:
    """A record read back from its canonical bytes, with the body its seal covers, in one encoding pass (each
    top-level member is encoded once and used for both the whole record and the body). NotCanonical: the bytes are
    not a record (:func:`parse_record`) or not its canonical encoding (keys sorted, 2-space indent, ASCII, shortest
    float repr, one final newline). Canonical bytes are read by orjson (:func:`_read_by_orjson`: about a quarter of
    the encoder's cost; the body cut from the bytes, :func:`_body_of`), else by the plain parser and the encoder
    (:func:`_read_canonical`: what orjson cannot write as canonical_json does); anything else is parsed again
    strictly here, so that what is wrong is named."""
    doc = _read_by_orjson(data)
    if doc is not None:
        return Sealed(doc, _body_of(data, doc))
    fast = _read_canonical(data)
    if fast is not None:
        return fast
    doc = parse_record(data)
    try:
        members = {k: _member(k, doc[k]) for k in sorted(doc)}
    except RecursionError:
        raise NotCanonical("nested too deeply to encode") from None
    except (TypeError, ValueError) as exc:
        raise NotCanonical(f"cannot be encoded canonically ({exc})") from None
    if _object(list(members.values())) != data:
        raise NotCanonical(
            "not in canonical form (keys sorted, 2-space indent, ASCII, shortest numbers, one final newline): "
            "the bytes were written by something else than the registry"
        )
    body = _object([m for k, m in members.items() if k not in SEAL_FIELDS])
    return Sealed(doc, body)
