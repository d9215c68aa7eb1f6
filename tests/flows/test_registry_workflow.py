"""The lab's registry workflow from the command line: calibrate --dry-run writes nothing, a calibration whose
status is fail exits 1 with its JSON printed, passport approve makes a version the current passport, and the
differential method starts from the current passport (never a failed newest one)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.calibrate import tilt
from pipeline.calibrate.methods import base_passport_of
from pipeline.calibrate.publish import publish
from pipeline.errors import ThermocalError
from pipeline.io.runs import read_run, write_run
from pipeline.passport.registry import Registry
from pipeline.simulate.chamber import SimConfig, simulate

pytestmark = pytest.mark.slow  # Prefect flows end to end

REPO = Path(__file__).resolve().parents[2]
EXE = str(Path(sys.executable).parent / "thermocal")


def test_cli_dry_run_of_a_failing_calibration_exits_1_and_writes_nothing(tmp_path):
    sample = REPO / "sample_data" / "standard_short.mcap"
    reg = tmp_path / "reg"
    cmd = [
        EXE,
        "calibrate",
        str(sample),
        "--registry",
        str(reg),
        "--dry-run",
        "--json",
        "--tol-normal-g",
        "1e-9",
        "--tol-range-g",
        "1e-9",
    ]
    p = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ), timeout=600)
    assert p.returncode == 1, p.stderr
    r = json.loads(p.stdout)  # the JSON is printed all the same
    assert r["status"] == "fail" and r["dry_run"] is True and r["version"] == 1 and r["passport"] is None
    assert r["passport_content"]["uncertainty"]["coefficients"]["K"] and r["passport_content"]["valid_temp_c"]
    # our one line (on a loaded machine Prefect's ephemeral server may log its own shutdown after it)
    ours = [line for line in p.stderr.splitlines() if line.startswith("thermocal:")]
    assert len(ours) == 1 and "status fail" in ours[0] and p.stderr.startswith("thermocal:")
    assert not reg.exists()  # nothing written


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A short run calibrated into a registry as v1 (status fail: impossible limits) and v2 (pass), in process;
    each publish preceded by its dry run, which names the same version and writes nothing."""
    d = tmp_path_factory.mktemp("wf")
    run_path = write_run(simulate(SimConfig(seed=8, program="short", rate_hz=1.0)).run, d / "short.mcap", "mcap")
    run = read_run(run_path)
    reg = d / "reg"
    results = []
    for tol in ({"tol_normal_g": 1e-9, "tol_range_g": 1e-9}, {}):
        settings = tilt.CalibrationSettings(**tol)
        cal = tilt.calibrate([run], settings)
        before = sorted(p.name for p in reg.rglob("*")) if reg.exists() else []
        dry = publish(reg, cal, input_paths=[str(run_path)], settings=settings, figure=False, dry_run=True)
        assert (sorted(p.name for p in reg.rglob("*")) if reg.exists() else []) == before
        res = publish(reg, cal, input_paths=[str(run_path)], settings=settings, figure=False)
        assert dry["dry_run"] and dry["version"] == res["version"] and dry["status"] == res["status"]
        results.append(res)
    assert [r["status"] for r in results] == ["fail", "pass"] and [r["version"] for r in results] == [1, 2]
    return run_path, reg, run


def test_dry_run_names_the_existing_version(calibrated):
    run_path, reg, run = calibrated
    settings = tilt.CalibrationSettings()
    cal = tilt.calibrate([run], settings)
    before = sorted(p.name for p in (reg / "units" / "AU-0001").iterdir())
    dry = publish(reg, cal, input_paths=[str(run_path)], settings=settings, dry_run=True)
    assert dry["existing"] is True and dry["version"] == 2 and dry["figure"] is None
    assert dry["passport_content"]["uncertainty"] is not None
    assert sorted(p.name for p in (reg / "units" / "AU-0001").iterdir()) == before


def test_cli_approve_and_differential_base_is_the_current_passport(calibrated, tmp_path):
    from pipeline.calibrate.methods import default_base_passport

    _, reg, _ = calibrated
    registry = Registry(reg)
    # v2 (pass) is the newest: the base; a failed newest version with nothing approved is refused
    base, line = default_base_passport(reg, "AU-0001")
    assert base.version == 2
    assert line == (
        "differential base: AU-0001 v2 (status pass, not approved; the current passport: the newest "
        "version that did not fail, none is approved)"
    )
    p = subprocess.run(
        [EXE, "passport", "approve", "AU-0001", "1", "--by", "A. Metrologist", "--registry", str(reg)],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        timeout=120,
    )
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "fail" in p.stderr
    p = subprocess.run(
        [EXE, "passport", "approve", "AU-0001", "2", "--by", "A. Metrologist", "--registry", str(reg), "--json"],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["current_version"] == 2 and out["approval"]["by"] == "A. Metrologist"
    assert registry.current("AU-0001") == 2 and registry.verify().ok
    # a newer failed version does not displace the approved one as the base
    failing = registry.load("AU-0001", 1)
    failing = {k: v for k, v in failing.items() if k not in ("signature", "content_sha256")}
    registry.publish(failing, inputs=[{"path": "other", "sha256": "e" * 64}], settings={}, code_version="t")
    assert registry.current("AU-0001") == 2 and default_base_passport(reg, "AU-0001")[0].version == 2
    # a registry whose only version failed, nothing approved: a failed calibration is never the current passport
    # (issue 26): there is none, and no base (the differential method then takes the constants at T0 from the
    # orientations themselves, and says why)
    reg2 = Registry(tmp_path / "reg2")
    reg2.publish(failing, inputs=[{"path": "other", "sha256": "e" * 64}], settings={}, code_version="t")
    assert reg2.state("AU-0001") is None and reg2.current("AU-0001") is None
    state = reg2.state("AU-0001", 1)
    assert state.text() == "AU-0001 v1 (status fail, not approved)" and "failed its verification" in state.warning()
    with pytest.raises(ThermocalError, match="failed its verification"):
        base_passport_of(reg2, "AU-0001")
    base, line = default_base_passport(tmp_path / "reg2", "AU-0001")
    assert base is None and "no current passport" in line and "from the orientations themselves" in line


def test_diagnose_registry_compares_with_the_current_passport(calibrated, tmp_path):
    """diagnose --registry: the unit's current passport (v2, approved above, though a newer v3 exists)."""
    from flows.diagnose_cmd import diagnose_command

    run_path, reg, _ = calibrated
    assert Registry(reg).current("AU-0001") == 2 and len(Registry(reg).versions("AU-0001")) == 3
    rep = diagnose_command(run_path, None, True, tmp_path / "d.png", tmp_path / "d.json", registry=reg)
    assert "AU-0001 v2 (status pass, approved by A. Metrologist)" in rep["passport_source"]
    used = dict(rep["passport_used"])
    assert used.pop("verification")["verified"] is True
    assert used == {
        "unit": "AU-0001",
        "version": 2,
        "status": "pass",
        "approved": True,
        "approved_by": ["A. Metrologist"],
        "current": True,
    }
    assert rep["verdict"] == "consistent" and rep["findings"] == []
    # nothing approved and the newest version failed: a failed calibration is never the current passport (issue
    # 26): the newest that did not fail is
    reg3 = Registry(tmp_path / "reg3")
    for v in (2, 1):
        doc = Registry(reg).load("AU-0001", v)
        reg3.publish(
            {k: x for k, x in doc.items() if k not in ("signature", "content_sha256")},
            inputs=[{"path": f"r{v}", "sha256": str(v) * 64}],
            settings={},
            code_version="t",
        )
    rep = diagnose_command(run_path, None, True, tmp_path / "d3.png", tmp_path / "d3.json", registry=reg3.root)
    assert rep["passport_used"]["version"] == 1 and rep["passport_used"]["status"] == "pass"
    assert "AU-0001 v1 (status pass, not approved; the current passport" in rep["passport_source"]
    assert not any("failed its verification" in n for n in rep.get("notes", []))
