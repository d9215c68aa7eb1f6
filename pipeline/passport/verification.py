"""One verification path for every consumer of a passport (apply, export, report, diagnose, the differential base,
trends): is this the passport a trusted station wrote, unchanged, and is it a passport at all?

Two questions, always asked in this order:

1. Integrity and trust (:func:`check_sealed`): the bytes are the record's canonical encoding (no duplicate keys, no
   other layout: :func:`pipeline.passport.canonical.read_sealed`), ``content_sha256`` is the hash of the content,
   and ``signature`` is a trusted station's over the same bytes (:mod:`pipeline.passport.signing`). For a version in
   a registry the registry adds its parent link, its log row and its approvals
   (:meth:`pipeline.passport.registry.Registry.load_state`); a loose file
   (:func:`pipeline.passport.registry.load_passport_file`) has no parent
   to check, and one inside a registry's unit folder is checked as that registry's version. A passport that fails
   is refused in one line (:class:`UntrustedPassport`, exit 2) unless the command was given ``--unverified``: it is
   then used, and every output says so (:attr:`Verification.label`).
2. Well-formedness (:func:`check_content`), asked even with ``--unverified``: every field a consumer reads has its
   type and shape (3x3 finite K, polynomial orders and list lengths within bounds, finite temperatures, ...), K is
   invertible at T0. A malformed passport is one line and exit 2, never an internal error.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pipeline.errors import RegistryError, ThermocalError
from pipeline.passport.canonical import NotCanonical, parse_record, read_sealed
from pipeline.passport.signing import TrustStore, verify_record

__all__ = [
    "MAX_ORDER",
    "MalformedPassport",
    "UntrustedPassport",
    "Verification",
    "check_content",
    "check_schema",
    "check_sealed",
]

#: Highest polynomial order (thermal model, rate terms) a passport may carry; more is not a calibration.
MAX_ORDER = 8
#: Most entries of a passport's lists (plateaus, verification rows, breakpoints, notes).
MAX_ITEMS = 100_000
#: K is refused as singular beyond this condition number (a three-axis unit's is about 1).
MAX_K_CONDITION = 1e6
UNVERIFIED_HINT = "--unverified uses it anyway, and says so in every output"


class UntrustedPassport(RegistryError):
    """A passport that does not verify (altered, unsigned, signed by an untrusted key, not canonical, a broken
    parent link): one line, exit 2."""


class MalformedPassport(ThermocalError):
    """A passport whose content is not a passport's (a field of the wrong type or shape, a singular K)."""


@dataclass(frozen=True)
class Verification:
    """How a passport was checked: ``verified`` (every check passed), else ``problem`` (the first failed check,
    with ``--unverified``); ``key_id`` the signing key; ``loose``: a file outside a registry (no parent link to
    check); ``subject`` names it (``AU-0001 v3`` or the file)."""

    subject: str
    verified: bool
    problem: str | None = None
    key_id: str | None = None
    loose: bool = False

    @property
    def label(self) -> str:
        """One phrase for every output: ``verified (hash, signature by key ..., parent link)`` or
        ``UNVERIFIED (--unverified): <problem>``."""
        if not self.verified:
            return f"UNVERIFIED (--unverified): {self.problem}"
        what = "canonical bytes, hash, signature by trusted key " + str(self.key_id)
        return f"verified ({what}{'; a loose file: no parent link to check' if self.loose else ', parent link'})"

    def as_dict(self) -> dict:
        return {
            "verified": self.verified,
            "problem": self.problem,
            "key_id": self.key_id,
            "loose_file": self.loose,
            "label": self.label,
        }


# ---------------------------------------------------------------------------------------------------------------
# integrity and trust of one record


@dataclass(frozen=True)
class SealCheck:
    """:func:`check_sealed`'s answer: the record (None when the bytes are not one), the problems found (empty:
    canonical, self-hash right, signed by a trusted key), the signing key's id and whether it is this station's."""

    record: dict | None
    problems: tuple[str, ...]
    key_id: str | None = None
    own: bool = False
    canonical: bool = False
    self_hash_ok: bool = False

    @property
    def ok(self) -> bool:
        return not self.problems


def check_sealed(data: bytes, trust: TrustStore) -> SealCheck:
    """The record in ``data`` and what is wrong with its seal: not canonical (duplicate keys, another layout), a
    stored ``content_sha256`` that is not the content's, no signature or one no trusted key made over these bytes."""
    try:
        sealed = read_sealed(data)
    except NotCanonical as exc:
        try:
            loose = parse_record(data)  # a record all the same (e.g. another layout): the rest is still named
        except NotCanonical:
            return SealCheck(None, (f"not a record: {exc}",))
        return SealCheck(loose, (f"not its canonical bytes: {exc}",))
    record = sealed.record
    if record.get("content_sha256") != sealed.body_sha256:
        return SealCheck(record, ("stored content_sha256 does not match the content (altered)",), canonical=True)
    sig = verify_record(record, trust, sealed.body)
    problems = () if sig.ok else (str(sig.problem),)
    return SealCheck(record, problems, sig.key_id, sig.own, canonical=True, self_hash_ok=True)


#: A passport file larger than this is not read (a calibration's is tens of kB; an extended one a few hundred).
MAX_PASSPORT_BYTES = 8 << 20


def check_schema(doc: dict, subject: str) -> None:
    from pipeline.passport.document import SCHEMA_ID

    if doc.get("schema") != SCHEMA_ID:
        raise MalformedPassport(f"not a {SCHEMA_ID} document (its schema is {_short(doc.get('schema'))})", path=subject)


# ---------------------------------------------------------------------------------------------------------------
# well-formedness


class _Bad(Exception):
    """A malformed field: ``where`` its path, ``what`` is wrong with it. A container calls each of its fields with an
    empty path and puts the field's own path in front only when one fails (:meth:`under`): a well-formed passport
    builds no path string."""

    def __init__(self, where: str, what: str):
        super().__init__(where, what)
        self.where, self.what = where, what

    def __str__(self) -> str:
        return f"{self.where}: {self.what}"

    def under(self, path: str) -> _Bad:
        """This error, its path now below ``path`` (the failing field's path in its container)."""
        w = self.where
        self.where = path if not w else path + w if w[0] in ".[" else f"{path}.{w}"
        return self


Check = Callable[[Any, str], None]


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _kind(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
        type(value), "a number"
    )


def num(value: Any, where: str) -> None:
    if type(value) is float or type(value) is int:  # (the usual case first: JSON's numbers)
        if -1e300 <= value <= 1e300:
            return
    elif isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Bad(where, f"{_kind(value)} where a number belongs")
    if not -1e300 <= value <= 1e300:  # NaN, infinities and integers too large for a float too
        raise _Bad(where, f"{_short(value)} is not a finite number")


def integer(lo: int, hi: int) -> Check:
    def check(value: Any, where: str) -> None:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _Bad(where, f"{_kind(value)} where an integer belongs")
        if not lo <= value <= hi:
            raise _Bad(where, f"{value} is outside {lo}..{hi}")

    return check


def text(value: Any, where: str) -> None:
    if not isinstance(value, str):
        raise _Bad(where, f"{_kind(value)} where a string belongs")


def anything(value: Any, where: str) -> None:
    return None


def nullable(check: Check) -> Check:
    def inner(value: Any, where: str) -> None:
        if value is not None:
            check(value, where)

    return inner


def one_of(*allowed: Any) -> Check:
    def check(value: Any, where: str) -> None:
        if value not in allowed:
            raise _Bad(where, f"{_short(value)} is not one of {', '.join(map(str, allowed))}")

    return check


def list_of(item: Check, min_len: int = 0, max_len: int = MAX_ITEMS) -> Check:
    def check(value: Any, where: str) -> None:
        if not isinstance(value, list):
            raise _Bad(where, f"{_kind(value)} where a list belongs")
        if not min_len <= len(value) <= max_len:
            what = f"exactly {min_len}" if min_len == max_len else f"{min_len}..{max_len}"
            raise _Bad(where, f"{len(value)} entries, expected {what}")
        for k, v in enumerate(value):
            try:
                item(v, "")
            except _Bad as exc:
                raise exc.under(f"{where}[{k}]") from None

    return check


def dict_of(item: Check, keys: tuple[str, ...] | None = None, max_len: int = 1000) -> Check:
    """An object whose values all pass ``item``; with ``keys``, exactly those keys."""

    def check(value: Any, where: str) -> None:
        if not isinstance(value, dict):
            raise _Bad(where, f"{_kind(value)} where an object belongs")
        if keys is not None and set(value) != set(keys):
            raise _Bad(where, f"keys {', '.join(sorted(map(str, value))) or '(none)'}, expected {', '.join(keys)}")
        if len(value) > max_len:
            raise _Bad(where, f"{len(value)} keys")
        for k, v in value.items():
            try:
                item(v, "")
            except _Bad as exc:
                raise exc.under(f"{where}.{k}") from None

    return check


def obj(required: dict[str, Check] | None = None, optional: dict[str, Check] | None = None) -> Check:
    """An object with these fields (others are allowed and not read)."""

    def check(value: Any, where: str) -> None:
        if not isinstance(value, dict):
            raise _Bad(where, f"{_kind(value)} where an object belongs")
        for key, c in (required or {}).items():
            if key not in value:
                raise _Bad(where, f"field {key!r} is missing")
            try:
                c(value[key], "")
            except _Bad as exc:
                raise exc.under(f"{where}.{key}" if where else key) from None
        for key, c in (optional or {}).items():
            if key in value:
                try:
                    c(value[key], "")
                except _Bad as exc:
                    raise exc.under(f"{where}.{key}" if where else key) from None

    return check


vec3 = list_of(num, 3, 3)
mat3 = list_of(vec3, 3, 3)
vec3_sigma = list_of(nullable(num), 3, 3)
mat3_sigma = list_of(list_of(nullable(num), 3, 3), 3, 3)
temperature = num
ALPHA_KEYS, BETA_KEYS, GAMMA_KEYS = ("x", "y", "z"), ("xx", "yy", "zz"), ("xy", "xz", "yx", "yz", "zx", "zy")


def _polynomial(value: Any, where: str) -> None:
    obj({"order": integer(0, MAX_ORDER)})(value, where)
    n = value["order"]
    if n:
        coefficients = list_of(num, n, n)
        obj(
            {
                "alpha": dict_of(coefficients, ALPHA_KEYS),
                "beta": dict_of(coefficients, BETA_KEYS),
                "gamma": dict_of(coefficients, GAMMA_KEYS),
            }
        )(value, where)


def _piecewise(value: Any, where: str) -> None:
    obj({"breakpoints_c": list_of(temperature, 1, 1000), "segments": list_of(anything, 0, 999)})(value, where)
    bp, segments = value["breakpoints_c"], value["segments"]
    if any(b <= a for a, b in zip(bp, bp[1:])):
        raise _Bad(f"{where}.breakpoints_c", "not increasing")
    if len(segments) != len(bp) - 1:
        raise _Bad(f"{where}.segments", f"{len(segments)} segments for {len(bp)} breakpoints")
    segment = obj(
        {
            "alpha": dict_of(num, ALPHA_KEYS),
            "beta": dict_of(num, BETA_KEYS),
            "gamma": dict_of(num, GAMMA_KEYS),
        },
        {"t_lo_c": temperature, "t_hi_c": temperature},
    )
    for k, s in enumerate(segments):
        segment(s, f"{where}.segments[{k}]")


def thermal_model(value: Any, where: str) -> None:
    obj({"kind": one_of("polynomial", "piecewise_linear")})(value, where)
    (_polynomial if value["kind"] == "polynomial" else _piecewise)(value, where)


def _rate_terms(value: Any, where: str) -> None:
    obj(
        {"order": integer(0, MAX_ORDER), "dt_order": integer(0, MAX_ORDER), "temp_smooth_s": num},
        {"lag_tau_s": num},
    )(value, where)
    n = value["order"] * (value["dt_order"] + 1)
    flat = list_of(num, n, n)
    nested = list_of(list_of(num, value["dt_order"] + 1, value["dt_order"] + 1), value["order"], value["order"])

    def either(v: Any, w: str) -> None:
        try:
            nested(v, w)
        except _Bad:
            flat(v, w)

    obj({"alpha_rate": dict_of(either, ALPHA_KEYS), "beta_rate": dict_of(either, BETA_KEYS)})(value, where)
    cross = value.get("cross_axis_abs")
    if cross:
        dict_of(list_of(num, 1, MAX_ORDER))(cross, f"{where}.cross_axis_abs")
        if not set(cross) <= set(GAMMA_KEYS) or len({len(v) for v in cross.values()}) > 1:
            raise _Bad(f"{where}.cross_axis_abs", "keys or lengths are not a cross-axis model's")


_PASSPORT = obj(
    required={
        "coefficients": obj({"K": mat3, "U0": vec3}),
        "thermal_model": thermal_model,
    },
    optional={
        "schema": text,
        "unit": nullable(text),
        "version": nullable(integer(1, 10**9)),
        "parent_sha256": nullable(text),
        "created_utc": nullable(text),
        "normal_temp_c": temperature,
        "g_local_mps2": num,
        "output_unit": text,
        "method": nullable(text),
        "status": nullable(one_of("pass", "fail", "unverified")),
        "valid_temp_c": nullable(list_of(temperature, 2, 2)),
        "notes": list_of(text),
        "per_plateau": list_of(
            obj({"temp_c": temperature, "K": mat3, "U0": vec3}, {"positions": list_of(text, 0, 1000)})
        ),
        "plateaus": list_of(obj({"temp_c": temperature}, {"positions": list_of(text, 0, 1000)})),
        "verification": list_of(
            obj(
                {"temp_c": temperature, "position": text},
                {
                    "dg_uncompensated_g": nullable(num),
                    "dg_method1_g": nullable(num),
                    "dg_method2_g": nullable(num),
                    "tolerance_g": nullable(num),
                },
            )
        ),
        "verification_summary": list_of(obj({}, {"temp_c": nullable(temperature), "n": integer(0, 10**9)})),
        "rate_terms": nullable(_rate_terms),
        "extended_model": nullable(obj()),
        "provenance": obj(
            {},
            {
                "inputs": list_of(obj({}, {"path": text, "sha256": text})),
                "settings": obj(),
                "code_version": text,
                "identity": text,
            },
        ),
        "uncertainty": nullable(
            obj(
                {},
                {
                    "coefficients": nullable(obj({}, {"K": nullable(mat3_sigma), "U0": nullable(vec3_sigma)})),
                    "per_plateau": nullable(
                        list_of(obj({}, {"K": nullable(mat3_sigma), "U0": nullable(vec3_sigma), "temp_c": num}))
                    ),
                    "thermal_model": nullable(obj()),
                    "rate_terms": nullable(obj()),
                    "undetermined": dict_of(text),
                    "fixed_by_convention": dict_of(text),
                    "basis": nullable(obj()),
                },
            )
        ),
    },
)


def check_content(doc: Any, subject: str | None = None) -> None:
    """MalformedPassport (one line naming ``subject`` and the field) when ``doc`` is not well-formed: the fields
    every consumer reads have their types, shapes and bounds (:data:`MAX_ORDER`, :data:`MAX_ITEMS`), the
    uncertainties mirror them, and K at T0 is invertible (condition number below :data:`MAX_K_CONDITION`).
    Deeply nested or huge documents are refused, never a crash."""
    try:
        _PASSPORT(doc, "")
        _sigma_shapes(doc)
    except _Bad as exc:
        raise MalformedPassport(f"malformed passport: {exc}", path=subject) from None
    except RecursionError:
        raise MalformedPassport("malformed passport: nested too deeply", path=subject) from None
    import numpy as np

    K = np.asarray(doc["coefficients"]["K"], dtype=float)
    cond = float(np.linalg.cond(K))
    if not math.isfinite(cond) or cond > MAX_K_CONDITION:
        raise MalformedPassport(
            f"malformed passport: coefficients.K is singular (condition number {cond:.3g}): no specific force can "
            "be recovered from it",
            path=subject,
        )


def _sigma_shapes(doc: dict) -> None:
    """The uncertainty of the thermal model mirrors it: lists of numbers or nulls per coefficient key."""
    sig = (doc.get("uncertainty") or {}).get("thermal_model")
    if not sig:
        return
    item = list_of(nullable(num), 0, MAX_ORDER)
    for part in ("alpha", "beta", "gamma"):
        if part in sig and sig[part] is not None:
            dict_of(nullable(item) if sig.get("kind") != "piecewise_linear" else anything)(
                sig[part], f"uncertainty.thermal_model.{part}"
            )
