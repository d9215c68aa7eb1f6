"""The one path that writes a calibration of any method into the registry: passport, provenance, and the
verification figure beside it (:func:`publish`), and the ``calibrate --json`` object it returns."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path

from pipeline.calibrate.figures import FigureJob, figure_beside
from pipeline.calibrate.result import CalibrationResult
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.passport.provenance import RunDigest, code_version, input_digest
from pipeline.passport.registry import Registry


def recorded_settings(settings: CalibrationSettings | dict, method: str, extra: Mapping | None = None) -> dict:
    """The settings a passport records in its provenance, and that its identity hashes with the input hashes
    (:func:`pipeline.passport.registry.identity_key`): the calibration settings, what else the method depends on
    (``extra``: :attr:`CalibrationResult.settings_extra`) and the method. The fleet's skip check
    (:func:`pipeline.calibrate.fleet.plan_fleet`) uses it too."""
    base = settings.to_dict() if isinstance(settings, CalibrationSettings) else dict(settings)
    return {**base, **(extra or {}), "method": method}


def calibration_json(result: CalibrationResult, published) -> dict:
    """The ``calibrate --json`` object of docs/contract.md for a published passport (``published`` None: a dry run,
    nothing written)."""
    return {
        "unit": result.unit,
        "version": published.version if published else None,
        "passport": str(published.path) if published else None,
        "passport_sha256": published.sha256 if published else None,
        "created": published.created if published else False,
        "plateaus": result.plateaus,
        "verification": [
            {
                "temp_c": r.temp_c,
                "position": r.position,
                "dg_uncompensated_g": r.dg_uncompensated_g,
                "dg_method1_g": r.dg_method1_g,
                "dg_method2_g": r.dg_method2_g,
            }
            for r in result.rows
        ],
        "status": result.status,
        "unit_grade": result.passport.get("unit_grade"),
        "tolerances": result.passport.get("tolerances"),
    }


def publish(
    registry_root: str | os.PathLike,
    result: CalibrationResult,
    *,
    input_paths: list[str],
    settings: CalibrationSettings,
    figure: bool = True,
    constants_figure: bool = False,
    input_digests: Mapping[str, RunDigest] | None = None,
    input_units: Mapping[str, dict] | None = None,
    dry_run: bool = False,
    draw: Callable[[FigureJob], object] | None = None,
) -> dict:
    """Publish a calibration of any method as a new version (or find the identical existing one: same input hashes,
    same settings, same method) and, for a new version, write ``<passport>.png`` with the VP errors before and after
    compensation, and with ``constants_figure`` ``<passport>.constants.png``, the constants per plateau against
    temperature with the thermal model (``thermocal calibrate`` draws it; the fleet does not). Returns the
    ``calibrate --json`` object (with ``method``, ``warnings``, ``figure`` and, when asked, ``constants_figure``).

    ``input_digests``: hashes of the input paths made earlier (:func:`pipeline.passport.provenance.hash_run`, by the
    fleet's planning), reused for the runs not changed since (else the run is hashed again).

    ``input_units``: for an input path that is one unit of a run with several units, ``{"unit", "run_id"}``
    recorded with it in the provenance (the run and the unit within it, log-format.md).

    ``dry_run`` (``calibrate --dry-run``): nothing is written (no version, no figure); the result says which
    version would be written (``version``) or which existing one has the same inputs and settings
    (``existing``: true), with ``dry_run``: true and the passport's content (``passport_content``).

    ``draw``: given, each figure to draw is handed to it as a :class:`pipeline.calibrate.figures.FigureJob` (for
    :func:`pipeline.calibrate.figures.draw_figure` elsewhere, e.g. by
    :class:`pipeline.calibrate.figure_worker.FigureWorker`'s process while the next unit is calibrated) and the result
    names the figure's path; the caller drops a path whose figure was not made
    (:func:`pipeline.calibrate.figures.drop_missing_figures`). The passport is the same either way."""
    known, within = input_digests or {}, input_units or {}
    notes = {str(Path(src).resolve()): v for src, v in result.input_notes.items()}
    inputs = [
        {
            "path": str(Path(p).resolve()),
            "sha256": input_digest(p, known.get(str(p))),
            **within.get(str(p), {}),
            **notes.get(str(Path(p).resolve()), {}),
        }
        for p in input_paths
    ]
    recorded = recorded_settings(settings, result.method, result.settings_extra)
    if dry_run:
        version, existing = Registry(Path(registry_root)).planned(result.passport, inputs=inputs, settings=recorded)
        out = calibration_json(result, None)
        out.update(
            version=version,
            existing=existing,
            dry_run=True,
            method=result.method,
            figure=None,
            warnings=list(result.warnings),
            passport_content=result.passport,
        )
        return out
    published = Registry(Path(registry_root)).publish(
        result.passport, inputs=inputs, settings=recorded, code_version=code_version()
    )
    out = calibration_json(result, published)
    out["method"] = result.method
    passport_path = Path(published.path)
    whole = passport_path.absolute()  # a job may be drawn by a process in another folder
    title = f"{result.unit} v{published.version}"
    jobs = {"figure": FigureJob(str(whole.with_suffix(".png")), "verification", title, rows=tuple(result.rows))}
    if constants_figure:
        jobs["constants_figure"] = FigureJob(
            str(whole.with_suffix(".constants.png")), "constants", title, passport=str(whole)
        )
    for (key, job), suffix in zip(jobs.items(), (".png", ".constants.png")):
        path, wanted = passport_path.with_suffix(suffix), figure or key == "constants_figure"
        if draw is not None and wanted and (published.created or not path.exists()):
            draw(job)
            out[key] = str(path)
        else:
            out[key] = figure_beside(path, wanted, published.created, job.draw)
    out["warnings"] = list(result.warnings)
    return out
