"""A small real registry for the human-readable output and the certificate: two versions of one unit calibrated
from a short simulated run (2 Hz voltmeter), by the same library steps as the calibration flow (no Prefect)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.calibrate.publish import publish_calibration
from pipeline.calibrate.tilt import CalibrationSettings, fit_unit, observe_run, verify_unit
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate


@pytest.fixture(scope="session")
def calibrated_registry(tmp_path_factory) -> dict:
    """``{"registry": Path, "unit": str, "results": [calibrate result v1 (auto model), v2 (piecewise)]}``."""
    root = tmp_path_factory.mktemp("human")
    run_path = write_run(simulate(SimConfig(program="short", rate_hz=2.0, seed=11)).run, root / "run.mcap", "mcap")
    run = read_run(run_path)
    obs, _ = observe_run(run)
    results = []
    for model in ("auto", "piecewise"):
        settings = CalibrationSettings(thermal_model=model)
        fit = fit_unit(run.meta.unit_serial, obs, settings, run.meta.normal_temp_c)
        rows, status = verify_unit(fit.model, obs, run.meta.normal_temp_c, settings.tolerances)
        results.append(publish_calibration(root / "registry", fit, rows, status, obs, input_paths=[str(run_path)],
                                           settings=settings, g_local_mps2=run.meta.g_local_mps2))
    return {"registry": root / "registry", "unit": run.meta.unit_serial, "results": results, "run": Path(run_path)}
