"""The difference of two passport versions in physical units (docs/physics.md): changed constants and thermal
coefficients with their engineering scale (ppm of gain, micro-g) and significance, changed fields, settings and
inputs. ``thermocal passport diff`` prints it (:meth:`pipeline.passport.registry.Registry.diff`)."""

from __future__ import annotations

from typing import Any

from pipeline.passport.document import output_unit_of
from pipeline.passport.significance import annotate, significance_note
from pipeline.passport.text import per
from pipeline.positions import AXES


def diff_passports(a: dict, b: dict, *, unit: str, v1: int, v2: int) -> dict:
    """What changed from passport ``a`` (version ``v1`` of ``unit``) to ``b`` (version ``v2``), in the units of
    docs/physics.md.

    Returns {"unit", "v1", "v2", "constants", "thermal_model", "rate_terms", "fields", "settings", "inputs"}; the
    lists hold
    only what changed. A constant or thermal coefficient entry is {"name", "unit", "old", "new", "delta",
    "delta_scaled", "scaled_unit"}: K (the output unit per g: V/g, or (m/s^2)/g) also as ppm of the row's gain
    |Kii|, U0 (the output unit) as micro-g (delta/|Kii|), alpha (output unit/C^n) as micro-g/C^n, beta and gamma
    (1/C^n) as ppm/C^n; the differential method's rate terms (``rate_terms``: alpha_rate as micro-g/(C/min)^n/C^k,
    beta_rate as ppm/(C/min)^n/C^k, cross_axis_abs as ppm of the row's gain/C^m). ``fields`` are other changed
    values (status, normal temperature, output unit,
    thermal-model kind/order/breakpoints, code version) as {"name", "old", "new"}; ``settings`` the same for each
    changed setting (dotted names); ``inputs`` {"added", "removed"}.
    Constant and coefficient entries also carry ``uncertainty``, ``uncertainty_scaled`` and ``significant``
    (:mod:`pipeline.passport.significance`; rule in ``significance``).
    """
    gains = _gains_v_per_g(a) or _gains_v_per_g(b)
    u = output_unit_of(b)
    fields = [
        {"name": k, "old": a.get(k), "new": b.get(k)}
        for k in ("schema", "status", "normal_temp_c", "g_local_mps2")
        if a.get(k) != b.get(k)
    ]
    if output_unit_of(a) != u:
        fields.append({"name": "output_unit", "old": output_unit_of(a), "new": u})
    pa, pb = a.get("provenance") or {}, b.get("provenance") or {}
    if pa.get("code_version") != pb.get("code_version"):
        fields.append({"name": "provenance.code_version", "old": pa.get("code_version"), "new": pb.get("code_version")})
    thermal, thermal_fields = _diff_thermal(a.get("thermal_model") or {}, b.get("thermal_model") or {}, gains, u)
    rate, rate_fields = _diff_rate(a.get("rate_terms") or {}, b.get("rate_terms") or {}, gains, u)
    old_in = {i["sha256"]: i for i in pa.get("inputs") or []}
    new_in = {i["sha256"]: i for i in pb.get("inputs") or []}
    return {
        "unit": unit,
        "v1": int(v1),
        "v2": int(v2),
        "constants": annotate(
            _diff_constants(a.get("coefficients") or {}, b.get("coefficients") or {}, gains, u), a, b
        ),
        "thermal_model": annotate(thermal, a, b),
        "rate_terms": annotate(rate, a, b),
        "significance": significance_note(),
        "fields": fields + thermal_fields + rate_fields,
        "settings": [
            {"name": k, "old": o, "new": n}
            for k, (o, n) in _diff_flat(pa.get("settings") or {}, pb.get("settings") or {}).items()
        ],
        "inputs": {
            "added": [new_in[s] for s in new_in if s not in old_in],
            "removed": [old_in[s] for s in old_in if s not in new_in],
        },
    }


def _gains_v_per_g(doc: dict) -> list[float] | None:
    """|Kii| of a passport's normal-temperature K, or None if absent/zero."""
    try:
        k = doc["coefficients"]["K"]
        gains = [abs(float(k[i][i])) for i in range(3)]
    except (KeyError, IndexError, TypeError, ValueError):
        return None
    return gains if all(gains) else None


def _entry(name: str, unit: str, old: Any, new: Any, scale: float | None, scaled_unit: str) -> dict:
    """One changed number; delta_scaled = delta * scale (None when a side is missing or no scale is known)."""
    numeric = isinstance(old, (int, float)) and isinstance(new, (int, float))
    delta = new - old if numeric else None
    return {
        "name": name,
        "unit": unit,
        "old": old,
        "new": new,
        "delta": delta,
        "delta_scaled": delta * scale if delta is not None and scale is not None else None,
        "scaled_unit": scaled_unit,
    }


def _diff_constants(ca: dict, cb: dict, gains: list[float] | None, u: str = "V") -> list[dict]:
    out = []
    ka, kb = ca.get("K"), cb.get("K")
    ua, ub = ca.get("U0"), cb.get("U0")
    for i, ai in enumerate(AXES):
        ppm = 1e6 / gains[i] if gains else None
        for j, aj in enumerate(AXES):
            old, new = _at(ka, i, j), _at(kb, i, j)
            if old != new:
                out.append(_entry(f"K.{ai}{aj}", per(u, "g"), old, new, ppm, "ppm of gain"))
    for i, ai in enumerate(AXES):
        old, new = _at(ua, i), _at(ub, i)
        if old != new:
            out.append(_entry(f"U0.{ai}", u, old, new, 1e6 / gains[i] if gains else None, "micro-g"))
    return out


def _at(seq: Any, *index: int) -> Any:
    try:
        for i in index:
            seq = seq[i]
        return seq
    except (IndexError, KeyError, TypeError):
        return None


def _coef_scale(group: str, key: str, gains: list[float] | None) -> tuple[float | None, str]:
    """Scale of a thermal coefficient: alpha_i (output unit)/C^n -> micro-g/C^n (/|Kii|); beta, gamma 1/C^n ->
    ppm/C^n."""
    if group == "alpha":
        i = AXES.index(key[:1]) if key[:1] in AXES else -1
        return (1e6 / gains[i] if gains and i >= 0 else None), "micro-g"
    return 1e6, "ppm"


def _diff_rate(ra: dict, rb: dict, gains: list[float] | None, u: str = "V") -> tuple[list[dict], list[dict]]:
    """Changed rate terms of two differential passports (element-wise when both have the same orders) and changed
    orders, lag and smoothing. Entry names: ``rate_terms.alpha_rate.x[n][k]`` (multiplies r^n dT^k),
    ``rate_terms.beta_rate.xx[n][k]``, ``rate_terms.cross_axis_abs.xy[m]`` (multiplies dT^m)."""
    fields = [
        {"name": f"rate_terms.{k}", "old": ra.get(k), "new": rb.get(k)}
        for k in ("order", "dt_order", "lag_tau_s", "temp_smooth_s")
        if ra.get(k) != rb.get(k)
    ]
    if not ra or not rb or ra.get("order") != rb.get("order") or ra.get("dt_order") != rb.get("dt_order"):
        return [], fields
    out = []
    for group, base in (("alpha_rate", u), ("beta_rate", "1")):
        ga, gb = ra.get(group) or {}, rb.get(group) or {}
        for key in sorted(set(ga) | set(gb)):
            rows_a, rows_b = ga.get(key) or [], gb.get(key) or []
            for n in range(max(len(rows_a), len(rows_b))):
                for k in range(max(len(_at(rows_a, n) or []), len(_at(rows_b, n) or []))):
                    old, new = _at(rows_a, n, k), _at(rows_b, n, k)
                    if old != new:
                        scale, su = _coef_scale("alpha" if group == "alpha_rate" else "beta", key, gains)
                        per_ = f"(C/min)^{n + 1}/C^{k}"
                        out.append(
                            _entry(
                                f"rate_terms.{group}.{key}[{n + 1}][{k}]",
                                per(base, per_),
                                old,
                                new,
                                scale,
                                f"{su}/{per_}",
                            )
                        )
    ca, cb = ra.get("cross_axis_abs") or {}, rb.get("cross_axis_abs") or {}
    for key in sorted(set(ca) | set(cb)):
        sa, sb = ca.get(key) or [], cb.get(key) or []
        i = AXES.index(key[0])
        for m in range(max(len(sa), len(sb))):
            old, new = _at(sa, m), _at(sb, m)
            if old != new:
                out.append(
                    _entry(
                        f"rate_terms.cross_axis_abs.{key}[{m + 1}]",
                        f"{per(u, 'g')}/C^{m + 1}",
                        old,
                        new,
                        1e6 / gains[i] if gains else None,
                        f"ppm of gain/C^{m + 1}",
                    )
                )
    return out, fields


def _diff_thermal(ta: dict, tb: dict, gains: list[float] | None, u: str = "V") -> tuple[list[dict], list[dict]]:
    """Changed thermal coefficients (element-wise when the two models have the same shape) and changed shape fields."""
    fields = [
        {"name": f"thermal_model.{k}", "old": ta.get(k), "new": tb.get(k)}
        for k in ("kind", "order", "breakpoints_c")
        if ta.get(k) != tb.get(k)
    ]
    if ta.get("kind") != tb.get("kind") or ta.get("breakpoints_c") != tb.get("breakpoints_c"):
        return [], fields
    out = []
    if ta.get("kind") == "polynomial":
        for group in ("alpha", "beta", "gamma"):
            ga, gb = ta.get(group) or {}, tb.get(group) or {}
            for key in sorted(set(ga) | set(gb)):
                sa, sb = ga.get(key) or [], gb.get(key) or []
                for n in range(max(len(sa), len(sb))):
                    old, new = _at(sa, n), _at(sb, n)
                    if old != new:
                        scale, su = _coef_scale(group, key, gains)
                        base = u if group == "alpha" else "1"
                        out.append(
                            _entry(
                                f"{group}.{key}[{n + 1}]", per(base, f"C^{n + 1}"), old, new, scale, f"{su}/C^{n + 1}"
                            )
                        )
    elif ta.get("kind") == "piecewise_linear":
        sa, sb = ta.get("segments") or [], tb.get("segments") or []
        for s in range(max(len(sa), len(sb))):
            seg_a, seg_b = _at(sa, s) or {}, _at(sb, s) or {}
            for group in ("alpha", "beta", "gamma"):
                ga, gb = seg_a.get(group) or {}, seg_b.get(group) or {}
                for key in sorted(set(ga) | set(gb)):
                    old, new = ga.get(key), gb.get(key)
                    if old != new:
                        scale, su = _coef_scale(group, key, gains)
                        base = u if group == "alpha" else "1"
                        out.append(_entry(f"segments[{s}].{group}.{key}", per(base, "C"), old, new, scale, f"{su}/C"))
    return out, fields


def _flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts as {"a.b.c": leaf}; an empty dict nested inside is a leaf."""
    if isinstance(obj, dict) and (obj or not prefix):
        flat: dict[str, Any] = {}
        for k, v in obj.items():
            flat.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return flat
    return {prefix: obj}


def _diff_flat(a: dict, b: dict) -> dict[str, tuple[Any, Any]]:
    fa, fb = _flatten(a), _flatten(b)
    return {k: (fa.get(k), fb.get(k)) for k in sorted(set(fa) | set(fb)) if fa.get(k) != fb.get(k)}
