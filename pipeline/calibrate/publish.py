"""Writing a calibration into the registry: passport, provenance, and the verification figure beside it."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Mapping
from pathlib import Path

from pipeline.calibrate.tilt import (
    CalibrationSettings,
    UnitFit,
    calibration_result,
    plateau_summary,
)
from pipeline.passport.document import build_passport
from pipeline.passport.provenance import RunDigest, code_version, input_digest
from pipeline.passport.registry import Registry


def provenance_settings(settings: dict, method: str) -> dict:
    """The settings a passport records in its provenance, and that its identity hashes with the input hashes
    (:func:`pipeline.passport.registry.identity_key`): the calibration settings and the method. The fleet's skip check
    (:func:`pipeline.calibrate.fleet.plan_fleet`) uses it too."""
    return {**settings, "method": method}


def publish_calibration(registry_root: str | Path, fit: UnitFit, rows, status: str, observations, *,
                        input_paths: list[str], settings: CalibrationSettings, g_local_mps2: float,
                        figure: bool = True, input_digests: Mapping[str, RunDigest] | None = None) -> dict:
    """Build the passport of seed 000's tilt method (``tilt_six_position``) and publish it with
    :func:`publish_passport`. Returns the ``calibrate --json`` object."""
    plateaus = plateau_summary(observations)
    doc = build_passport(fit, rows, status, g_local_mps2=g_local_mps2, plateaus=plateaus, method="tilt_six_position")
    return publish_passport(registry_root, doc, fit, rows, status, plateaus, input_paths=input_paths,
                            settings=settings.to_dict(), figure=figure, input_digests=input_digests)


def publish_passport(registry_root: str | Path, doc: dict, fit: UnitFit, rows, status: str, plateaus: list[dict], *,
                     input_paths: list[str], settings: dict, figure: bool = True,
                     input_digests: Mapping[str, RunDigest] | None = None) -> dict:
    """Publish a passport of any method as a new version (or find the identical existing one: same input hashes,
    same settings, same method) and, for a new version, write ``<passport>.png`` with the VP errors before and after
    compensation. Returns the ``calibrate --json`` object.

    ``input_digests``: hashes of the input paths made earlier (:func:`pipeline.passport.provenance.hash_run`, by the fleet's
    planning), reused for the runs not changed since (else the run is hashed again)."""
    known = input_digests or {}
    inputs = [{"path": str(Path(p).resolve()), "sha256": input_digest(p, known.get(str(p)))} for p in input_paths]
    settings = provenance_settings(settings, doc.get("method", "tilt_six_position"))
    published = Registry(Path(registry_root)).publish(doc, inputs=inputs, settings=settings,
                                                      code_version=code_version())
    result = calibration_result(fit, rows, status, plateaus, published)
    result["method"] = settings["method"]
    fig = Path(published.path).with_suffix(".png")
    if figure and (published.created or not fig.exists()):
        from pipeline.plots import plot_verification

        # drawn under a temporary name, then renamed: a killed writer or a full disk leaves no partial figure
        # (a leftover ".tmp-" file is removed by the registry at the unit's next publish)
        tmp = fig.with_name(f".tmp-{fig.stem}-{os.getpid()}.png")
        try:
            plot_verification(rows, tmp, title=f"{fit.unit} v{published.version}: VP gravity-module error")
            os.replace(tmp, fig)
        except OSError:
            pass  # the figure is a convenience; the passport is written
        finally:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
    result["figure"] = str(fig) if fig.exists() else None
    return result
