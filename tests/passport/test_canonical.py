"""Canonical bytes (issue 26 item 5): a record read back must BE its canonical encoding; duplicate keys, NaN, other
layouts and nesting too deep are refused as a phrase, never a crash; the one-pass reading gives the same bytes as
the encoder."""

from __future__ import annotations

import json
import re

import orjson
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from pipeline.passport.canonical import (
    NotCanonical,
    Sealed,
    _orjson_floats_are_python,
    _read_by_orjson,
    _read_canonical,
    canonical_json,
    parse_canonical,
    parse_record,
    read_sealed,
    signed_body,
)

scalars = st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False, allow_infinity=False)
texts = st.text(st.characters(codec="utf-8"), max_size=8)
values = st.recursive(
    scalars | texts, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(texts, inner, max_size=4)
)
records = st.dictionaries(texts | st.sampled_from(["content_sha256", "signature"]), values, max_size=6)


@settings(max_examples=100, deadline=None)
@given(records)
def test_read_sealed_is_the_inverse_of_the_encoder(record):
    data = canonical_json(record)
    sealed = read_sealed(data)
    assert sealed.record == json.loads(data)
    assert sealed.body == signed_body(record)


any_floats = st.floats() | st.sampled_from([float("inf"), -float("inf"), float("nan"), -0.0, 1e16, 1e-5])
odd_texts = st.sampled_from(["inf", " inf", ": -inf,", " nan", "nan,", "\x7f", '\u00e9\n"\\', "a: inf"])
any_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | any_floats | texts | odd_texts,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.tuples(inner)
        | st.dictionaries(texts | odd_texts, inner, max_size=4)
        | st.dictionaries(st.integers(-3, 3), inner, max_size=2)
    ),
)


def _dumps_or_error(value):
    try:
        return json.dumps(value, sort_keys=True, indent=2, ensure_ascii=True, allow_nan=False) + "\n"
    except (TypeError, ValueError) as exc:
        return type(exc), str(exc)


@settings(max_examples=300, deadline=None)
@given(any_values)
@example(float("inf"))  # (a bare non-finite float: was written as 'inf')
@example(float("nan"))
@example([-float("inf")])
def test_canonical_json_is_json_dumps_byte_for_byte(value):
    """The encoder (joins, not json's pure-Python indent encoder) writes exactly json.dumps' text, and raises its
    error otherwise: non-finite floats anywhere, strings that look like them, tuples, int keys, every escape."""
    try:
        ours = canonical_json(value).decode("ascii")
    except (TypeError, ValueError) as exc:
        ours = type(exc), str(exc)
    assert ours == _dumps_or_error(value)


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        (b'{\n  "a": 1,\n  "a": 2\n}\n', 'duplicate key "a"'),
        (b'{\n  "a": NaN\n}\n', "non-finite number NaN"),
        (b'{\n  "a": Infinity\n}\n', "non-finite number Infinity"),
        (b'{"a": 1}\n', "not in canonical form"),
        (b'{\n  "b": 1,\n  "a": 2\n}\n', "not in canonical form"),
        (b'{\n  "a": 1e5\n}\n', "not in canonical form"),
        (b'{\n  "a": 1\n}', "not in canonical form"),
        (b'{\n  "a": "\xc3\xa9"\n}\n', "not in canonical form"),
        (b"[1, 2]\n", "not a JSON object"),
        (b'{"a": ', "unparsable JSON"),
        (b'{"a": "\xff"}', "UTF-8"),
        (b'{"a": ' + b"[" * 200_000 + b"]" * 200_000 + b"}", "nested too deeply"),
    ],
)
def test_what_is_not_a_canonical_record_is_a_phrase(data, fragment):
    with pytest.raises(NotCanonical) as info:
        read_sealed(data)
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_duplicates_are_found_at_any_depth():
    with pytest.raises(NotCanonical, match='duplicate key "K"'):
        parse_record(b'{"c": {"K": 1, "K": 2}}')


def _reference(data: bytes):
    """read_sealed's definition: the strict parse, the bytes must be the record's canonical_json, the body its
    signed_body (all by the encoder, none of the shortcut's steps)."""
    doc = parse_record(data)
    if canonical_json(doc) != data:
        raise NotCanonical("not in canonical form")
    return doc, signed_body(doc)


def _decided(data: bytes, refused) -> tuple:
    """(the definition's (record, body) or None when it raises one of ``refused``, read_sealed's or None when it
    raises NotCanonical)."""
    try:
        expected = _reference(data)
    except refused:
        expected = None
    try:
        sealed = read_sealed(data)
        got = (sealed.record, sealed.body)
    except NotCanonical:
        got = None
    return expected, got


EDITS = [b" ", b"\n", b"\n  ", b",", b"\t", b"}", b"]", b'"', b"\\", b":", b"0", b"\r"]


@settings(max_examples=100, deadline=None)
@given(
    st.dictionaries(
        texts | st.sampled_from(["content_sha256", "signature", "a,\n", '{"[', "x"]), values, min_size=1, max_size=6
    ),
    st.lists(
        st.tuples(
            st.sampled_from(["insert", "delete", "replace", "swap", "indent", "shift"]),
            st.integers(0, 10**6),
            st.sampled_from(EDITS),
        ),
        max_size=3,
    ),
)
def test_the_shortcut_for_canonical_bytes_decides_as_the_encoder(record, edits):
    """read_sealed parses canonical bytes with the plain parser (no duplicate-key hook; the bytes compared with the
    record's encoding): on canonical bytes and on the same bytes edited (a space, newline, indent, comma, bracket,
    quote inserted, deleted or replaced anywhere; lines swapped; one line indented differently; a line break moved)
    it accepts exactly what the definition (strict parse, canonical_json, signed_body) accepts, with the same record
    (key order too) and body, and refuses the rest."""
    data = canonical_json(record)
    assert _read_canonical(data) == read_sealed(data) == Sealed(record, signed_body(record))  # the shortcut answers
    for kind, where, text in edits:
        k = where % (len(data) + 1)
        if kind == "insert":
            data = data[:k] + text + data[k:]
        elif kind == "delete":
            data = data[:k] + data[k + 1 :]
        elif kind == "replace":
            data = data[:k] + text + data[k + 1 :]
        elif kind == "swap" and data.count(b"\n") > 2:
            lines = data.split(b"\n")
            j = k % (len(lines) - 2)
            lines[j], lines[j + 1] = lines[j + 1], lines[j]
            data = b"\n".join(lines)
        elif kind == "indent" and b"\n  " in data:
            at = data.find(b"\n  ", k % len(data))
            at = at if at >= 0 else data.find(b"\n  ")
            data = data[:at] + b"\n" + text.strip(b"\n") + data[at + 1 :]
        elif kind == "shift" and b"\n" in data[:-1]:  # a line break moved by a character or two, indent kept
            at = data.rfind(b"\n", 0, max(k, 1))
            at = at if at >= 0 else data.find(b"\n")
            end = at + 1 + len(data[at + 1 :]) - len(data[at + 1 :].lstrip(b" "))
            rest = data[:at] + data[end:]
            to = min(max(at + (1 if k % 2 else -1) * (1 + k % 3 // 2), 0), len(rest))
            data = rest[:to] + data[at:end] + rest[to:]
    expected, got = _decided(data, NotCanonical)
    assert got == expected
    if got is not None:
        assert list(got[0]) == list(expected[0])  # the same key order as the strict parse


# ---------------------------------------------------------------------------------------------------------------
# the orjson path (_read_by_orjson): the same answer as the definition on every byte string

json_floats = st.floats(allow_nan=False, allow_infinity=False) | st.sampled_from(
    [-0.0, 1e-5, 1.5e-5, 9.999999999999999e-05, 1e-4, 1e-7, 2.5e-06, 1e-10, 1e15, 1e16, 5e-324, 1.7976931348623157e308]
)
odd_chars = st.text(st.characters(), max_size=6) | st.sampled_from(
    ["\x7f", "\x1f", "\x00", "\u00e9", "\ud800", "\U0001f600", "e-7", "0.00001", "a,\n", " 1e-7,\n", "\u2028"]
)
wide_ints = st.integers(-(2**70), 2**70) | st.sampled_from([2**63, 2**64 - 1, 2**64, -(2**63), -(2**63) - 1])
odd_values = st.recursive(
    st.none() | st.booleans() | wide_ints | json_floats | odd_chars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(odd_chars, inner, max_size=4),
    max_leaves=12,
)
_NUMBER = re.compile(rb"(?<=[ \n])-?[0-9][-+.0-9eE]*(?=,?\n)")
_ESCAPE = re.compile(rb"\\u[0-9a-f]{4}|\\[nrtbf\"\\]")


def _respell_number(token: bytes, how: int) -> bytes:
    """Another text of (about) the same number: orjson's, upper case, a trailing zero, a plus sign, %e, -0, ...
    (a token no longer a number after an earlier edit: as it is)"""
    try:
        x = float(token)
    except ValueError:
        return token
    return [
        orjson.dumps(x),
        token.upper(),
        token + b"0" if b"." in token else token + b".0",
        token.replace(b"e-", b"e-0"),
        token.replace(b"e-0", b"e-"),
        token.replace(b"e+", b"e"),
        f"{x:.17g}".encode(),
        f"{x:e}".encode(),
        b"-" + token if not token.startswith(b"-") else token[1:],
        b"-0" if token in (b"0", b"0.0") else b"0" + token.lstrip(b"-"),
    ][how % 10]


def _respell_escape(escape: bytes, how: int) -> bytes:
    """Another text of (about) the same character: upper-case hex, the raw character, a \\u form of a short escape."""
    char = json.loads(b'"' + escape + b'"')
    raw = char.encode("utf-8", "surrogatepass")
    return [escape.upper().replace(b"\\U", b"\\u"), raw, b"\\u%04x" % ord(char) if len(char) == 1 else raw][how % 3]


@settings(max_examples=300, deadline=None)
@given(
    st.dictionaries(odd_chars | st.sampled_from(["content_sha256", "signature"]), odd_values, min_size=1, max_size=5),
    st.lists(
        st.tuples(st.sampled_from(["number", "escape", "orjson", "byte"]), st.integers(0, 10**6), st.integers(0, 9)),
        max_size=3,
    ),
)
@example({"a": 1e-7, "b": [1.5e-5, -0.0], "c": 1e16}, [("orjson", 0, 0)])
@example({"a": 1e-7}, [("number", 0, 0)])
@example({"a": 1.5e-5}, [("number", 0, 0)])
@example({"a": "\x7f"}, [("byte", 0, 0)])
@example({"a": "x\x7f"}, [("escape", 0, 1)])  # (a raw DEL inside a string: orjson reads and writes it raw)
@example({"a": [10.00001, -10.000015, 100.00001]}, [])  # (0.0000 inside a number of another decade)
@example({"a": "\u00e9", "\u00e9": 1}, [("orjson", 0, 0)])
@example({"a": 2**64}, [])
@example({"a": [1.0000000000000001e31]}, [("number", 0, 2)])  # (1e+310: inf, not encodable)
@example({"a": [1e-05]}, [("number", 0, 2), ("number", 0, 0)])  # (1e-05.0: no number)
@example({"a": "\ud800"}, [])
def test_the_orjson_path_decides_as_the_encoder(record, edits):
    """read_sealed's first path (orjson reads and writes the bytes; floats compared in Python's repr; non-ASCII and
    DEL refused) accepts exactly what the definition (strict parse, canonical_json, signed_body) accepts, with the
    same record (key order too) and body: on canonical bytes of records with any float (-0.0, 1e-05 vs orjson's
    0.00001, 1e-07 vs 1e-7, subnormals, 1e16), any character (controls, DEL, non-ASCII keys, lone surrogates),
    integers beyond 64 bits; and on the same bytes with a number spelled otherwise (orjson's text, upper case, a
    trailing zero, a padded or unpadded exponent, -0), an escape spelled otherwise (upper-case hex, the raw character,
    \\u for \\n), orjson's own text of the whole record, or a raw DEL/non-ASCII byte inserted."""
    data = canonical_json(record)
    for kind, where, how in edits:
        if kind == "number" and (tokens := list(_NUMBER.finditer(data))):
            m = tokens[where % len(tokens)]
            data = data[: m.start()] + _respell_number(m[0], how) + data[m.end() :]
        elif kind == "escape" and (escapes := list(_ESCAPE.finditer(data))):
            m = escapes[where % len(escapes)]
            data = data[: m.start()] + _respell_escape(m[0], how) + data[m.end() :]
        elif kind == "orjson":
            try:
                data = orjson.dumps(json.loads(data), option=orjson.OPT_INDENT_2 | orjson.OPT_SORT_KEYS) + b"\n"
            except (TypeError, ValueError):
                pass
        elif kind == "byte":
            k = where % (len(data) + 1)
            data = data[:k] + [b"\x7f", "\u00e9".encode(), b"\t", b"\x1f"][how % 4] + data[k:]
    # (ValueError: a number beyond a float's range, read as inf, cannot be encoded)
    expected, got = _decided(data, (NotCanonical, ValueError))
    assert repr(got) == repr(expected)  # (repr: 1 and 1.0, 0.0 and -0.0 are ==; the key order counts too)
    fast = _read_by_orjson(data)
    assert fast is None or (expected is not None and repr(fast) == repr(expected[0]))
    if expected is not None:  # bytes that passed, read again from the cache: as json.loads reads them
        assert repr(parse_canonical(data)) == repr(json.loads(data))


@settings(max_examples=300, deadline=None)
@given(json_floats, wide_ints.filter(lambda n: -(2**63) <= n < 2**64))
@example(1.5e-5, 0)
@example(-9.999999999999999e-05, 0)
def test_the_orjson_path_reads_every_float_and_64_bit_integer(x, n):
    """Canonical bytes of any float (in the decade orjson writes out, with a one-digit exponent, -0.0, subnormal, the
    largest) and any 64-bit integer go by the orjson path, not only by the fallback: it is the path the registry's
    files take."""
    record = {"a": x, "b": [x, -x, n], "c": {"d": [[x]], "e": n}, "signature": {"v": x}}
    data = canonical_json(record)
    assert _orjson_floats_are_python()
    assert repr(_read_by_orjson(data)) == repr(record)
    assert repr(read_sealed(data)) == repr(Sealed(record, signed_body(record)))
    assert repr(parse_canonical(data)) == repr(record)
