"""Which changes between two passport versions are real: a change of a constant or thermal coefficient is
*significant* when it exceeds its expanded combined uncertainty, ``|delta| > k * sqrt(u1**2 + u2**2)`` with ``u1``,
``u2`` the two versions' standard uncertainties of that number (their ``uncertainty`` blocks) and the coverage factor
``k`` (2 by default: about 95 % for a normal error; 1 marks everything beyond one combined standard uncertainty).

Used by :meth:`pipeline.passport.registry.Registry.diff` to annotate its entries, and by the readable
``passport diff`` output (:func:`significant_changes`), in the entry's engineering unit (ppm of gain, micro-g,
ppm/C^n, micro-g/C^n).
"""

from __future__ import annotations

import functools
import math
import re
from typing import Any

COVERAGE_FACTOR = 2.0

_CONST = re.compile(r"^(K)\.([xyz])([xyz])$|^(U0)\.([xyz])$")
_POLY = re.compile(r"^(alpha|beta|gamma)\.([xyz]{1,2})\[(\d+)\]$")
_PIECE = re.compile(r"^segments\[(\d+)\]\.(alpha|beta|gamma)\.([xyz]{1,2})$")
_RATE = re.compile(r"^rate_terms\.(alpha_rate|beta_rate)\.([xyz]{1,2})\[(\d+)\]\[(\d+)\]$")
_CROSS_ABS = re.compile(r"^rate_terms\.cross_axis_abs\.([xyz]{2})\[(\d+)\]$")


def sigma_of(passport: dict, name: str) -> float | None:
    """The standard uncertainty a passport records for the diff entry ``name`` (``K.xy``, ``U0.z``,
    ``alpha.x[2]``, ``segments[0].beta.yy``, ``rate_terms.alpha_rate.x[1][0]``, ``rate_terms.cross_axis_abs.xy[2]``),
    in the entry's own unit; None when it records none."""
    return _number_at(passport.get("uncertainty") or {}, name)


def value_of(passport: dict, name: str) -> float | None:
    """The passport's value of the diff entry ``name`` (the names of :func:`sigma_of`), in the entry's own unit;
    None when it has none."""
    return _number_at(passport, name)


@functools.lru_cache(maxsize=4096)
def _path_of(name: str) -> tuple[str | int, ...] | None:
    """The keys and indices leading to the number named ``name`` (the names of :func:`sigma_of`) from the passport
    or its ``uncertainty`` block; None for another name. Each name is parsed once."""
    ax = "xyz"
    if m := _CONST.match(name):
        return (
            ("coefficients", "K", ax.index(m.group(2)), ax.index(m.group(3)))
            if m.group(1)
            else (
                "coefficients",
                "U0",
                ax.index(m.group(5)),
            )
        )
    if m := _POLY.match(name):
        return ("thermal_model", m.group(1), m.group(2), int(m.group(3)) - 1)
    if m := _PIECE.match(name):
        return ("thermal_model", "segments", int(m.group(1)), m.group(2), m.group(3))
    if m := _RATE.match(name):
        return ("rate_terms", m.group(1), m.group(2), int(m.group(3)) - 1, int(m.group(4)))
    if m := _CROSS_ABS.match(name):
        return ("rate_terms", "cross_axis_abs", m.group(1), int(m.group(2)) - 1)
    return None


def _number_at(block: dict, name: str) -> float | None:
    """The number named ``name`` in a passport (``block`` the passport) or its ``uncertainty`` block, which mirrors
    the passport's ``coefficients``, ``thermal_model`` and ``rate_terms``."""
    path = _path_of(name)
    if path is None:
        return None
    value: Any = block
    try:
        for key in path:
            value = value[key]
    except (KeyError, IndexError, TypeError):
        return None
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def annotate(entries: list[dict], old: dict, new: dict, k: float = COVERAGE_FACTOR) -> list[dict]:
    """Add to each diff entry ``uncertainty`` (combined standard uncertainty, the entry's unit),
    ``uncertainty_scaled`` (the same in ``scaled_unit``) and ``significant`` (True/False; None when either version
    records no uncertainty for it). ``delta_scaled / uncertainty_scaled`` is the change in sigmas."""
    for e in entries:
        u1, u2 = sigma_of(old, e["name"]), sigma_of(new, e["name"])
        if u1 is None or u2 is None or not isinstance(e.get("delta"), (int, float)):
            e.update(uncertainty=None, uncertainty_scaled=None, significant=None)
            continue
        u = math.hypot(u1, u2)
        scale = (e["delta_scaled"] / e["delta"]) if e.get("delta_scaled") is not None and e["delta"] else None
        e["uncertainty"] = u
        e["uncertainty_scaled"] = abs(u * scale) if scale is not None else None
        e["significant"] = bool(abs(e["delta"]) > k * u)
    return entries


def significant_changes(diff: dict) -> list[dict]:
    """The constants and thermal coefficients of a :meth:`Registry.diff` result whose change exceeds its expanded
    combined uncertainty, largest first (in sigmas); entries without an uncertainty are not among them."""
    rows = [
        e
        for e in diff.get("constants", []) + diff.get("thermal_model", []) + diff.get("rate_terms", [])
        if e.get("significant")
    ]
    return sorted(rows, key=lambda e: -abs(e["delta"]) / e["uncertainty"] if e["uncertainty"] else 0.0)


def significance_note(k: float = COVERAGE_FACTOR) -> dict[str, Any]:
    """How ``significant`` was decided (stored in the diff result)."""
    return {
        "coverage_factor": k,
        "rule": "significant when |delta| > coverage_factor * sqrt(u_old^2 + u_new^2), u the versions' "
        "standard uncertainties; null when a version records none",
    }
