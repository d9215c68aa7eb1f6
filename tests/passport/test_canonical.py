"""Canonical bytes (issue 26 item 5): a record read back must BE its canonical encoding; duplicate keys, NaN, other
layouts and nesting too deep are refused as a phrase, never a crash; the one-pass reading gives the same bytes as
the encoder."""

from __future__ import annotations

import json

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from pipeline.passport.canonical import (
    NotCanonical,
    Sealed,
    _read_canonical,
    canonical_json,
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
    try:
        expected = _reference(data)
    except NotCanonical:
        expected = None
    try:
        sealed = read_sealed(data)
        got = (sealed.record, sealed.body)
    except NotCanonical:
        got = None
    assert got == expected
    if got is not None:
        assert list(got[0]) == list(expected[0])  # the same key order as the strict parse
