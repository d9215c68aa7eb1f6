"""The malformed-passport corpus of issue 26 (item 6): passports whose content is not a passport's, each a
:class:`Malformed` with the bytes of a file (a loose file, not canonical) or a document to sign into a registry.

Every command that reads a passport must end each in one line and exit 2 (never an internal error, exit 3), with or
without ``--unverified``; ``passport verify``/``log``/``show``/``diff`` of a registry holding one must not crash.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from dataclasses import dataclass

from tests.acceptance.tampered import passport as small_passport


@dataclass(frozen=True)
class Malformed:
    """``change`` edits a copy of a good passport in place; ``raw`` (when given) makes the file's bytes from it
    instead of JSON (for what JSON cannot say: nesting deeper than any parser, NaN)."""

    name: str
    change: Callable[[dict], None]
    raw: Callable[[dict], bytes] | None = None
    usable: bool = False  # what a consumer reads is fine (an unknown field is odd): it may be used


def _set(path: str, value) -> Callable[[dict], None]:
    def change(doc: dict) -> None:
        *head, last = path.split(".")
        d = doc
        for k in head:
            d = d[k]
        d[last] = value

    return change


def _deep(depth: int):
    value: list = []
    for _ in range(depth):
        value = [value]
    return value


CORPUS: tuple[Malformed, ...] = (
    Malformed("singular-K", _set("coefficients.K", [[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]])),
    Malformed("zero-K", _set("coefficients.K", [[0.0] * 3] * 3)),
    Malformed("K-not-3x3", _set("coefficients.K", [[1.0, 0.0], [0.0, 1.0]])),
    Malformed("K-strings", _set("coefficients.K", "abc")),
    Malformed("K-huge", _set("coefficients.K", [[1e308, 0.0, 0.0], [0.0, 1e308, 0.0], [0.0, 0.0, 1e308]])),
    Malformed("U0-object", _set("coefficients.U0", {"x": 1})),
    Malformed("U0-integer-beyond-float", _set("coefficients.U0", [10**400, 0, 0])),  # (was OverflowError: exit 3)
    Malformed("coefficients-null", _set("coefficients", None)),
    Malformed("order-1e6", _set("thermal_model.order", 10**6)),
    Malformed(  # (a file only: 21 MB of coefficients is more than any registry writer would publish quickly)
        "order-1e6-coefficients",
        lambda d: d["thermal_model"].update(
            order=10**6, alpha={a: [1e-9] * 10**6 for a in "xyz"}, beta={a: [0.0] for a in ("xx", "yy", "zz")}
        ),
        raw=lambda d: json.dumps(d).encode(),
    ),
    Malformed("order-negative", _set("thermal_model.order", -3)),
    Malformed("thermal-model-list", _set("thermal_model", [])),
    Malformed("thermal-kind-unknown", _set("thermal_model.kind", "spline")),
    Malformed(
        "piecewise-unsorted",
        _set("thermal_model", {"kind": "piecewise_linear", "breakpoints_c": [20.0, -40.0], "segments": [{}]}),
    ),
    Malformed("alpha-strings", _set("thermal_model.alpha", {"x": ["a"], "y": ["b"], "z": ["c"]})),
    Malformed("normal-temp-string", _set("normal_temp_c", "20")),
    Malformed("g-null", _set("g_local_mps2", None)),
    Malformed("valid-temp-strings", _set("valid_temp_c", ["a", "b"])),
    Malformed("per-plateau-number", _set("per_plateau", 5)),
    Malformed("per-plateau-null-rows", _set("per_plateau", [None, None])),
    Malformed("verification-numbers", _set("verification", [1, 2])),
    Malformed("status-number", _set("status", 5)),
    Malformed("version-string", _set("version", "3")),
    Malformed("uncertainty-string", _set("uncertainty", "x")),
    Malformed("uncertainty-K-strings", _set("uncertainty", {"coefficients": {"K": "abc", "U0": [1, 2, 3]}})),
    Malformed("provenance-list", _set("provenance", [])),
    Malformed("rate-terms-wrong", _set("rate_terms", {"order": "a"})),
    Malformed("extended-model-number", _set("extended_model", 5)),
    Malformed("notes-number", _set("notes", 5)),
    Malformed("deep-nesting-field", _set("thermal_model.alpha", {"x": _deep(200), "y": [0.0], "z": [0.0]})),
    Malformed("deep-nesting-extra", _set("x_extra", _deep(400)), usable=True),
    Malformed(
        "deep-nesting-100k",
        lambda d: None,
        raw=lambda d: json.dumps(d)[:-1].encode() + b', "x": ' + b"[" * 100_000 + b"]" * 100_000 + b"}",
    ),
    Malformed("nan-literal", lambda d: None, raw=lambda d: json.dumps({**d, "normal_temp_c": float("nan")}).encode()),
    Malformed("not-an-object", lambda d: None, raw=lambda d: b"[1, 2, 3]"),
)


def good_passport() -> dict:
    """A passport every consumer takes (the tampered corpus's small passport, made complete enough)."""
    doc = small_passport("AU-0701", 1)
    doc.update(valid_temp_c=[-40.0, 70.0], per_plateau=[], notes=[], output_unit="V")
    return doc


def malformed(m: Malformed) -> dict:
    doc = copy.deepcopy(good_passport())
    m.change(doc)
    return doc


def file_bytes(m: Malformed) -> bytes:
    doc = malformed(m)
    return m.raw(doc) if m.raw else json.dumps(doc).encode()
