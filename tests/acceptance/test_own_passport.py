"""A recording agrees with the passport made from it (issue 26 item 7): sample_data's run against its own passport in
a registry was a `mismatch` (a "constants_shift" that improved the residual by a twentieth of the noise: 7 sigma by
the fit's own uncertainty); and 7 of 30 clean simulated short runs against their own passports. A change is now named
only when the recording shows it (pipeline.diagnose.shift.VISIBLE_FRACTION)."""

from __future__ import annotations

from pathlib import Path

import pytest

from flows.diagnose_cmd import diagnose_command
from pipeline.calibrate import tilt
from pipeline.calibrate.publish import publish
from pipeline.diagnose.diagnosis import diagnose_run
from pipeline.io.runs import read_run
from pipeline.simulate.chamber import SimConfig, simulate

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "standard_short.mcap"


def test_the_sample_is_consistent_against_its_own_passport_in_a_registry(tmp_path):
    run = read_run(SAMPLE)
    settings = tilt.CalibrationSettings()
    result = publish(tmp_path / "reg", tilt.calibrate([run], settings), input_paths=[str(SAMPLE)], settings=settings)
    assert result["status"] == "pass"
    rep = diagnose_command(SAMPLE, None, True, None, registry=tmp_path / "reg", out_dir=tmp_path / "out")
    assert rep["verdict"] == "consistent" and rep["findings"] == [], rep["findings"]
    assert rep["passport_used"]["version"] == 1 and rep["passport_used"]["verification"]["verified"]
    assert rep["rms_after_v"] < 1.1 * rep["rms_noise_v"]
    assert Path(rep["figure"]).parent == tmp_path / "out"


@pytest.mark.slow
def test_thirty_clean_runs_are_consistent_against_their_own_passports():
    """Short program at 2 Hz (about 4 s a seed): calibrate, then diagnose against that passport."""
    mismatched = []
    for seed in range(30):
        run = simulate(SimConfig(program="short", rate_hz=2.0, seed=seed)).run
        cal = tilt.calibrate([run], tilt.CalibrationSettings())
        assert cal.status == "pass", seed
        rep = diagnose_run(run, cal.passport).report
        if rep["verdict"] != "consistent":
            mismatched.append((seed, [f["effect"] for f in rep["findings"]]))
    assert mismatched == []
