"""Writing a calibration into the registry: passport, provenance, and the verification figure beside it."""

from __future__ import annotations

from pathlib import Path

from .calibration import CalibrationSettings, UnitFit, calibration_result, plateau_summary
from .passport import build_passport
from .provenance import code_version, input_digest
from .registry import Registry


def publish_calibration(registry_root: str | Path, fit: UnitFit, rows, status: str, observations, *,
                        input_paths: list[str], settings: CalibrationSettings, g_local_mps2: float,
                        method: str = "tilt_six_position", figure: bool = True) -> dict:
    """Build the passport, publish it as a new version (or find the identical existing one) and, for a new
    version, write ``<passport>.png`` with the VP errors before and after compensation. Returns the
    ``calibrate --json`` object."""
    plateaus = plateau_summary(observations)
    doc = build_passport(fit, rows, status, g_local_mps2=g_local_mps2, plateaus=plateaus, method=method)
    inputs = [{"path": str(Path(p).resolve()), "sha256": input_digest(p)} for p in input_paths]
    published = Registry(Path(registry_root)).publish(doc, inputs=inputs, settings=settings.to_dict(),
                                                      code_version=code_version())
    result = calibration_result(fit, rows, status, plateaus, published)
    fig = Path(published.path).with_suffix(".png")
    if figure and (published.created or not fig.exists()):
        from .plots import plot_verification

        try:
            plot_verification(rows, fig, title=f"{fit.unit} v{published.version}: VP gravity-module error")
        except OSError:
            pass  # the figure is a convenience; the passport is written
    result["figure"] = str(fig) if fig.exists() else None
    return result
