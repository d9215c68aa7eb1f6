"""The calibration flow: ingest -> (choose) -> observe -> fit -> write, one Prefect task per step (per file for
ingest and observe). Each task is a call of one library function; the method
(:class:`pipeline.calibrate.method.Method` from the registry ``pipeline.calibrate.methods``: ``tilt``, seed 000;
``scalar``, seed 004; ``differential``, seed 003, from a base passport or, on sweeps, from the orientations)
supplies observe and fit:

- ingest:  ``pipeline.io.runs.read_run``
- choose:  with ``method="auto"`` (the command line's default) the first run's segmentation
  and the method the recording supports (``pipeline.calibrate.methods.resolve_auto``, shared with the fleet);
  observe reuses that segmentation (the run is read and segmented once)
- observe: ``Method.observe`` (e.g. ``pipeline.calibrate.observations``: segmentation and per-segment averages)
- fit:     ``Method.calibrate_observed`` (the method's fit: constants, thermal model; then the tail every method
  shares, ``Method.finish``: VP verification, plausibility, passport document)
- write:   ``pipeline.calibrate.publish.publish`` (``pipeline.passport.registry``, ``pipeline.plots``)
"""

from __future__ import annotations

import os

from .runtime import Steps, prefect_defaults

prefect_defaults()

from prefect import flow, get_run_logger, task  # noqa: E402
from prefect.artifacts import create_markdown_artifact  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402  (no input hashing: a Run is large and never reused)

from pipeline.calibrate.inputs import select_runs  # noqa: E402
from pipeline.calibrate.methods import by_name, default_base_passport, resolve_auto  # noqa: E402
from pipeline.calibrate.observations import ObservedRun, unit_of  # noqa: E402
from pipeline.calibrate.publish import publish  # noqa: E402
from pipeline.calibrate.result import CalibrationResult  # noqa: E402
from pipeline.calibrate.settings import CalibrationSettings  # noqa: E402
from pipeline.errors import ThermocalError  # noqa: E402
from pipeline.io import runs as runio  # noqa: E402
from pipeline.passport.canonical import canonical_json  # noqa: E402
from pipeline.passport.registry import Registry  # noqa: E402
from pipeline.run import Run  # noqa: E402
from pipeline.segment import Segmentation  # noqa: E402


@task(name="ingest", cache_policy=NO_CACHE)
def ingest(path: str) -> Run:
    return runio.read_run(path)


@task(name="choose", cache_policy=NO_CACHE)
def choose(
    run: Run, settings: CalibrationSettings, base_passport: dict | None
) -> tuple[str, dict | None, Segmentation, str]:
    """``--method auto``: the method the run supports, the base passport if it needs one, the run's segmentation
    and why (``pipeline.calibrate.methods.resolve_auto``)."""
    return resolve_auto(run, settings, base_passport)


@task(name="observe", cache_policy=NO_CACHE)
def observe(
    run: Run,
    method: str,
    settings: CalibrationSettings,
    base_passport: dict | None,
    segmentation: Segmentation | None = None,
) -> ObservedRun:
    return by_name(method).observe(run, settings, base_passport=base_passport, segmentation=segmentation)


@task(name="fit", cache_policy=NO_CACHE)
def fit(
    observed: list[ObservedRun], method: str, settings: CalibrationSettings, base_passport: dict | None
) -> CalibrationResult:
    return by_name(method).calibrate_observed(observed, settings, base_passport=base_passport)


def record_head(registry: str) -> None:
    """The registry's signed head statement (``passport head``) as a Prefect artifact, for a later ``passport
    verify --against``; a registry that does not verify gets an artifact saying why instead. (Not a task: the
    flows' task lists are their calibration steps.)"""
    try:
        text = "```json\n" + canonical_json(Registry(registry).head()).decode("ascii") + "```"
    except ThermocalError as e:
        text = f"no head statement: {e.one_line()}"
    create_markdown_artifact(
        key="registry-head", markdown=text, description=f"thermocal: signed head statement of the registry {registry}"
    )


@task(name="write", cache_policy=NO_CACHE)
def write(
    registry: str,
    calibration: CalibrationResult,
    paths: list[str],
    settings: CalibrationSettings,
    dry_run: bool = False,
) -> dict:
    return publish(registry, calibration, input_paths=paths, settings=settings, constants_figure=True, dry_run=dry_run)


@flow(name="thermocal-calibrate", log_prints=False)
def calibrate_flow(
    paths: list[str],
    registry: str,
    settings: CalibrationSettings = CalibrationSettings(),
    method: str = "tilt",
    base_passport: dict | None = None,
    dry_run: bool = False,
) -> dict:
    """Calibrate one unit from one or more runs (TP runs, and runs with VP data that verify them).

    ``method``: ``tilt`` (seed 000, default), ``scalar`` (seed 004), ``differential`` (seed 003, starting from
    ``base_passport``'s normal-temperature constants; without one, from the unit's current passport in the
    registry, else from the orientations alone) or ``auto`` (the method the first run supports: the result's
    ``method_auto`` says which and why). ``dry_run``: compute everything, write nothing to the registry."""
    logger = get_run_logger()
    step = Steps("calibrate")  # progress lines on stderr when it is a terminal
    if method != "auto":
        by_name(method)  # an unknown method fails before any run is read
    runs = []
    for p in paths:
        step(f"ingest {os.path.basename(p)}")
        runs.append(ingest(p))
    path_of = {r.source: p for p, r in zip(paths, runs)}
    runs, selection_warnings = select_runs(runs)  # one file per run_id (a truncated copy is left out)
    paths = [path_of[r.source] for r in runs]
    unit = unit_of(runs)
    segmentation, chosen = None, None  # the first run's, when made to choose the method
    if method == "auto":
        step(f"choose the method (segment {os.path.basename(paths[0])})")
        method, base_passport, segmentation, chosen = choose(runs[0], settings, base_passport)
    base_line = None  # which version the differential method starts from, and its status
    if not by_name(method).uses_base_passport:
        base_passport = None
    elif base_passport is None:
        base_passport, base_line = default_base_passport(registry, unit)
    observed = []
    for k, (run, p) in enumerate(zip(runs, paths)):
        seg = segmentation if k == 0 else None
        step(f"observe ({'average' if seg else 'segment, average'}) {os.path.basename(p)}")
        observed.append(observe(run, method, settings, base_passport, seg))
    del runs  # the samples are not needed past the observations
    step(f"fit ({method}: constants, thermal model, VP verification)")
    calibration = fit(observed, method, settings, base_passport)
    calibration.warnings[:0] = selection_warnings + ([base_line] if base_line and base_passport is None else [])
    for w in calibration.warnings:
        logger.warning(w)
    step("write" if not dry_run else "dry run (nothing written)")
    result = write(registry, calibration, list(paths), settings, dry_run)
    if not dry_run:
        record_head(registry)
    create_markdown_artifact(
        key=_artifact_key(unit), markdown=result_markdown(result), description=f"thermocal calibration of {unit}"
    )
    if chosen:
        result["method_auto"] = chosen
    if base_line and base_passport is not None:
        result["base_passport_used"] = base_line
    step(f"done: {unit} v{result['version']} {result['status']}")
    return result


def _artifact_key(unit: str) -> str:
    safe = "".join(c if c.isalnum() else "-" for c in unit.lower()).strip("-")
    return f"calibration-{safe or 'unit'}"


def result_markdown(result: dict) -> str:
    lines = [
        f"# {result['unit']}: passport v{result['version']} ({result['status']})",
        "",
        f"`{result['passport']}`",
        "",
        "| plateau C | positions |",
        "|---:|---|",
    ]
    lines += [f"| {p['temp_c']:+.2f} | {' '.join(p['positions'])} |" for p in result["plateaus"]]
    if result["verification"]:
        lines += ["", "| T C | VP | dg uncomp. ug | dg m1 ug | dg m2 ug |", "|---:|---|---:|---:|---:|"]
        lines += [
            f"| {v['temp_c']:+.1f} | {v['position']} | {v['dg_uncompensated_g'] * 1e6:.1f} | "
            f"{v['dg_method1_g'] * 1e6:.1f} | {v['dg_method2_g'] * 1e6:.1f} |"
            for v in result["verification"]
        ]
    return "\n".join(lines)


def run_calibrate(
    paths: list[str],
    registry: str,
    settings: CalibrationSettings,
    method: str = "tilt",
    base_passport: dict | None = None,
    dry_run: bool = False,
) -> dict:
    """Run the flow in this process, recorded on thermocal's local Prefect server
    (:func:`flows.runtime.flow_settings`)."""
    from .runtime import flow_settings, quiet_task_failures

    with flow_settings(), quiet_task_failures():
        return calibrate_flow(paths, registry, settings, method, base_passport, dry_run)
