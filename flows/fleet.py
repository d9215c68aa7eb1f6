"""The fleet flow: calibrate every run under a folder, one passport per unit, past bad runs.

One flow run per fleet job, one task per unit (``calibrate-unit``, a call of
:func:`pipeline.calibrate.fleet.compute_group`): a unit's runs, TP runs and the VP runs that verify them, are
calibrated together. The units whose only runs are one run holding several units (or the files one such run was cut
into) are one task (``calibrate-units``, :func:`pipeline.calibrate.fleet.compute_run`): read and segmented once for
its units,
as ``thermocal calibrate`` does, so that both commands make the same passports from it. Planning (discovery,
metadata, content hashes, the registry's identity check) is :func:`pipeline.calibrate.fleet.plan_fleet`, run once in
the flow.

The tasks only compute; publishing happens in one place, the flow itself, as each unit's result comes back
(:func:`pipeline.calibrate.fleet.publish_group`: signed with this station's key, appended to the registry the user
named, its path made absolute here before anything runs). So a worker on another machine, with another working
folder or another key, neither writes a passport where the user did not ask nor signs one this station would not
trust; and a worker killed mid-unit loses nothing: dask runs that unit's task again elsewhere, and nothing of it was
written before its result reached the flow.

Where the unit tasks run is a flow parameter, so that a deployment can choose it too:

- ``dask_address="tcp://host:8786"``: on an existing dask.distributed cluster, through prefect-dask's
  ``DaskTaskRunner(address=...)``. The workers need thermocal installed and must reach the Prefect API: the flow's
  (:func:`run_fleet`: ``PREFECT_API_URL``, else thermocal's local server on 127.0.0.1, which serves workers on this
  machine only; for workers on other machines run ``prefect server start --host 0.0.0.0`` and set
  ``PREFECT_API_URL`` to it).
- else a local pool of ``workers`` (default: the machine's CPU count). ``pool="process"``: the unit tasks run in
  Prefect's ThreadPoolTaskRunner and each hands its calibration to a process pool of the flow's own
  (``concurrent.futures``, spawn, workers warmed by :func:`pipeline.calibrate.fleet.prepare_worker`, each leaving
  when the flow's process is gone: :func:`flows.runtime.pool_worker_init`), handed to the tasks as a parameter, so the
  computation runs in parallel past the GIL while Prefect's side of a task run (states, events) stays in the flow
  process. Prefect's ProcessPoolTaskRunner was dropped for this: it rebuilds Prefect's settings for every task
  run in the worker (~0.13 s of CPU per task, 15 % of a unit) and its workers import Prefect (~4 s to start).
  A task shows Running from the moment its unit is queued for a process (twice as many task threads as
  processes keep the processes busy); a worker process killed (OOM) breaks the pool, and the units not done by
  then fail with that reason, as they did on Prefect's process pool. ``pool="thread"``: the calibration runs in
  the task's thread (the GIL: JSON blocks and figures hold it). ``"auto"`` picks processes from
  :data:`AUTO_PROCESS_MIN_UNITS` units on (starting the workers costs ~1 s of CPU each), threads below. Figures:
  benchmarks/fleet_throughput.py and the README.

The flow returns the ``fleet --json`` object (docs/contract.md) and leaves a table artifact ``thermocal-fleet``.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
import time
from concurrent.futures import Executor, ProcessPoolExecutor

from .runtime import Steps, prefect_defaults

prefect_defaults()

from prefect import flow, get_run_logger, task  # noqa: E402
from prefect.artifacts import create_table_artifact  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402
from prefect.futures import as_completed  # noqa: E402
from prefect.runtime import flow_run  # noqa: E402

from pipeline.calibrate import fleet as fleet_plan  # noqa: E402
from pipeline.calibrate.settings import CalibrationSettings  # noqa: E402
from pipeline.passport.document import Passport  # noqa: E402

from .calibrate import record_head  # noqa: E402

#: ``pool="auto"``: a process pool from this many units on (its start-up pays off), else threads.
AUTO_PROCESS_MIN_UNITS = 4
ARTIFACT_KEY = "thermocal-fleet"


@task(name="calibrate-unit", task_run_name="calibrate-{unit}", cache_policy=NO_CACHE)
def calibrate_unit(
    unit: str,
    runs: list[str],
    settings: CalibrationSettings,
    method: str = "tilt",
    base_passport: Passport | None = None,
    within: dict | None = None,
    pool: Executor | None = None,
) -> fleet_plan.ComputedUnit:
    """:func:`pipeline.calibrate.fleet.compute_group` (no registry, no key: the flow publishes), in the process
    ``pool`` when given (the flow's), else here."""
    args = (unit, runs, settings, method, base_passport, within)
    return pool.submit(fleet_plan.compute_group, *args).result() if pool else fleet_plan.compute_group(*args)


@task(name="calibrate-units", task_run_name="calibrate-{name}", cache_policy=NO_CACHE)
def calibrate_units(
    name: str,
    run: list[str],
    bases: dict[str, Passport | None],
    settings: CalibrationSettings,
    method: str = "tilt",
    pool: Executor | None = None,
) -> list[fleet_plan.ComputedUnit]:
    """The units ``bases`` of ``run``, a run holding several units (or the files one was cut into) that is their
    only run, together: :func:`pipeline.calibrate.fleet.compute_run` (read and segmented once, as ``calibrate``
    does), in the process ``pool`` when given, else here. ``name``: the units, for the task run's name."""
    args = (run, bases, settings, method)
    return pool.submit(fleet_plan.compute_run, *args).result() if pool else fleet_plan.compute_run(*args)


def _submit(runner, batch: list[fleet_plan.UnitGroup], settings, method, pool):
    """The task of one batch of :meth:`pipeline.calibrate.fleet.FleetPlan.batches`: ``calibrate-units`` for the
    units of a run with several, ``calibrate-unit`` for one unit."""
    run = batch[0].shared_runs
    if run is None:
        (g,) = batch
        params = {
            "unit": g.unit,
            "runs": list(g.runs),
            "settings": settings,
            "method": method,
            "base_passport": g.base_passport,
            "within": g.within,
            "pool": pool,
        }
        return runner.submit(calibrate_unit, params)
    params = {
        "name": "+".join(g.unit for g in batch),
        "run": list(run),
        "bases": {g.unit: g.base_passport for g in batch},
        "settings": settings,
        "method": method,
        "pool": pool,
    }
    return runner.submit(calibrate_units, params)


def default_workers() -> int:
    """Workers of the local pool: the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def make_task_runner(dask_address: str | None, workers: int | None, pool: str, n_units: int):
    """The task runner for the unit tasks (see the module doc), its description, and the size of the process pool
    the tasks hand their calibration to (0: none)."""
    if dask_address:
        from prefect_dask import DaskTaskRunner

        return DaskTaskRunner(address=dask_address), f"DaskTaskRunner({dask_address})", 0
    from prefect.task_runners import ThreadPoolTaskRunner

    if pool not in fleet_plan.POOLS:
        raise ValueError(f"unknown pool {pool!r}; expected one of {', '.join(fleet_plan.POOLS)}")
    n = max(1, min(workers or default_workers(), n_units))
    if pool == "auto":
        pool = "process" if n > 1 and n_units >= AUTO_PROCESS_MIN_UNITS else "thread"
    if pool == "process":
        # twice as many task threads as processes: while a thread does Prefect's bookkeeping of a finished unit,
        # the next unit is already queued for the process that computed it (no process waits for a thread)
        threads = min(2 * n, n_units)
        return (
            ThreadPoolTaskRunner(max_workers=threads),
            f"ThreadPoolTaskRunner({threads}) + ProcessPoolExecutor({n})",
            n,
        )
    return ThreadPoolTaskRunner(max_workers=n), f"ThreadPoolTaskRunner({n})", 0


@contextlib.contextmanager
def _compute_pool(processes: int):
    """The flow's process pool of ``processes`` workers for the unit tasks (None if 0), for the duration."""
    if not processes:
        yield None
        return
    from .runtime import pool_worker_init  # a light module: its workers watch this process from their first second

    pool = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"), initializer=pool_worker_init)
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


class _Progress:
    """A rich progress bar and one line per unit on stderr (when ``show``: progress asked for and stderr a
    terminal, :class:`flows.runtime.Steps`); always a Prefect log line per unit."""

    def __init__(self, show: bool, total: int, logger):
        self.logger = logger
        self.bar = None
        if show and total:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )

            self.bar = Progress(
                TextColumn("fleet"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                console=Console(stderr=True),
                transient=False,
            )
            self.task = self.bar.add_task("units", total=total)

    def __enter__(self):
        if self.bar:
            self.bar.start()
        return self

    def __exit__(self, *exc):
        if self.bar:
            self.bar.stop()

    def unit_done(self, line: str, failures: list[dict]) -> None:
        self.logger.info(line)
        for f in failures:
            self.logger.warning(failure_line(f))
        if self.bar:
            self.bar.console.print(line, highlight=False)
            self.bar.advance(self.task)


def _fleet_run_name() -> str:
    """The flow run's name: the folder it calibrates (``fleet-inbox``), not a random pair of words."""
    from prefect.runtime import flow_run as current

    root = str((current.parameters or {}).get("root") or "")
    return f"fleet-{os.path.basename(os.path.normpath(root)) or 'runs'}"


@flow(name="thermocal-fleet", log_prints=False, flow_run_name=_fleet_run_name)
def fleet_flow(
    root: str,
    registry: str,
    settings: CalibrationSettings = CalibrationSettings(),
    dask_address: str | None = None,
    workers: int | None = None,
    pool: str = "auto",
    figures: bool = True,
    progress: bool = False,
    method: str = "tilt",
    trends: bool = False,
) -> dict:
    """Calibrate every run under ``root`` into ``registry`` by ``method`` (``pipeline.calibrate.methods``): one
    task per unit, bad runs reported, done units skipped. Returns the ``fleet --json`` object: ``done``, ``failed``,
    ``skipped`` (docs/contract.md), ``flow_run_id`` and ``timing`` (wall, planning and in-task compute seconds, the
    runner). ``trends``: then run the trends flow over the registry (:func:`flows.trends.trends_flow`, a subflow
    with its own table artifact); the summary gets ``trends``, the number of findings of each kind."""
    logger = get_run_logger()
    t0 = time.perf_counter()
    registry = os.path.abspath(registry)  # the registry the user named, whatever the workers' working folders
    step = Steps("fleet")  # progress only when asked and stderr is a terminal
    step.on = step.on and progress
    step(f"plan: find, read and hash the runs under {root}")
    plan = fleet_plan.plan_fleet(root, registry, settings, method)
    step(
        f"{plan.runs_found} runs: {len(plan.groups)} units to calibrate, {len(plan.skipped)} runs skipped, "
        f"{len(plan.failed)} unreadable"
    )
    logger.info(
        f"{plan.runs_found} runs under {root}: {len(plan.groups)} units to calibrate, "
        f"{len(plan.skipped)} runs skipped, {len(plan.failed)} unreadable"
    )
    for f in plan.failed:
        logger.warning(failure_line(f))
    for w in plan.warnings:
        logger.warning(w["warning"])
    t_plan = time.perf_counter() - t0
    outcomes: list[fleet_plan.UnitOutcome] = []
    runner_name = "none"
    if plan.groups:
        batches = plan.batches()
        runner, runner_name, processes = make_task_runner(dask_address, workers, pool, len(batches))
        with runner, _compute_pool(processes) as compute_pool, _Progress(step.on, len(plan.groups), logger) as bar:
            futures = {_submit(runner, batch, settings, method, compute_pool): batch for batch in batches}
            for fut in as_completed(list(futures)):
                batch = futures[fut]
                try:
                    got = fut.result()
                    computed = got if isinstance(got, list) else [got]
                except Exception as exc:
                    reason = fleet_plan.reason_of(exc)
                    computed = [
                        fleet_plan.ComputedUnit(
                            g.unit, list(g.runs), None, [], [{"run": r, "reason": reason} for r in g.runs], 0.0
                        )
                        for g in batch
                    ]
                for w in (w for unit in computed for w in unit.run_warnings):  # a unit named, calibrated elsewhere
                    logger.warning(w["warning"])
                    plan.warnings.append(w)
                for group, unit in zip(batch, computed):  # the one place the fleet signs and writes: on the station
                    if unit.calibration is not None and group.warnings:  # found while planning: first, as calibrate
                        unit.calibration.warnings[:0] = list(group.warnings)
                    outcome = fleet_plan.publish_group(registry, unit, settings, figures, group.digests, group.within)
                    outcomes.append(outcome)
                    bar.unit_done(_unit_line(outcome, len(outcomes), len(plan.groups)), outcome.failed)
    summary = fleet_summary(plan, outcomes)
    summary["flow_run_id"] = str(flow_run.id)
    summary["timing"] = {
        "wall_s": time.perf_counter() - t0,
        "plan_s": t_plan,
        "compute_s": sum(o.compute_s for o in outcomes),
        "units": len(outcomes),
        "runner": runner_name,
    }
    create_table_artifact(
        key=ARTIFACT_KEY,
        table=summary_table(summary),
        description=f"thermocal fleet over {root}: {len(summary['done'])} units done, "
        f"{len(summary['failed'])} runs failed, {len(summary['skipped'])} skipped",
    )
    if outcomes:
        record_head(str(registry))
    if trends and os.path.isdir(registry):
        from .trends import KINDS, trends_flow

        report = trends_flow(str(registry))
        summary["trends"] = {k: len(report[k]) for k in KINDS}
    return summary


def failure_line(f: dict) -> str:
    """A failed run, or unit of a run, in one line: its reason, which names the file (else prefixed with it) and the
    unit (else followed by it: a unit of a run with several whose calibration failed, e.g. ``voltmeter: ...: no
    temperature plateau ...``, would not say which)."""
    line = str(f["reason"])
    if f.get("run") and str(f["run"]) not in line:
        line = f"{f['run']}: {line}"
    if f.get("unit") and str(f["unit"]) not in line:
        line += f" (unit {f['unit']})"
    return line


def _unit_line(o: fleet_plan.UnitOutcome, k: int, total: int) -> str:
    if o.result is None:
        head = f"{o.unit}: FAILED ({o.failed[0]['reason'] if o.failed else 'no runs'})"
    else:
        r = o.result
        head = (
            f"{o.unit}: v{r['version']} {r['status']}{'' if r.get('created', True) else ' (existing)'}, "
            f"{len(o.used_runs)} run(s)" + (f", {len(o.failed)} dropped" if o.failed else "")
        )
    return f"[{k}/{total}] {head} ({o.compute_s:.1f} s)"


def fleet_summary(plan: fleet_plan.FleetPlan, outcomes: list[fleet_plan.UnitOutcome]) -> dict:
    """The ``fleet --json`` object: done units (by serial, each with its calibration's warnings: a truncated file, a
    VP segment off every plateau, ...), failed runs, skipped runs, warnings (by path)."""
    done, failed = [], list(plan.failed)
    for o in sorted(outcomes, key=lambda o: o.unit):
        if o.result is not None:
            r = o.result
            done.append(
                {
                    "unit": o.unit,
                    "version": r["version"],
                    "status": r["status"],
                    "runs": o.used_runs,
                    "created": bool(r.get("created", True)),
                    "passport": r["passport"],
                    "passport_sha256": r["passport_sha256"],
                    "warnings": list(r.get("warnings") or []),
                }
            )
        failed += [{**f, "unit": o.unit} for f in o.failed]
    return {
        "done": done,
        "failed": sorted(failed, key=lambda f: f["run"]),
        "skipped": sorted(plan.skipped, key=lambda s: s["run"]),
        "warnings": sorted(plan.warnings, key=lambda w: w["run"]),
    }


def summary_table(summary: dict) -> list[dict]:
    """Rows of the table artifact: one per done unit, failed run, skipped run."""
    rows = [
        {
            "unit": d["unit"],
            "outcome": "done",
            "version": d["version"],
            "status": d["status"],
            "runs": ", ".join(os.path.basename(r) for r in d["runs"]),
            "detail": "" if d["created"] else "existing",
        }
        for d in summary["done"]
    ]
    rows += [
        {
            "unit": f.get("unit", ""),
            "outcome": "failed",
            "version": "",
            "status": "",
            "runs": os.path.basename(f["run"]),
            "detail": f["reason"],
        }
        for f in summary["failed"]
    ]
    rows += [
        {
            "unit": ", ".join(s.get("units", [])),
            "outcome": "skipped",
            "version": s.get("version", ""),
            "status": "",
            "runs": os.path.basename(s["run"]),
            "detail": s["why"],
        }
        for s in summary["skipped"]
    ]
    return rows


def run_fleet(
    root: str,
    registry: str,
    settings: CalibrationSettings = CalibrationSettings(),
    *,
    dask_address: str | None = None,
    workers: int | None = None,
    pool: str = "auto",
    figures: bool = True,
    progress: bool = False,
    method: str = "tilt",
    local_server: bool = True,
) -> dict:
    """Run the fleet flow in this process, recorded on ``PREFECT_API_URL`` or thermocal's local Prefect server
    (``local_server=False``: Prefect's own choice; :func:`flows.runtime.flow_settings`). Progress (when asked for)
    and the flow's log lines reach stderr only when it is a terminal; the flow run's logs in Prefect are kept either
    way."""
    from .runtime import flow_settings, run_logs_off_console

    with flow_settings(local_server), run_logs_off_console(not Steps("fleet").on):
        return fleet_flow(
            str(root),
            str(registry),
            settings,
            dask_address=dask_address,
            workers=workers,
            pool=pool,
            figures=figures,
            progress=progress and sys.stderr is not None,
            method=method,
        )
