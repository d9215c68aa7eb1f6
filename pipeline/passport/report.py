"""The calibration certificate (``thermocal report``): one self-contained HTML page a person reads and signs.

It states the unit and the passport version (with its content hash and signing key), the inputs with their
hashes, the method and settings, the constants at the normal temperature with their standard uncertainties, the
thermal model with its coefficients and uncertainties, the validity range, the figures (embedded as ``data:`` URIs,
so the file stands alone), the verification table against its limits, the status, the approval records and lines
to sign. :func:`certificate_html` builds the page from documents (no file access but the figures it draws in a
temporary folder); :func:`print_pdf` prints a page to PDF with a headless Chromium when one is installed.
"""

from __future__ import annotations

import base64
import html
import shutil
import subprocess
import tempfile
from pathlib import Path

from pipeline.errors import ThermocalError
from pipeline.passport.document import gains_v_per_g, output_unit_of
from pipeline.passport.text import (
    approval_text,
    grade_text,
    max_error_g,
    model_text,
    per,
    reason_lines,
    sigma_reasons,
    signed,
    tag,
)
from pipeline.positions import AXES
from pipeline.verify import verification_visits

_UG = 1e6

_CSS = """
body { font-family: "DejaVu Sans", Arial, sans-serif; font-size: 10.5pt; margin: 18mm; color: #111; }
h1 { font-size: 17pt; margin-bottom: 2pt; } h2 { font-size: 12.5pt; margin-top: 16pt; border-bottom: 1px solid #888; }
table { border-collapse: collapse; margin: 6pt 0; } td, th { border: 1px solid #bbb; padding: 2pt 6pt; }
th { background: #eee; text-align: left; } td.num { text-align: right; font-family: "DejaVu Sans Mono", monospace; }
.status { font-size: 14pt; font-weight: bold; padding: 4pt 10pt; display: inline-block; border: 2px solid; }
.pass { color: #176317; } .fail { color: #b00000; } .unverified { color: #8a5a00; }
tr.failrow td { background: #fde2e2; } .mono { font-family: "DejaVu Sans Mono", monospace; font-size: 9pt; }
img { max-width: 100%; border: 1px solid #ccc; margin: 4pt 0; } .sign td { height: 26pt; min-width: 150pt; }
.note { color: #444; font-size: 9pt; } @media print { h2 { break-after: avoid; } img { break-inside: avoid; } }
"""


def certificate_html(
    doc: dict,
    *,
    approved: list[dict] | None = None,
    registry: str | None = None,
    figures: dict[str, bytes] | None = None,
    verification=None,
) -> str:
    """The certificate of passport ``doc`` as one HTML page. ``approved``: the version's valid approval records
    (``by``, ``approved_utc``); ``figures``: PNG bytes by caption (default: drawn from the passport by
    :func:`passport_figures`); ``verification``: how the passport was verified
    (:class:`pipeline.passport.verification.Verification`): stated beside the signing key, and a banner when it was
    used without verifying (``--unverified``)."""
    figures = passport_figures(doc) if figures is None else figures
    e = html.escape
    unit, version = str(doc.get("unit")), doc.get("version")
    status = str(doc.get("status", "unverified"))
    prov = doc.get("provenance") or {}
    sig = doc.get("signature") or {}
    valid = doc.get("valid_temp_c")
    parts = [
        f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>Calibration certificate {e(unit)} v{e(str(version))}</title><style>{_CSS}</style></head><body>",
        f"<h1>Calibration certificate</h1><p>Accelerometer unit <b>{e(unit)}</b>, passport version "
        f"<b>{e(str(version))}</b>, created {e(str(doc.get('created_utc') or '-'))} (UTC)</p>",
        f"<p><span class='status {e(status)}'>status: {e(status.upper())}</span></p>",
        *(
            [f"<p class='unverified'>{e(verification.label)}: this certificate does not vouch for the passport</p>"]
            if verification is not None and not verification.verified
            else []
        ),
        "<h2>Identification</h2><table>",
        _row("unit serial number", e(unit)),
        _row("passport version", e(str(version))),
        _row("content sha256", f"<span class='mono'>{e(str(doc.get('content_sha256') or '-'))}</span>"),
        _row(
            "signed by station key",
            f"<span class='mono'>{e(str(sig.get('key_id') or 'unsigned'))}</span> ({e(str(sig.get('alg') or '-'))})",
        ),
        *([_row("verification", e(verification.label))] if verification is not None else []),
        _row("parent version sha256", f"<span class='mono'>{e(str(doc.get('parent_sha256') or 'none'))}</span>"),
        _row("registry", e(registry or "-")),
        _row("code", e(str(prov.get("code_version") or "-"))),
        "</table>",
        "<h2>Inputs</h2><table><tr><th>recording</th><th>sha256</th></tr>",
        *[
            f"<tr><td>{e(str(i.get('path')))}</td><td class='mono'>{e(str(i.get('sha256')))}</td></tr>"
            for i in prov.get("inputs") or []
        ],
        "</table>",
        "<h2>Method</h2><table>",
        _row("calibration method", e(str(doc.get("method", "-")))),
        _row("thermal model", e(model_text(doc.get("thermal_model")))),
        _row("normal temperature T0", f"{float(doc.get('normal_temp_c', 20.0)):+.1f} C"),
        _row("local gravity", f"{float(doc.get('g_local_mps2', 9.80665)):.5f} m/s^2"),
        _row(
            "valid temperature range",
            f"{valid[0]:+.1f} C to {valid[1]:+.1f} C (the calibration temperatures; outside it the model extrapolates)"
            if valid
            else "not stated",
        ),
        _row("settings", f"<span class='mono'>{e(_settings_text(prov.get('settings') or {}))}</span>"),
        "</table>",
        "<h2>Constants at the normal temperature</h2>",
        _constants_table(doc),
        "<h2>Thermal model</h2>",
        _thermal_table(doc),
        "<h2>Verification</h2>",
        f"<p>Unit {e(grade_text(doc))}.</p>",
        _verification_summary(doc),
        _verification_table(doc),
    ]
    for caption, png in figures.items():
        uri = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
        parts.append(f"<h2>{e(caption)}</h2><img alt='{e(caption)}' src='{uri}'>")
    notes = doc.get("notes") or []
    if notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{e(str(n))}</li>" for n in notes) + "</ul>")
    parts += [
        "<h2>Approval</h2>",
        f"<p>{e(approval_text(approved))} (approval records in the registry, signed by the approving station)</p>",
        "<table class='sign'><tr><th></th><th>name</th><th>signature</th><th>date</th></tr>"
        "<tr><th>calibrated by</th><td></td><td></td><td></td></tr>"
        "<tr><th>checked and approved by</th><td></td><td></td><td></td></tr></table>",
        "<p class='note'>Uncertainties are standard uncertainties (1 sigma) from the fit's residuals and the "
        "noise measured in the recordings; |dg| = | |a| - 1 | is the gravity-module error at the "
        "verification positions after compensation by method 1 (the verdict) and method 2.</p>",
        "</body></html>",
    ]
    return "\n".join(parts)


def passport_figures(doc: dict) -> dict[str, bytes]:
    """The certificate's figures as PNG bytes by caption: the VP errors before and after compensation, and the
    constants per plateau against temperature with the thermal model."""
    from pipeline.plots import plot_constants, plot_verification

    title = f"{doc.get('unit')} v{doc.get('version')}"
    with tempfile.TemporaryDirectory(prefix="thermocal-report-") as tmp:
        vp = plot_verification(
            doc.get("verification") or [],
            Path(tmp) / "vp.png",
            title=f"{title}: gravity-module error at the verification positions",
        )
        const = plot_constants(
            doc,
            Path(tmp) / "constants.png",
            title=f"{title}: constants per plateau against temperature, thermal model, residuals",
        )
        return {
            "Verification: errors before and after compensation": vp.read_bytes(),
            "Constants against temperature": const.read_bytes(),
        }


def _row(name: str, value_html: str) -> str:
    return f"<tr><th>{html.escape(name)}</th><td>{value_html}</td></tr>"


def _settings_text(settings: dict) -> str:
    keep = {
        k: v
        for k, v in settings.items()
        if k in ("thermal_model", "constants_method", "grade", "tol_normal_g", "tol_range_g", "tolerances", "method")
        and v is not None
    }
    return ", ".join(f"{k}={v}" for k, v in sorted(keep.items()))


def _pm(value: float | None, sigma: float | None, scale: float, unit: str, tag: str | None = None) -> str:
    if value is None:
        return "-"
    text = signed(value)
    if tag is not None and (sigma is None or sigma == 0):
        text += f" {tag}"
    elif sigma is not None:
        text += f" &plusmn; {sigma * scale:.2g} {unit}"
    return text


def _constants_table(doc: dict) -> str:
    c = doc.get("coefficients") or {}
    K, U0 = c.get("K"), c.get("U0")
    if K is None or U0 is None:
        return "<p>no constants</p>"
    unc = (doc.get("uncertainty") or {}).get("coefficients") or {}
    sK, sU = unc.get("K"), unc.get("U0")
    gains = gains_v_per_g(doc) or [1.0, 1.0, 1.0]
    u = html.escape(output_unit_of(doc))
    rows = [
        "<table><tr><th>row i</th>"
        + "".join(f"<th>K<sub>i{a}</sub> ({per(u, 'g')})</th>" for a in AXES)
        + f"<th>U0<sub>i</sub> ({u})</th></tr>"
    ]
    fixed, undetermined = sigma_reasons(doc)
    for i, ax in enumerate(AXES):
        cells = [
            _pm(
                K[i][j],
                None if sK is None else sK[i][j],
                1e6 / gains[i],
                "ppm",
                tag=tag(f"K.{ax}{AXES[j]}", fixed, undetermined),
            )
            for j in range(3)
        ]
        cells.append(
            _pm(
                U0[i],
                None if sU is None else sU[i],
                1e6 / gains[i],
                "micro-g",
                tag=tag(f"U0.{ax}", fixed, undetermined),
            )
        )
        rows.append(f"<tr><th>{ax}</th>" + "".join(f"<td class='num'>{x}</td>" for x in cells) + "</tr>")
    rows.append(
        "</table><p class='note'>&plusmn; one standard uncertainty, in ppm of the row's gain |K<sub>ii</sub>| "
        "for K and in micro-g for U0.</p>"
    )
    rows += [f"<p class='note'>{html.escape(line.strip())}</p>" for line in reason_lines(doc)]
    return "".join(rows)


def _thermal_table(doc: dict) -> str:
    tm = doc.get("thermal_model") or {}
    sig = (doc.get("uncertainty") or {}).get("thermal_model") or {}
    gains = dict(zip(AXES, gains_v_per_g(doc) or [1.0, 1.0, 1.0]))
    u = html.escape(output_unit_of(doc))
    undetermined = sigma_reasons(doc)[1]
    rows = ["<table><tr><th>term</th><th>coefficient</th><th>value</th><th>in engineering units</th></tr>"]

    def add(term: str, group: str, key: str, value: float, sigma: float | None, power: str) -> None:
        if group == "alpha":
            scale, unit, own = 1e6 / gains[key[0]], f"micro-g/C{power}", per(u, f"C{power}")
        else:
            scale, unit, own = 1e6, f"ppm/C{power}", f"1/C{power}"
        eng = (
            f"{value * scale:+.4g} &plusmn; {sigma * scale:.2g} {unit}"
            if sigma is not None
            else f"{value * scale:+.4g} {unit}" + (" (undetermined)" if f"{group}.{key}" in undetermined else "")
        )
        rows.append(
            f"<tr><td>{html.escape(term)}</td><td>{group} {key}</td>"
            f"<td class='num'>{value:+.6e} {own}</td><td class='num'>{eng}</td></tr>"
        )

    if tm.get("kind") == "polynomial":
        for group in ("alpha", "beta", "gamma"):
            for key, coefs in (tm.get(group) or {}).items():
                s = (sig.get(group) or {}).get(key) or []
                for n, value in enumerate(coefs, 1):
                    add(f"dT^{n}", group, key, value, s[n - 1] if n - 1 < len(s) else None, f"^{n}")
    elif tm.get("kind") == "piecewise_linear":
        segs_sigma = sig.get("segments") or []
        for k, seg in enumerate(tm.get("segments") or []):
            s_seg = segs_sigma[k] if k < len(segs_sigma) else {}
            for group in ("alpha", "beta", "gamma"):
                for key, value in (seg.get(group) or {}).items():
                    add(
                        f"{seg.get('t_lo_c'):+.0f}..{seg.get('t_hi_c'):+.0f} C",
                        group,
                        key,
                        value,
                        (s_seg.get(group) or {}).get(key),
                        "",
                    )
    else:
        return "<p>no thermal model</p>"
    rows.append(
        "</table><p class='note'>alpha: offset terms, beta: gain terms, gamma: cross-axis terms, in powers "
        "of dT = T - T0; &plusmn; one standard uncertainty.</p>"
    )
    return (f"<p>{html.escape(model_text(tm))}</p>") + "".join(rows)


def _verification_summary(doc: dict) -> str:
    err = max_error_g(doc)
    if err is None:
        return "<p>No verification positions were recorded: the passport is unverified.</p>"
    return (
        f"<p>Largest gravity-module error after compensation (method 1): <b>{err * _UG:.1f} micro-g</b>; "
        f"status <b>{html.escape(str(doc.get('status')))}</b>.</p>"
    )


def _verification_table(doc: dict) -> str:
    rows = doc.get("verification") or []
    if not rows:
        return ""
    out = [
        "<table><tr><th>temperature</th><th>position</th><th>|dg| before (micro-g)</th>"
        "<th>|dg| method 1</th><th>|dg| method 2</th><th>limit</th><th>verdict</th></tr>"
    ]
    for v in verification_visits(rows):
        visit = f" (visit {v['visit']} of {v['visits']})" if v["visits"] > 1 else ""
        for r in v["rows"]:
            ok = r.get("passed", abs(r["dg_method1_g"]) <= r["tolerance_g"])
            out.append(
                f"<tr class='{'' if ok else 'failrow'}'><td>{r['temp_c']:+.2f} C{visit}</td>"
                f"<td>{html.escape(str(r['position']))}</td>"
                f"<td class='num'>{abs(r['dg_uncompensated_g']) * _UG:.1f}</td>"
                f"<td class='num'>{abs(r['dg_method1_g']) * _UG:.1f}</td>"
                f"<td class='num'>{abs(r['dg_method2_g']) * _UG:.1f}</td>"
                f"<td class='num'>{r['tolerance_g'] * _UG:.0f}</td>"
                f"<td class='{'pass' if ok else 'fail'}'>{'pass' if ok else 'FAIL'}</td></tr>"
            )
    out.append("</table>")
    return "".join(out)


def chromium() -> str | None:
    """The path of a headless-capable Chromium (Debian's ``chromium``), or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def chromium_args(profile_dir: str) -> list[str]:
    """Flags for a headless Chromium that touches no network and keeps its profile in ``profile_dir``."""
    return [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile_dir}",
    ]


def print_pdf(html_path: str | Path, pdf_path: str | Path, timeout_s: float = 120.0) -> Path:
    """Print the page ``html_path`` to ``pdf_path`` with a headless Chromium; ThermocalError when there is none or
    it fails."""
    exe = chromium()
    if exe is None:
        raise ThermocalError("printing a PDF needs Chromium (Debian: apt-get install chromium)", path=str(pdf_path))
    pdf_path = Path(pdf_path).resolve()
    with tempfile.TemporaryDirectory(prefix="thermocal-chromium-") as profile:
        proc = subprocess.run(
            [
                exe,
                *chromium_args(profile),
                "--no-pdf-header-footer",
                f"--print-to-pdf={pdf_path}",
                Path(html_path).resolve().as_uri(),
            ],
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )
    if proc.returncode != 0 or not pdf_path.is_file():
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise ThermocalError(f"Chromium could not print the PDF ({last})", path=str(pdf_path))
    return pdf_path
