"""A passport for people: the text of ``calibrate``'s summary, ``passport show``, ``passport log`` and
``passport diff`` (plain lines, engineering units: K in the output unit per g (V/g, or m/s^2 per g for a logger that
records acceleration: :func:`pipeline.passport.document.output_unit_of`) and U0 in the output unit, with their
uncertainty in ppm of the gain and micro-g, gravity-module errors in micro-g against their limits, times in UTC).

Every function takes documents and rows as the registry stores them (dicts) and returns lines or text; nothing here
reads or writes files.
"""

from __future__ import annotations

from collections.abc import Sequence

from pipeline.passport.document import gains_v_per_g, output_unit_of
from pipeline.positions import AXES
from pipeline.verify import verification_visits
from pipeline.words import count_words

_UG = 1e6  # g -> micro-g


def model_text(thermal_model: dict | None) -> str:
    """``polynomial, order 2`` / ``piecewise linear, breakpoints -40, +20, +70 C`` / ``-``."""
    tm = thermal_model or {}
    if tm.get("kind") == "polynomial":
        return f"polynomial, order {tm.get('order')}"
    if tm.get("kind") == "piecewise_linear":
        return "piecewise linear, breakpoints " + ", ".join(f"{t:+.0f}" for t in tm.get("breakpoints_c", [])) + " C"
    return str(tm.get("kind") or "-")


def model_short(thermal_model: dict | None) -> str:
    """``poly2`` / ``piecewise, 3 nodes`` / ``-`` (a column of ``passport log``)."""
    tm = thermal_model or {}
    if tm.get("kind") == "polynomial":
        return f"poly{tm.get('order')}"
    if tm.get("kind") == "piecewise_linear":
        return f"piecewise, {len(tm.get('breakpoints_c', []))} nodes"
    return str(tm.get("kind") or "-")


def max_error_g(doc: dict) -> float | None:
    """The largest |dg| after compensation (method 1, the verdict's) over the verification positions, g."""
    rows = doc.get("verification") or []
    return max((abs(r["dg_method1_g"]) for r in rows), default=None)


def per(unit: str, what: str) -> str:
    """``V/g``, ``(m/s^2)/g``: ``unit`` per ``what``."""
    return f"({unit})/{what}" if "/" in unit else f"{unit}/{what}"


def constants_lines(doc: dict) -> list[str]:
    """The normal-temperature constants K (output unit per g) and U0 (output unit), each with its standard
    uncertainty in ppm of the row's gain (K) or micro-g (U0) when the passport has one."""
    c = doc.get("coefficients") or {}
    K, U0 = c.get("K"), c.get("U0")
    if K is None or U0 is None:
        return ["constants: -"]
    unc = (doc.get("uncertainty") or {}).get("coefficients") or {}
    sK, sU = unc.get("K"), unc.get("U0")
    gains = gains_v_per_g(doc) or [1.0, 1.0, 1.0]
    u = output_unit_of(doc)
    lines = [
        f"constants at T0 = {doc.get('normal_temp_c', 20.0):+.1f} C (+- one standard uncertainty: ppm of "
        "the row's gain for K, micro-g for U0)",
        "        "
        + "".join(
            f"{h:<28}"
            for h in (f"K_ix ({per(u, 'g')})", f"K_iy ({per(u, 'g')})", f"K_iz ({per(u, 'g')})", f"U0_i ({u})")
        ).rstrip(),
    ]
    fixed, undetermined = sigma_reasons(doc)
    for i, ax in enumerate(AXES):
        cells = [
            _pm(
                K[i][j], None if sK is None else sK[i][j], gains[i], "ppm", tag(f"K.{ax}{AXES[j]}", fixed, undetermined)
            )
            for j in range(3)
        ]
        cells.append(_pm(U0[i], None if sU is None else sU[i], gains[i], "ug", tag(f"U0.{ax}", fixed, undetermined)))
        lines.append(f"  i={ax}  " + "".join(f"{cell:<28}" for cell in cells).rstrip())
    return lines + reason_lines(doc, ("K.", "U0."))


def sigma_reasons(doc: dict) -> tuple[dict[str, str], dict[str, str]]:
    """The passport's ``uncertainty.fixed_by_convention`` and ``uncertainty.undetermined`` ({field: why}); empty
    when it records none."""
    unc = doc.get("uncertainty") or {}
    return dict(unc.get("fixed_by_convention") or {}), dict(unc.get("undetermined") or {})


def reason_lines(doc: dict, prefixes: tuple[str, ...] = ()) -> list[str]:
    """One line per reason a field has no measured uncertainty (fields with the same reason on one line), for the
    fields starting with one of ``prefixes`` (all when empty)."""
    fixed, undetermined = sigma_reasons(doc)
    out = []
    for label, reasons in (("fixed by convention", fixed), ("no uncertainty", undetermined)):
        by_reason: dict[str, list[str]] = {}
        for name, why in reasons.items():
            if not prefixes or name.startswith(prefixes):
                by_reason.setdefault(why, []).append(name)
        out += [f"  {label}: {', '.join(names)}: {why}" for why, names in by_reason.items()]
    return out


def tag(name: str, fixed: dict, undetermined: dict) -> str | None:
    """The mark of a constant without a standard uncertainty: ``(by convention)`` when fixed by a convention,
    ``(undetermined)`` when the data do not determine it (:func:`sigma_reasons`), else None."""
    return "(by convention)" if name in fixed else "(undetermined)" if name in undetermined else None


def signed(value: float, decimals: int = 8) -> str:
    """``+0.55060846``; a value that rounds to zero reads ``+0.00000000``, never ``-0.00000000``."""
    text = f"{value:+.{decimals}f}"
    return text if float(text) != 0 else f"{0.0:+.{decimals}f}"


def _pm(value: float, sigma: float | None, gain: float, unit: str, tag: str | None = None) -> str:
    text = signed(value)
    if tag is not None and (sigma is None or sigma == 0):
        return f"{text} {tag}"
    if sigma is None:
        return text
    return f"{text} +-{sigma / gain * 1e6:.2g} {unit}"


def grade_text(doc: dict) -> str:
    """The unit grade and the verification limits a passport (or a ``calibrate --json`` result) was judged with
    (its ``tolerances``, :meth:`pipeline.verify.Tolerances.text`); for a passport written before grades, the limits
    its rows carry."""
    from pipeline.verify import Tolerances

    tol = doc.get("tolerances")
    if isinstance(tol, dict):
        try:
            return Tolerances(**tol).text()
        except TypeError:
            pass
    limits = sorted({r["tolerance_g"] for r in doc.get("verification") or [] if "tolerance_g" in r})
    return "grade not stated (a passport written before unit grades)" + (
        f"; limits {', '.join(f'{x:g}' for x in limits)} g" if limits else ""
    )


def verification_lines(doc: dict) -> list[str]:
    """A row per visit of a verification temperature: the largest |dg| before compensation and after (methods 1 and
    2) against the limit, and the verdict; under a failing row, its failing positions."""
    rows = doc.get("verification") or []
    if not rows:
        return ["verification: no VP data (unverified); " + grade_text(doc)]
    head = (
        f"  {'temperature':<18}{'VPs':>4}  {'max |dg| before':>16}  {'after m1':>10}  {'after m2':>10}  "
        f"{'limit':>8}  verdict"
    )
    lines = ["verification at the VP positions (|dg| = ||a| - 1|, micro-g; the verdict is on method 1)", head]
    lines.insert(1, "  " + grade_text(doc))
    for v in verification_visits(rows):
        rs = v["rows"]
        limit = max(r["tolerance_g"] for r in rs)
        failing = [r for r in rs if not r.get("passed", abs(r["dg_method1_g"]) <= r["tolerance_g"])]
        visit = f" visit {v['visit']}/{v['visits']}" if v["visits"] > 1 else ""
        lines.append(
            f"  {v['temp_c']:+6.1f} C{visit:<10}{len(rs):>4}  "
            f"{max(abs(r['dg_uncompensated_g']) for r in rs) * _UG:16.1f}  "
            f"{max(abs(r['dg_method1_g']) for r in rs) * _UG:10.1f}  "
            f"{max(abs(r['dg_method2_g']) for r in rs) * _UG:10.1f}  {limit * _UG:8.0f}  "
            + ("FAIL  <<" if failing else "pass")
        )
        for r in failing:
            lines.append(
                f"      FAIL {r['position']} at {r['temp_c']:+.2f} C: |dg| {abs(r['dg_method1_g']) * _UG:.1f} "
                f"> {r['tolerance_g'] * _UG:.0f} micro-g"
            )
    return lines


def approval_text(approved: list[dict] | None) -> str:
    if not approved:
        return "not approved"
    return "; ".join(f"approved by {a.get('by')} at {a.get('approved_utc')}" for a in approved)


def passport_summary(doc: dict, *, approved: list[dict] | None = None, figures: Sequence[str] = ()) -> str:
    """``passport show``: who, when, how, the verdict, the constants with their uncertainty, the thermal model, the
    verification table, the inputs with their hashes, the figures."""
    prov = doc.get("provenance") or {}
    valid = doc.get("valid_temp_c")
    err = max_error_g(doc)
    lines = [
        f"{doc.get('unit')} passport v{doc.get('version')}  created {doc.get('created_utc') or '-'}",
        f"  method: {doc.get('method', '-')}; thermal model: {model_text(doc.get('thermal_model'))}",
        f"  status: {doc.get('status', '-')}"
        + (f"; largest |dg| after compensation {err * _UG:.1f} micro-g" if err is not None else ""),
        f"  valid from {valid[0]:+.1f} to {valid[1]:+.1f} C" if valid else "  valid temperatures: not stated",
        f"  approval: {approval_text(approved)}",
        "",
    ]
    lines += constants_lines(doc) + [""] + verification_lines(doc)
    inputs = prov.get("inputs") or []
    if inputs:
        lines += ["", "inputs (sha256)"] + [f"  {i.get('sha256', '')[:16]}  {i.get('path')}" for i in inputs]
    if prov.get("code_version"):
        lines.append(f"code: {prov['code_version']}")
    for n in doc.get("notes") or []:
        lines.append(f"note: {n}")
    lines += [f"figure: {f}" for f in figures]
    return "\n".join(lines)


def log_lines(rows: list[dict], docs: dict[int, dict]) -> list[str]:
    """``passport log``: one line per version: number (``*`` the current passport), created (UTC), method, thermal
    model, status, largest |dg| after compensation (micro-g), approval, inputs. ``docs``: the version documents by
    number (for method, model and error)."""
    out = [
        f"   {'ver':<5} {'created (UTC)':<20} {'method':<18} {'thermal model':<19} {'status':<10} "
        f"{'max |dg|':>9}  approval"
    ]
    for r in rows:
        d = docs.get(r["version"], {})
        err = max_error_g(d)
        created = str(r.get("created_utc") or "-").replace("T", " ")[:19]
        mark = "*" if r.get("current") else " "
        appr = ", ".join(f"by {a.get('by')}" for a in r.get("approved") or []) or "-"
        out.append(
            f" {mark} v{r['version']:<4} {created:<20} {str(d.get('method', '-')):<18} "
            f"{model_short(d.get('thermal_model')):<19} {str(r.get('status')):<10} "
            + (f"{err * _UG:7.1f}ug" if err is not None else f"{'-':>9}")
            + f"  {appr}"
        )
    if any(r.get("current") for r in rows):
        out.append("   (* the current passport: the newest approved version, else the newest that did not fail)")
    return out


def diff_lines(d: dict, show_all: bool = False) -> list[str]:
    """``passport diff``: changed fields and settings, then each changed constant and thermal coefficient in its
    engineering unit (ppm of the gain, micro-g, ppm/C^n, micro-g/C^n) with its combined uncertainty and whether it
    is significant (changes within their uncertainty counted in one line unless ``show_all``); a thermal-model
    section only when the two models can be compared."""
    lines = [f"{d.get('unit')}: v{d.get('v1')} -> v{d.get('v2')}"]
    for f in d.get("fields", []):
        lines.append(f"  {f['name']}: {_short(f.get('old'))} -> {_short(f.get('new'))}")
    for f in d.get("settings", []):
        lines.append(f"  setting {f['name']}: {_short(f.get('old'))} -> {_short(f.get('new'))}")
    ins = d.get("inputs") or {}
    for i in ins.get("added", []):
        lines.append(f"  input added: {i.get('path')} ({str(i.get('sha256'))[:12]})")
    for i in ins.get("removed", []):
        lines.append(f"  input removed: {i.get('path')} ({str(i.get('sha256'))[:12]})")
    k = (d.get("significance") or {}).get("coverage_factor", 2)
    for title, key in (
        ("constants at T0", "constants"),
        ("thermal model coefficients", "thermal_model"),
        ("rate terms", "rate_terms"),
    ):
        entries = d.get(key, [])
        if not entries:
            continue
        shown = entries if show_all else [e for e in entries if e.get("significant") is not False]
        sig = sum(bool(e.get("significant")) for e in entries)
        lines.append(f"{title}: {sig} of {len(entries)} changes beyond {k:g} combined standard uncertainties")
        for e in shown:
            lines.append("  " + _entry_text(e))
        quiet = [e for e in entries if e not in shown]
        if quiet:
            worst = max(abs(e["delta"]) / e["uncertainty"] for e in quiet if e.get("uncertainty"))
            lines.append(
                f"  {len(quiet)} {'more ' if shown else ''}within their uncertainty (largest "
                f"{worst:.1f} sigma; --all lists them)"
            )
    if not d.get("constants") and not d.get("thermal_model") and not d.get("rate_terms"):
        lines.append("constants and thermal coefficients: unchanged")
    kinds = [f for f in d.get("fields", []) if f["name"] in ("thermal_model.kind", "thermal_model.breakpoints_c")]
    if kinds:
        lines.append("thermal models of different forms: their coefficients are not compared one by one")
    return lines


def _entry_text(e: dict) -> str:
    mark = {True: "SIGNIFICANT", False: "within noise", None: "no uncertainty"}[e.get("significant")]
    if e.get("delta_scaled") is not None:
        unit = e.get("scaled_unit", "")
        change = f"{e['delta_scaled']:+.3g} {unit}"
        u = e.get("uncertainty_scaled")
        if u:
            change += f" (+-{u:.2g}, {abs(e['delta_scaled']) / u:.1f} sigma)"
    elif isinstance(e.get("delta"), (int, float)):
        change = f"{e['delta']:+.3g} {e.get('unit', '')}"
    else:
        change = f"{_short(e.get('old'))} -> {_short(e.get('new'))}"
    return f"{e['name']:<22} {change:<44} {mark}"


def _short(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_short(x) for x in v) + "]"
    return str(v)


def _auto_reason(result: dict) -> str:
    """`` (picked by --method auto: <why>)`` when ``--method auto`` chose the method (the result's ``method_auto``:
    "<method> (<why>)"), else ``""``."""
    auto = result.get("method_auto")
    if not auto:
        return ""
    chosen = f"{result.get('method')} ("
    why = auto[len(chosen) : -1] if auto.startswith(chosen) and auto.endswith(")") else auto
    return f" (picked by --method auto: {why})"


def calibrate_lines(result: dict, doc: dict | None) -> list[str]:
    """``calibrate``'s summary: the version written (or found), method and model, then per temperature the largest
    |dg| against its limit with failing positions marked, the constants at T0 with their uncertainty, the figures,
    the warnings. ``doc``: the passport written (None: only the result's own fields)."""
    created = result.get("created")
    if result.get("dry_run"):
        lines = [
            f"{result['unit']}: dry run, nothing written "
            + (
                f"(same inputs and settings as v{result['version']})"
                if result.get("existing")
                else f"(would be v{result['version']})"
            )
        ]
    else:
        lines = [
            f"{result['unit']}: passport v{result['version']} "
            f"{'written' if created else '(unchanged inputs: the existing version)'}: {result.get('passport')}"
        ]
    auto = _auto_reason(result)
    if doc is not None:
        valid = doc.get("valid_temp_c")
        lines.append(
            f"  method {doc.get('method', result.get('method', '-'))}{auto}; thermal model "
            f"{model_text(doc.get('thermal_model'))}"
            + (f"; valid {valid[0]:+.1f} .. {valid[1]:+.1f} C" if valid else "")
        )
    elif auto:
        lines.append(f"  method {result.get('method', '-')}{auto}")
    lines.append(f"  status: {str(result['status']).upper()}")
    plateaus = result.get("plateaus") or []
    if plateaus:
        lines.append(
            f"  {count_words(len(plateaus), 'plateau')}: " + ", ".join(f"{p['temp_c']:+.1f}" for p in plateaus) + " C"
        )
    if doc is not None:
        lines += [""] + verification_lines(doc) + [""] + constants_lines(doc)
    for key, what in (("figure", "figure, VP errors"), ("constants_figure", "figure, constants")):
        if result.get(key):
            lines.append(f"{what}: {result[key]}")
    for w in result.get("warnings", []):
        lines.append(f"warning: {w}")
    return lines
