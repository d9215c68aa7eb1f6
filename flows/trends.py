"""The trends flow: ``thermocal trends`` as a Prefect flow (``thermocal-trends``), run by the nightly deployment
after the fleet flow (:func:`flows.fleet.fleet_flow` with ``trends=True``, which :mod:`flows.serve` sets), so that
each night's run reports which constants drift, which units stand out and which did not verify.

The flow reads the registry once (:func:`pipeline.passport.trends.fleet_trends`), logs one line per finding,
optionally writes the HTML page, and leaves a table artifact ``thermocal-trends``: one row per finding (kind, unit,
constant, the figure and its threshold, the due date), or one row saying nothing was found. It returns the
``trends --json`` object (docs/contract.md).
"""

from __future__ import annotations

from .runtime import prefect_defaults

prefect_defaults()

from prefect import flow, get_run_logger  # noqa: E402
from prefect.artifacts import create_table_artifact  # noqa: E402

from pipeline.passport.trends import fleet_trends, trends_text  # noqa: E402

ARTIFACT_KEY = "thermocal-trends"
KINDS = ("drifting", "unsteady", "outliers", "not_verified")


def _row(
    kind: str,
    unit: str = "",
    constant: str = "",
    figure: str = "",
    test: str = "",
    due_utc: str = "",
    versions: str = "",
) -> dict:
    """One row of the table artifact (the same columns for every kind)."""
    return {
        "kind": kind,
        "unit": unit,
        "constant": constant,
        "figure": figure,
        "test": test,
        "due_utc": due_utc,
        "versions": versions,
    }


def _versions(entry: dict) -> str:
    return " ".join(f"v{v['version']}" for v in entry["versions"])


def trends_table(report: dict) -> list[dict]:
    """Rows of the table artifact: one per finding, the same columns for every kind."""
    rows = [
        _row(
            "drifting",
            e["unit"],
            e["constant"],
            f"{e['rate_per_year']:.4g} +- {e['sigma_per_year']:.2g} {e['constant_unit']}/year",
            f"|z| {abs(e['z']):.1f} > {e['z_threshold']:.3g}",
            e["due_utc"] or "never",
            _versions(e),
        )
        for e in report["drifting"]
    ]
    rows += [
        _row(
            "unsteady",
            e["unit"],
            e["constant"],
            f"recent {e['recent_rate_per_year']:.4g} {e['constant_unit']}/year",
            f"chi2 {e['chi2']:.1f} on {e['dof']} dof, p {e['p_value']:.2g} < {e['p_threshold']:.2g}",
            e["due_utc"] or "never",
            _versions(e),
        )
        for e in report["unsteady"]
    ]
    rows += [
        _row(
            "outlier",
            e["unit"],
            e["constant"],
            f"{e['value']:.4g} against median {e['fleet_median']:.4g} ({e['fleet_units']} units)",
            f"|robust z| {abs(e['robust_z']):.1f} > {e['z_threshold']:.3g}",
            versions=f"v{e['version']}",
        )
        for e in report["outliers"]
    ]
    rows += [
        _row(
            "not verified",
            e["unit"],
            figure=e["problems"][0],
            test="registry verification",
            versions=" ".join(f"v{v}" for v in e["versions_used"]) or "none used",
        )
        for e in report["not_verified"]
    ]
    return rows or [
        _row("none", figure=f"{report['units']} units, {report['versions']} versions: no drift, no outlier")
    ]


@flow(name="thermocal-trends", log_prints=False)
def trends_flow(registry: str, html: str | None = None) -> dict:
    """The fleet over time of ``registry`` (module doc); ``html``: also write the page there."""
    logger = get_run_logger()
    result = fleet_trends(registry)
    report = result.report
    for line in trends_text(report).splitlines():
        logger.info(line)
    if html:
        from pipeline.passport.trends_page import write_trends_page

        write_trends_page(result, html, registry=registry)
    create_table_artifact(
        key=ARTIFACT_KEY,
        table=trends_table(report),
        description=f"thermocal trends over {registry}: "
        + ", ".join(f"{len(report[k])} {k.replace('_', ' ')}" for k in KINDS),
    )
    return report
