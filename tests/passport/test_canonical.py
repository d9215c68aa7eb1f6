"""Canonical bytes (issue 26 item 5): a record read back must BE its canonical encoding; duplicate keys, NaN, other
layouts and nesting too deep are refused as a phrase, never a crash; the one-pass reading gives the same bytes as
the encoder."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.passport.canonical import NotCanonical, canonical_json, parse_record, read_sealed, signed_body

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
