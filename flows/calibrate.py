"""The calibration flow: ingest -> (choose) -> observe -> fit -> write, one Prefect task per step (per file for
ingest). Each task is a call of one library function; the method
(:class:`pipeline.calibrate.method.Method` from the registry ``pipeline.calibrate.methods``: ``tilt``, seed 000;
``scalar``, seed 004; ``differential``, seed 003, from a base passport or, on sweeps, from the orientations)
supplies observe and fit:

- ingest:  ``pipeline.io.runs.read_run``
- join:    the files given together are one recording (``pipeline.calibrate.inputs.select_runs``: copies left
  out; ``join_runs``: the files in time order as one run)
- choose:  with ``method="auto"`` (the command line's default) the recording's segmentation
  and the method it supports (``pipeline.calibrate.methods.resolve_auto``, shared with the fleet);
  observe reuses that segmentation (the recording is read and segmented once)
- observe: ``Method.observe`` (e.g. ``pipeline.calibrate.observations``: segmentation and per-segment averages)
- fit:     ``Method.calibrate_observed`` (the method's fit: constants, thermal model; then the tail every method
  shares, ``Method.finish``: VP verification, plausibility, passport document)
- write:   ``pipeline.calibrate.publish.publish`` (``pipeline.passport.registry``, ``pipeline.plots``)

A run holding several units (log-format.md) is read once (``pipeline.io.runs.read_units``), segmented once for the
run (``segment``: ``pipeline.segment_units.segment_units``, the still times by consensus of the units), then each
unit goes through choose, observe, fit and write as above, in one task run a unit (``calibrate-unit``, as the
fleet's); a unit that fails (its input checks, or its
calibration) is reported with its reason and the others go on (:func:`calibrate_units`). A unit whose files are
several is one recording of them (``join_runs``), segmented as such; the units of a run with several split into
files are joined each and segmented together, by the consensus, so that each gets the whole file's passport.
"""

from __future__ import annotations

import contextlib
import functools
import os
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar, cast

from .runtime import Steps, prefect_defaults

prefect_defaults()

from prefect import flow, get_run_logger, task  # noqa: E402
from prefect.artifacts import create_markdown_artifact  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402  (no input hashing: a Run is large and never reused)
from prefect.utilities.annotations import opaque  # noqa: E402

from pipeline.calibrate.figure_worker import FigureWorker  # noqa: E402
from pipeline.calibrate.inputs import (  # noqa: E402
    absent_from_pieces,
    join_runs,
    joined_recordings,
    recordings_by_files,
    select_runs,
    units_span_ns,
)
from pipeline.calibrate.methods import by_name, default_base_passport, resolve_auto  # noqa: E402
from pipeline.calibrate.observations import ObservedRun, unit_of  # noqa: E402
from pipeline.calibrate.publish import publish  # noqa: E402
from pipeline.calibrate.result import CalibrationResult  # noqa: E402
from pipeline.calibrate.settings import CalibrationSettings  # noqa: E402
from pipeline.errors import ThermocalError  # noqa: E402
from pipeline.io import runs as runio  # noqa: E402
from pipeline.passport.canonical import canonical_json  # noqa: E402
from pipeline.passport.document import Passport, load_passport  # noqa: E402
from pipeline.passport.provenance import hash_run  # noqa: E402
from pipeline.passport.registry import Registry  # noqa: E402
from pipeline.run import Run, UnitRuns, check_serials  # noqa: E402
from pipeline.segment import Segmentation  # noqa: E402

T = TypeVar("T")


def _whole(value: T) -> T:
    """``value`` as a task input that Prefect links to the task run but does not walk through (``opaque``): Prefect
    looks for futures inside every input, twice a task run, and its walk through runs, segmentations, observations
    and calibrations was 7 % of a 16-unit calibrate; through the settings, paths and digests ~1 ms a task run."""
    return cast(T, opaque(value))


@task(name="ingest", cache_policy=NO_CACHE)
def ingest(path: str) -> UnitRuns:
    """The run at ``path`` with all its units, also when ``--unit`` names the ones to calibrate (checked over all the
    files given, :func:`pipeline.run.check_serials`): a run with several is segmented by the consensus of all its
    units, so that a unit's passport does not depend on which others were asked for (``fleet``, and ``calibrate``
    without ``--unit``, make the same); :func:`calibrate_units` calibrates the ``units`` alone."""
    return runio.read_units(path)


@task(name="segment", cache_policy=NO_CACHE)
def segment(units: dict[str, Run], settings: CalibrationSettings) -> tuple[dict[str, Segmentation], list[str]]:
    """The segmentation of every unit of a run with several units, once for the run."""
    from pipeline.segment_units import segment_units

    return segment_units(units, settings.segment)


@task(name="choose", cache_policy=NO_CACHE)
def choose(
    run: Run, settings: CalibrationSettings, base_passport: Passport | None, segmentation: Segmentation | None = None
) -> tuple[str, Passport | None, Segmentation, str]:
    """``--method auto``: the method the run supports, the base passport if it needs one, the run's segmentation
    and why (``pipeline.calibrate.methods.resolve_auto``)."""
    return resolve_auto(run, settings, base_passport, segmentation)


@task(name="observe", cache_policy=NO_CACHE)
def observe(
    run: Run,
    method: str,
    settings: CalibrationSettings,
    base_passport: Passport | None,
    segmentation: Segmentation | None = None,
) -> ObservedRun:
    return by_name(method).observe(run, settings, base_passport=base_passport, segmentation=segmentation)


@task(name="fit", cache_policy=NO_CACHE)
def fit(
    observed: list[ObservedRun], method: str, settings: CalibrationSettings, base_passport: Passport | None
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
    digests: dict | None = None,
    within: dict | None = None,
    draw=None,
) -> dict:
    return publish(
        registry,
        calibration,
        input_paths=paths,
        settings=settings,
        constants_figure=True,
        input_digests=digests,
        input_units=within,
        dry_run=dry_run,
        draw=draw,
    )


def _calibrate_run_name() -> str:
    """The flow run's name: the unit and the run it calibrates (``calibrate-AU-0001-2026-11-01-ch2``, ``+2`` for
    two more runs), read from the first run's metadata; the file's name when that cannot be read."""
    from prefect.runtime import flow_run as current

    paths = list((current.parameters or {}).get("paths") or [])
    if not paths:
        return "calibrate"
    try:
        meta = runio.read_run_meta(paths[0])
        name = f"calibrate-{meta.unit_serial}-{meta.run_id}"
    except ThermocalError:
        name = f"calibrate-{os.path.basename(str(paths[0]))}"
    return name + (f"+{len(paths) - 1}" if len(paths) > 1 else "")


@flow(name="thermocal-calibrate", log_prints=False, flow_run_name=_calibrate_run_name)
def calibrate_flow(
    paths: list[str],
    registry: str,
    settings: CalibrationSettings = CalibrationSettings(),
    method: str = "tilt",
    base_passport: dict | None = None,
    dry_run: bool = False,
    units: list[str] | None = None,
) -> dict:
    """Calibrate one unit from one or more runs (TP runs, and runs with VP data that verify them); runs holding
    several units: each unit (``units``: only these), :func:`calibrate_units`.

    ``method``: ``tilt`` (seed 000, default), ``scalar`` (seed 004), ``differential`` (seed 003, starting from
    ``base_passport``'s normal-temperature constants; without one, from the unit's current passport in the
    registry, else from the orientations alone) or ``auto`` (the method the recording supports: the result's
    ``method_auto`` says which and why). ``dry_run``: compute everything, write nothing to the registry."""
    step = Steps("calibrate")  # progress lines on stderr when it is a terminal
    if method != "auto":
        by_name(method)  # an unknown method fails before any run is read
    base = None if base_passport is None else load_passport(base_passport)  # the document a parameter, typed once
    several = _serials(paths, units) >= 2
    figures = None if dry_run or not several else FigureWorker()
    hashing = ThreadPoolExecutor(1)  # the files hashed in a thread (hashlib lets go of the GIL)
    try:
        # one unit: hashed while the files are read; several: while the run is segmented (one core), not beside the
        # reader's decompression threads, and the figure workers start (their imports) then too
        hashed = {} if several else {p: hashing.submit(hash_run, p) for p in paths}
        read = []
        for p in paths:
            step(f"ingest {os.path.basename(p)}")
            read.append(ingest(p))
        check_serials(read, units)  # a serial in no file; one missing from a piece is calibrated from the others
        hashed = hashed or {p: hashing.submit(hash_run, p) for p in paths}
        # a unit's steps from its runs and their paths, with what every unit of the command shares
        unit_steps = functools.partial(
            _calibrate_unit, registry=registry, settings=settings, method=method, base=base, dry_run=dry_run, step=step
        )
        with figures or contextlib.nullcontext():
            if any(r.several for r in read):
                result = calibrate_units(paths, read, unit_steps, settings, step, hashed, figures, units)
            else:
                digests = {p: f.result() for p, f in hashed.items()}
                result = unit_steps([r.select(units).one() for r in read], list(paths), digests=digests)
    finally:
        hashing.shutdown(wait=False, cancel_futures=True)
    if figures is not None and "units" in result:
        result["units"] = figures.results(result["units"])
    if not dry_run:
        record_head(registry)
    return result


def _serials(paths: list[str], units: list[str] | None) -> int:
    """How many units the files hold (of ``units``, when given), from their metadata (~1 ms a file); 0 when a file's
    cannot be read (the reading says why)."""
    try:
        found = {m.unit_serial for p in paths for m in runio.read_units_meta(p)[0]}
    except ThermocalError:
        return 0
    return len(found & set(units) if units else found)


def calibrate_units(paths, read, unit_steps, settings, step, hashed, draw=None, units=None) -> dict:
    """The runs ``read`` (:class:`pipeline.run.UnitRuns`, one per path) of which some hold several units: each
    unit calibrated from its runs (segmented once per run with several units), one after the other, the samples of
    a unit let go once it is observed. Returns ``{"units": [the calibrate object of each unit], "failed": [{"unit",
    "run", "reason"}]}`` (contract.md): a unit that failed its input checks or its calibration is listed with its
    one-line reason and the others go on. ``unit_steps(runs, paths, **kw)``: :func:`_calibrate_unit` with the
    command's registry, settings, method, base passport, dry run and progress bound; ``settings`` and ``step``: the
    same, for the segmentation and its progress line. ``hashed``: each path's
    :func:`pipeline.passport.provenance.hash_run` as a future, waited for once the runs are segmented (a file hashed
    once, not once per unit). ``draw``: publish's, for the figures drawn in other processes while the next unit is
    calibrated (:class:`pipeline.calibrate.figure_worker.FigureWorker`, which :func:`calibrate_flow` starts for two
    units or more). ``units``: only these are calibrated (``--unit``); every unit of a run takes part in its
    segmentation all the same."""
    logger = get_run_logger()
    failed: list[dict] = []
    by_unit: dict[str, list] = {}  # serial -> [(path, UnitRuns)]
    for p, got in zip(paths, read):
        failed += [{"unit": u, "run": p, "reason": why} for u, why in got.failed.items() if not units or u in units]
        for serial in got.units:
            by_unit.setdefault(serial, []).append((p, got))
    # a unit whose files are several is one recording of them (select_runs, join_runs): the units whose recordings
    # are the same files are segmented together, as the whole file holding them is (the consensus of their still
    # times over the joined recordings: a recording cut into files calibrates as the file it was cut from)
    joined = joined_recordings({s: [(p, got.units[s]) for p, got in items] for s, items in by_unit.items()})
    absent = absent_from_pieces(  # a unit missing from one of the files its run was cut into
        [(p, got.meta_values.get("run_id", ""), got.serials) for p, got in zip(paths, read) if got.several],
        lambda p: units_span_ns(read[paths.index(p)]),
    )
    segs: dict[str, dict] = {}  # path -> serial -> segmentation of the units calibrated from that file alone
    elsewhere: list[dict] = []  # a file's consensus line naming a unit whose passport comes from its joined files
    for p, got in zip(paths, read):
        if got.several and len(got.units) > 1 and any(s not in joined for s in got.units):
            step(f"segment {len(got.units)} units of {os.path.basename(p)} (still times once for the run)")
            segs[p], run_warnings = segment(_whole(got.units), settings)
            for w in run_warnings:
                logger.warning(w)
                if any(w.startswith(f"unit {s}: ") for s in joined if not units or s in units):
                    elsewhere.append({"run": p, "warning": w})  # its own passport cannot carry it: said by run
    joined_segs: dict[str, Segmentation] = {}
    for serials in recordings_by_files(joined).values():
        serials = [s for s in serials if any(got.several for _, got in by_unit[s])]
        if len(serials) > 1:
            step(
                f"segment {len(serials)} units of {_names(joined[serials[0]][1])} (still times once for the recording)"
            )
            got_segs, run_warnings = segment(_whole({s: joined[s][0] for s in serials}), settings)
            joined_segs.update(got_segs)
            for w in run_warnings:
                logger.warning(w)
    run_ids = {(p, s): got.units[s].meta.run_id for s, items in by_unit.items() for p, got in items}
    for serial in joined:  # the files' pieces of a joined unit are no longer needed
        for _, got in by_unit[serial]:
            got.units.pop(serial, None)
    for serial in [s for s in by_unit if units and s not in units]:
        joined.pop(serial, None)  # its samples were needed for the segmentation only
        for _, got in by_unit.pop(serial):
            got.units.pop(serial, None)
    digests = {p: f.result() for p, f in hashed.items()}
    results = []
    for serial, items in by_unit.items():
        recording = [(*joined.pop(serial), joined_segs.get(serial))] if serial in joined else None
        runs = [] if recording else [got.units[serial] for _, got in items]
        within = {p: {"unit": serial, "run_id": run_ids[p, serial]} for p, got in items if got.several}
        steps = functools.partial(
            unit_steps,
            runs,
            [p for p, _ in items],
            segmentations=[segs.get(p, {}).get(serial) for p, _ in items],
            digests=digests,
            within=within,
            release=lambda serial=serial, items=items: [got.units.pop(serial, None) for _, got in items],
            draw=draw,
            as_tasks=False,
            recording=recording,
            notes=absent.get(serial, []),
        )
        try:
            results.append(calibrate_unit(serial, _whole(steps)))
        except ThermocalError as e:
            failed.append({"unit": serial, "reason": e.one_line()})
            logger.warning(e.one_line())
        del runs, steps, recording
    return {"units": results, "failed": failed, **({"warnings": elsewhere} if elsewhere else {})}


@task(name="calibrate-unit", task_run_name="calibrate-{unit}", cache_policy=NO_CACHE)
def calibrate_unit(unit: str, steps) -> dict:
    """A unit of a run with several: its choose, observe, fit and write (``steps()``: :func:`_calibrate_unit`, the
    steps as plain calls) in one task run, as the fleet's ``calibrate-unit``. Four task runs a unit kept thermocal's
    local server (Prefect's API: each task run's state events) on most of a core while the units were calibrated."""
    return steps()


def _calibrate_unit(
    runs,
    paths: list[str],
    registry: str,
    settings: CalibrationSettings,
    method: str,
    base: Passport | None,
    dry_run: bool,
    step,
    segmentations: list | None = None,
    digests=None,
    within: dict | None = None,
    release=None,
    draw=None,
    as_tasks: bool = True,
    recording: list | None = None,
    notes: list[str] | None = None,
) -> dict:
    """One unit from its runs (one per path; ``segmentations``: each run's, where already made): select, choose,
    observe, fit, write, each a task run (``as_tasks=False``: plain calls, inside :func:`calibrate_unit`'s task run);
    ``release()`` is called once the samples are no longer needed; ``draw``: publish's, for figures drawn
    elsewhere. ``recording``: a list holding (the unit's files already selected and joined, the paths kept, the
    selection's warnings, the joined recording's segmentation or None), emptied here, in place of ``runs``.
    ``notes``: warnings about the unit's inputs found before (a piece of its run it is missing from), put first."""
    logger = get_run_logger()
    call = _as_task if as_tasks else _as_call
    if recording:
        run, paths, selection_warnings, segmentation = recording.pop()
        unit, chosen = run.meta.unit_serial, None
    else:
        segmentations = segmentations or [None] * len(runs)
        seg_of = {id(r): seg for r, seg in zip(runs, segmentations)}
        path_of = {id(r): p for p, r in zip(paths, runs)}
        runs, selection_warnings = select_runs(runs)  # one file per run_id (a truncated copy is left out)
        paths = [path_of[id(r)] for r in runs]
        segmentations = [seg_of[id(r)] for r in runs]
        unit = unit_of(runs)
        # the files given together are one recording (a segmentation made for one file holds for that file alone)
        segmentation, chosen = (segmentations[0] if len(runs) == 1 else None), None
        run = join_runs(runs)
        del runs
    if method == "auto":
        what = "" if segmentation is not None else f" (segment {_names(paths)})"
        step(f"choose the method for {unit}{what}")
        method, base, segmentation, chosen = call(choose, run, settings, base, segmentation)
    base_line = None  # which version the differential method starts from, and its status
    if not by_name(method).uses_base_passport:
        base = None
    elif base is None:
        base, base_line = default_base_passport(registry, unit)
    step(f"observe ({'average' if segmentation else 'segment, average'}) {unit} in {_names(paths)}")
    observed = [call(observe, run, method, settings, base, segmentation)]
    del run  # the samples are not needed past the observations
    if release is not None:
        release()
    step(f"fit ({method}: constants, thermal model, VP verification)")
    calibration = call(fit, observed, method, settings, base)
    calibration.warnings[:0] = [*(notes or []), *selection_warnings] + (
        [base_line] if base_line and base is None else []
    )
    for w in calibration.warnings:
        logger.warning(w)
    step("write" if not dry_run else "dry run (nothing written)")
    result = call(write, registry, calibration, list(paths), settings, dry_run, digests, within, draw)
    create_markdown_artifact(
        key=_artifact_key(unit), markdown=result_markdown(result), description=f"thermocal calibration of {unit}"
    )
    if chosen:
        result["method_auto"] = chosen
    if base_line and base is not None:
        result["base_passport_used"] = base_line
    step(f"done: {unit} v{result['version']} {result['status']}")
    return result


def _as_task(step, *args):
    """``step`` (a task) run as a task run, each input :func:`_whole`."""
    return step(*(_whole(a) for a in args))


def _as_call(step, *args):
    """``step`` (a task) called as the plain function it wraps (no task run)."""
    return step.fn(*args)


def _names(paths: list[str]) -> str:
    return " + ".join(os.path.basename(p) for p in paths)


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
    units: list[str] | None = None,
    local_server: bool = True,
) -> dict:
    """Run the flow in this process, recorded on ``PREFECT_API_URL`` or thermocal's local Prefect server
    (``local_server=False``: Prefect's own choice; :func:`flows.runtime.flow_settings`)."""
    from .runtime import flow_settings, quiet_task_failures

    with flow_settings(local_server), quiet_task_failures():
        return calibrate_flow(paths, registry, settings, method, base_passport, dry_run, units)
