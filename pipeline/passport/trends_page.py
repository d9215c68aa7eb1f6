"""The HTML page of ``thermocal trends --html FILE``: one table per finding kind (drifting, unsteady, outliers, units
not verified) and a figure per finding, embedded as PNG so the page stands alone: for a drifting or unsteady
constant, its values against time with their standard uncertainties (1 sigma error bars), the fitted line and the
limit about the current value; for an outlier, the fleet's values of that constant (its type's units) with the unit
marked, the median and the threshold."""

from __future__ import annotations

import base64
import html
import io
import os
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from pipeline.io.files import write_text_whole
from pipeline.passport.trends import FleetValues, Series, TrendsResult, utc_of

_CSS = """
body { font-family: "DejaVu Sans", Arial, sans-serif; font-size: 10.5pt; margin: 14mm; color: #111; }
h1 { font-size: 17pt; } h2 { font-size: 12.5pt; margin-top: 16pt; border-bottom: 1px solid #888; }
table { border-collapse: collapse; margin: 6pt 0; } td, th { border: 1px solid #bbb; padding: 2pt 6pt; }
th { background: #eee; text-align: left; } td.num { text-align: right; font-family: "DejaVu Sans Mono", monospace; }
img { max-width: 100%; border: 1px solid #ccc; margin: 4pt 0; } .note { color: #444; font-size: 9pt; }
figure { margin: 8pt 0; } figcaption { font-size: 9pt; color: #333; }
"""


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _dates(t_s: np.ndarray) -> list[datetime]:
    return [datetime.fromtimestamp(float(t), UTC) for t in t_s]


def series_figure(s: Series, title: str) -> str:
    """The constant against time (error bars 1 sigma), the weighted line and the limit about the current value, as
    a PNG data URI."""
    from pipeline.plots import new_figure

    fig, ax = new_figure(1, 1, figsize=(7.5, 3.4))
    t_end = max(float(s.time_s[-1]), s.current_time_s)
    span = max(t_end - float(s.time_s[0]), 86400.0)
    t_line = np.linspace(float(s.time_s[0]) - 0.05 * span, t_end + 0.25 * span, 50)
    ax.errorbar(_dates(s.time_s), s.value, yerr=s.sigma, fmt="o", color="#1f77b4", capsize=3, label="versions")
    ax.plot(_dates(t_line), s.intercept + s.rate_per_s * (t_line - s.t_ref_s), color="#ff7f0e", label="fitted line")
    if s.limit is not None:
        for sign in (1.0, -1.0):
            ax.axhline(
                s.current_value + sign * s.limit, color="#b00000", ls="--", lw=1, label="limit" if sign > 0 else None
            )
    for v, t, y in zip(s.versions, s.time_s, s.value):
        ax.annotate(f"v{v}", (_dates(np.array([t]))[0], y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_ylabel(f"{s.constant} ({s.output_unit})")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="best")
    fig.autofmt_xdate()
    fig.tight_layout()
    return _png(fig)


def fleet_figure(f: FleetValues, threshold: float, title: str) -> str:
    """The fleet's values of the constant (one dot per unit of the type), the unit marked, the median and
    median +- threshold x robust sigma, as a PNG data URI."""
    from pipeline.plots import new_figure

    fig, ax = new_figure(1, 1, figsize=(7.5, 2.6))
    order = np.argsort(f.values)
    x = f.values[order]
    rng = np.random.default_rng(0)
    jitter = rng.uniform(-0.3, 0.3, x.size)
    marked = np.array([f.units[i] == f.unit for i in order])
    ax.scatter(x[~marked], jitter[~marked], s=14, color="#1f77b4", label=f"fleet ({x.size} units)")
    ax.scatter(x[marked], jitter[marked], s=60, color="#b00000", marker="D", label=f.unit)
    ax.axvline(f.median, color="#444", lw=1, label="median")
    for sign in (1.0, -1.0):
        ax.axvline(
            f.median + sign * threshold * f.sigma,
            color="#ff7f0e",
            ls="--",
            lw=1,
            label=f"median +- {threshold:.3g} robust sigma" if sign > 0 else None,
        )
    ax.set_yticks([])
    ax.set_ylim(-1, 1)
    ax.set_xlabel(f.constant)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return _png(fig)


def _num(x, fmt: str = ".4g") -> str:
    return "-" if x is None else format(x, fmt)


def _table(head: list[str], rows: list[list[str]]) -> str:
    e = html.escape
    out = ["<table><tr>" + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>"]
    for r in rows:
        out.append("<tr>" + "".join(f"<td class='num'>{e(c)}</td>" for c in r) + "</tr>")
    return "\n".join(out) + "</table>"


def trends_html(result: TrendsResult, *, registry: str | None = None) -> str:
    """The page (module doc) of a :func:`pipeline.passport.trends.fleet_trends` result."""
    e = html.escape
    r = result.report
    tests = r["tests"]
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>Fleet trends</title>"
        f"<style>{_CSS}</style></head><body>",
        "<h1>The fleet over time</h1>",
        f"<p>{r['units']} units, {r['versions']} passport versions"
        + (f" in <span class='mono'>{e(registry)}</span>" if registry else "")
        + "; every passport verified before use.</p>",
    ]
    d, u, o = tests["drift"], tests["unsteady"], tests["outliers"]
    parts.append(f"<h2>Drifting constants ({len(r['drifting'])})</h2>")
    parts.append(
        f"<p class='note'>{e(d['rule'])}; threshold {_num(d['z_threshold'])} over {d['series_tested']} series.</p>"
    )
    parts.append(
        _table(
            ["unit", "constant", "rate / year", "sigma / year", "z", "scaled / year", "limit", "due", "versions"],
            [
                [
                    x["unit"],
                    x["constant"],
                    f"{x['rate_per_year']:.4g} {x['constant_unit']}",
                    _num(x["sigma_per_year"]),
                    f"{x['z']:.1f}",
                    f"{_num(x['rate_scaled_per_year'])} {x['scaled_unit']}",
                    f"{_num(x['limit'])} ({x['grade']}, {x['limit_g']:.3g} g)",
                    (x["due_utc"] or "never")[:10],
                    ", ".join(f"v{v['version']}" for v in x["versions"]),
                ]
                for x in r["drifting"]
            ],
        )
    )
    parts.append(f"<h2>Unsteady constants ({len(r['unsteady'])})</h2>")
    parts.append(
        f"<p class='note'>{e(u['rule'])}; threshold p {_num(u['p_threshold'])} over {u['series_tested']} series.</p>"
    )
    parts.append(
        _table(
            ["unit", "constant", "chi2 / dof", "p", "line rate / year", "recent rate / year", "due (recent)"],
            [
                [
                    x["unit"],
                    x["constant"],
                    f"{x['chi2']:.1f} / {x['dof']}",
                    f"{x['p_value']:.2g}",
                    f"{x['line_rate_per_year']:.4g} {x['constant_unit']}",
                    f"{x['recent_rate_per_year']:.4g} +- {x['recent_sigma_per_year']:.2g}",
                    (x["due_utc"] or "never")[:10],
                ]
                for x in r["unsteady"]
            ],
        )
    )
    parts.append(f"<h2>Outliers ({len(r['outliers'])})</h2>")
    parts.append(f"<p class='note'>{e(o['rule'])}; {o['comparisons']} comparisons.</p>")
    parts.append(
        _table(
            ["unit", "version", "constant", "value", "sigma", "fleet median", "robust sigma", "robust z", "type"],
            [
                [
                    x["unit"],
                    f"v{x['version']}",
                    x["constant"],
                    _num(x["value"]),
                    _num(x["sigma"]),
                    _num(x["fleet_median"]),
                    _num(x["fleet_sigma"]),
                    f"{x['robust_z']:+.1f} (> {x['z_threshold']:.3g})",
                    f"{x['unit_type']} ({x['fleet_units']} units)",
                ]
                for x in r["outliers"]
            ],
        )
    )
    if r["not_verified"]:
        parts.append(f"<h2>Units not verified ({len(r['not_verified'])})</h2>")
        parts.append(
            _table(
                ["unit", "problem", "versions used"],
                [
                    [x["unit"], x["problems"][0], ", ".join(f"v{v}" for v in x["versions_used"]) or "none"]
                    for x in r["not_verified"]
                ],
            )
        )
    figures = [(f"{k}: {x['unit']} {x['constant']}", x) for k in ("drifting", "unsteady") for x in r[k]]
    if figures or r["outliers"]:
        parts.append("<h2>Figures</h2>")
    for caption, x in figures:
        s = result.series[(x["unit"], x["constant"])]
        due = f", due {x['due_utc'][:10]}" if x["due_utc"] else ""
        uri = series_figure(s, f"{caption}{due} (current v{x['current_version']}, {utc_of(s.current_time_s)[:10]})")
        parts.append(f"<figure><img alt='{e(caption)}' src='{uri}'><figcaption>{e(caption)}</figcaption></figure>")
    for x in r["outliers"]:
        caption = f"outlier: {x['unit']} v{x['version']} {x['constant']}, robust z {x['robust_z']:+.1f}"
        uri = fleet_figure(result.fleets[(x["unit"], x["constant"])], x["z_threshold"], caption)
        parts.append(f"<figure><img alt='{e(caption)}' src='{uri}'><figcaption>{e(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_trends_page(result: TrendsResult, path: str | os.PathLike, *, registry: str | None = None) -> Path:
    """Write :func:`trends_html` to ``path`` (whole or not at all: a temporary file renamed); ThermocalError (one
    line naming the file) when it cannot be written."""
    return write_text_whole(path, trends_html(result, registry=registry), "page")
