"""A small real registry for the human-readable output and the certificate: two versions of one unit calibrated
from a short simulated run (2 Hz voltmeter), by the same library steps as the calibration flow (no Prefect)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.calibrate import tilt
from pipeline.calibrate.publish import publish
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate


@pytest.fixture(scope="session")
def calibrated_registry(tmp_path_factory) -> dict:
    """``{"registry": Path, "unit": str, "results": [calibrate result v1 (auto model), v2 (piecewise)], "run"}``."""
    root = tmp_path_factory.mktemp("human")
    run_path = write_run(simulate(SimConfig(program="short", rate_hz=2.0, seed=11)).run, root / "run.mcap", "mcap")
    run = read_run(run_path)
    observed = [tilt.observe(run)]
    results = []
    for model in ("auto", "piecewise"):
        settings = CalibrationSettings(thermal_model=model)
        result = tilt.calibrate_observed(observed, settings)
        results.append(publish(root / "registry", result, input_paths=[str(run_path)], settings=settings))
    return {"registry": root / "registry", "unit": run.meta.unit_serial, "results": results, "run": Path(run_path)}
