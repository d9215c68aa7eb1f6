"""The calibration flow: ingest -> segment -> fit -> verify -> write, one Prefect task per step (per file for
ingest and segment). Each task is a call of one library function:

- ingest:  ``pipeline.io.runs.read_run``
- segment: ``pipeline.calibrate.tilt.observe_run`` (``pipeline.segment.segment_run`` + per-segment averages)
- fit:     ``pipeline.calibrate.tilt.fit_unit`` (``pipeline.constants``, ``pipeline.thermal``)
- verify:  ``pipeline.calibrate.tilt.verify_unit`` (``pipeline.verify``, ``pipeline.compensate``)
- write:   ``pipeline.calibrate.publish.publish_calibration`` (``pipeline.passport.document``, ``pipeline.passport.registry``,
           ``pipeline.plots``)

The other methods of the source papers replace segment/fit/verify by one task each:

- ``--method scalar``:       ``pipeline.calibrate.scalar.calibrate_scalar`` (seed 004, orientation-free)
- ``--method differential``: ``pipeline.calibrate.differential.calibrate_differential`` (seed 003, from a base passport)
and are written by ``pipeline.calibrate.publish.publish_passport``.
"""

from __future__ import annotations

from .runtime import prefect_defaults

prefect_defaults()

from prefect import flow, get_run_logger, task  # noqa: E402
from prefect.artifacts import create_markdown_artifact  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402  (no input hashing: a Run is large and never reused)

from pipeline.calibrate import tilt as calibration  # noqa: E402
from pipeline.calibrate.publish import publish_calibration, publish_passport  # noqa: E402
from pipeline.io import runs as runio  # noqa: E402


@task(name="ingest", cache_policy=NO_CACHE)
def ingest(path: str):
    return runio.read_run(path)


@task(name="segment", cache_policy=NO_CACHE)
def segment(run, settings: calibration.CalibrationSettings):
    return calibration.observe_run(run, settings.segment)


@task(name="fit", cache_policy=NO_CACHE)
def fit(unit: str, observations, settings: calibration.CalibrationSettings, normal_temp_c: float):
    return calibration.fit_unit(unit, observations, settings, normal_temp_c)


@task(name="verify", cache_policy=NO_CACHE)
def verify(model, observations, normal_temp_c: float, settings: calibration.CalibrationSettings):
    return calibration.verify_unit(model, observations, normal_temp_c, settings.tolerances)


@task(name="write", cache_policy=NO_CACHE)
def write(registry: str, unit_fit, rows, status, observations, paths, settings, g_local_mps2):
    return publish_calibration(registry, unit_fit, rows, status, observations, input_paths=paths,
                               settings=settings, g_local_mps2=g_local_mps2)


@task(name="fit-scalar", cache_policy=NO_CACHE)
def fit_scalar(runs, settings: calibration.CalibrationSettings):
    from pipeline.calibrate.scalar import calibrate_scalar

    return calibrate_scalar(runs, settings=settings)


@task(name="fit-differential", cache_policy=NO_CACHE)
def fit_differential(runs, base_passport: dict, settings: calibration.CalibrationSettings):
    from pipeline.calibrate.differential import calibrate_differential

    return calibrate_differential(runs, base_passport, calibration_settings=settings)


@task(name="write", cache_policy=NO_CACHE)
def write_method(registry: str, mc, paths, settings: dict):
    return publish_passport(registry, mc.passport, mc.fit, mc.rows, mc.status, mc.plateaus, input_paths=paths,
                            settings=settings)


@flow(name="thermocal-calibrate", log_prints=False)
def calibrate_flow(paths: list[str], registry: str,
                   settings: calibration.CalibrationSettings = calibration.CalibrationSettings(),
                   method: str = "tilt", base_passport: dict | None = None) -> dict:
    """Calibrate one unit from one or more runs (TP runs, and runs with VP data that verify them).

    ``method``: ``tilt`` (seed 000, default), ``scalar`` (seed 004) or ``differential`` (seed 003, starting from
    ``base_passport``'s normal-temperature constants)."""
    logger = get_run_logger()
    runs = [ingest(p) for p in paths]
    unit = calibration.unit_of(runs)
    if method == "tilt":
        result = _calibrate_tilt(runs, registry, settings, list(paths), logger)
    else:
        if method == "scalar":
            mc = fit_scalar(runs, settings)
            extra = {}
        else:
            mc = fit_differential(runs, base_passport, settings)
            extra = {"base_passport_sha256": base_passport.get("content_sha256") or base_passport.get("unit")}
        result = write_method(registry, mc, list(paths), {**settings.to_dict(), **extra})
        result["warnings"] = [w for r in runs for w in r.warnings] + list(mc.passport.get("notes", []))
    create_markdown_artifact(key=_artifact_key(unit), markdown=result_markdown(result),
                             description=f"thermocal calibration of {unit}")
    return result


def _calibrate_tilt(runs, registry, settings, paths, logger) -> dict:
    observations, warnings = [], []
    for run in runs:
        obs, warn = segment(run, settings)
        observations += obs
        warnings += warn
    for w in warnings:
        logger.warning(w)
    meta = runs[0].meta
    unit_fit = fit(meta.unit_serial, observations, settings, meta.normal_temp_c)
    rows, status = verify(unit_fit.model, observations, meta.normal_temp_c, settings)
    result = write(registry, unit_fit, rows, status, observations, paths, settings, meta.g_local_mps2)
    result["warnings"] = warnings + unit_fit.skipped
    return result


def _artifact_key(unit: str) -> str:
    safe = "".join(c if c.isalnum() else "-" for c in unit.lower()).strip("-")
    return f"calibration-{safe or 'unit'}"


def result_markdown(result: dict) -> str:
    lines = [f"# {result['unit']}: passport v{result['version']} ({result['status']})", "",
             f"`{result['passport']}`", "", "| plateau C | positions |", "|---:|---|"]
    lines += [f"| {p['temp_c']:+.2f} | {' '.join(p['positions'])} |" for p in result["plateaus"]]
    if result["verification"]:
        lines += ["", "| T C | VP | dg uncomp. ug | dg m1 ug | dg m2 ug |", "|---:|---|---:|---:|---:|"]
        lines += [f"| {v['temp_c']:+.1f} | {v['position']} | {v['dg_uncompensated_g'] * 1e6:.1f} | "
                  f"{v['dg_method1_g'] * 1e6:.1f} | {v['dg_method2_g'] * 1e6:.1f} |" for v in result["verification"]]
    return "\n".join(lines)


def run_calibrate(paths: list[str], registry: str, settings: calibration.CalibrationSettings,
                  method: str = "tilt", base_passport: dict | None = None) -> dict:
    """Run the flow in this process (local ephemeral Prefect unless PREFECT_API_URL is set)."""
    from .runtime import flow_settings, quiet_task_failures

    with flow_settings(), quiet_task_failures():
        return calibrate_flow(paths, registry, settings, method, base_passport)
