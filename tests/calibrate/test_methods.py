"""One recipe per method, used by every caller: the fleet runs any method (``plan_fleet``/``calibrate_group`` with
``method``), the differential method starts from the unit's newest non-differential passport (so a nightly fleet
does not chain versions), and diagnose's fitted passport is the tilt recipe's."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate import differential, ramp, scalar, tilt
from pipeline.calibrate.fleet import ALREADY_PROCESSED, calibrate_group, plan_fleet
from pipeline.calibrate.methods import base_passport_of, by_name, names
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import CalibrationError
from pipeline.io.runs import read_run, write_run
from pipeline.passport.registry import Registry
from pipeline.segment import segment_run
from pipeline.simulate.chamber import SimConfig, simulate


@pytest.fixture(scope="module")
def inboxes(tmp_path_factory):
    """AU-0001: a short-program run (2 Hz) in one inbox, a differential-program run (1 Hz) in another."""
    d = tmp_path_factory.mktemp("methods")
    short = write_run(simulate(SimConfig(seed=5, program="short", rate_hz=2)).run, d / "in1" / "short.mcap", "mcap")
    diff = write_run(
        simulate(
            SimConfig(seed=6, program="differential", rate_hz=1, effects=[("fixture_face_error", {"sigma_deg": 1.5})])
        ).run,
        d / "in2" / "diff.mcap",
        "mcap",
    )
    return short, diff


def _fleet(inbox: Path, registry: Path, method: str) -> tuple:
    plan = plan_fleet(inbox, registry, CalibrationSettings(), method)
    outcomes = [
        calibrate_group(
            g.unit,
            g.runs,
            registry,
            CalibrationSettings(),
            figure=False,
            digests=g.digests,
            method=method,
            base_passport=g.base_passport,
        )
        for g in plan.groups
    ]
    return plan, outcomes


def test_methods_share_one_interface():
    """Each recipe module's functions are its method's (one implementation each)."""
    assert names() == ("tilt", "scalar", "differential", "ramp")
    for name, module in zip(names(), (tilt, scalar, differential, ramp)):
        m = by_name(name)
        assert m is module.CALIBRATION_METHOD and m.passport_method == module.METHOD
        assert module.observe == m.observe and module.calibrate_observed == m.calibrate_observed
        assert module.calibrate == m.calibrate
    assert [by_name(n).passport_method for n in names()] == ["tilt_six_position", "scalar", "differential", "ramp"]
    assert [by_name(n).uses_base_passport for n in names()] == [False, False, True, False]
    with pytest.raises(CalibrationError, match="unknown method 'sweep' \\(tilt, scalar, differential, ramp\\)"):
        by_name("sweep")


@pytest.mark.slow  # fleet flows
def test_fleet_runs_every_method(inboxes, tmp_path):
    """tilt, scalar, then differential over the same registry: each a new version with its method, the scalar and
    tilt passports equal to their recipes' (same constants), a second plan skips what is done; the differential
    group starts from the current passport (the tilt version: the scalar one failed), also on the next night."""
    short, diff = inboxes
    reg = tmp_path / "reg"
    plan, _ = _fleet(short.parent, reg, "differential")  # nothing to start from yet
    assert not plan.groups and len(plan.failed) == 1
    assert "no normal-temperature passport of AU-0001" in plan.failed[0]["reason"]

    run = read_run(short)
    for k, (method, rec) in enumerate((("tilt", tilt), ("scalar", scalar)), start=1):
        plan, (outcome,) = _fleet(short.parent, reg, method)
        assert outcome.result["version"] == k and outcome.result["method"] == rec.METHOD
        doc = json.loads(Path(outcome.result["passport"]).read_text())
        again = rec.calibrate([run]).passport
        np.testing.assert_allclose(doc["coefficients"]["K"], again["coefficients"]["K"], rtol=0, atol=1e-15)
        np.testing.assert_allclose(doc["coefficients"]["U0"], again["coefficients"]["U0"], rtol=0, atol=1e-15)
        plan, outcomes = _fleet(short.parent, reg, method)
        assert not outcomes and [s["why"] for s in plan.skipped] == [ALREADY_PROCESSED]

    # the base is the unit's current passport among the non-differential versions: while nothing is approved the
    # newest that did not fail, v1 (tilt): v2 (scalar) failed its verification and is never the current passport
    assert [v.status for v in Registry(reg).versions("AU-0001")] == ["pass", "fail"]
    base, state = base_passport_of(reg, "AU-0001")
    assert base.version == 1 and not state.approved
    assert state.text() == (
        "AU-0001 v1 (status pass, not approved; the current passport: the newest version that did not fail, "
        "none is approved)"
    )
    Registry(reg).approve("AU-0001", 1, "A. Metrologist")
    plan, (outcome,) = _fleet(diff.parent, reg, "differential")
    assert plan.groups[0].base_passport.version == 1 and not outcome.failed
    doc = json.loads(Path(outcome.result["passport"]).read_text())
    assert outcome.result["version"] == 3 and doc["method"] == "differential"
    assert doc["base_passport"]["version"] == 1 and doc["thermal_model"]["order"] == 3
    base, state = base_passport_of(reg, "AU-0001")
    assert (
        base.version == 1
        and state.approved
        and state.text() == ("AU-0001 v1 (status pass, approved by A. Metrologist)")
    )
    plan, outcomes = _fleet(diff.parent, reg, "differential")  # the next night: nothing new
    assert not outcomes and [s["why"] for s in plan.skipped] == [ALREADY_PROCESSED]
    assert [v.version for v in Registry(reg).versions("AU-0001")] == [1, 2, 3]


def test_diagnose_fits_with_the_tilt_recipe(inboxes):
    """diagnose's passport fitted from the run is the tilt recipe's passport of that run (same constants, thermal
    model and verification)."""
    from pipeline.diagnose.diagnosis import fit_passport

    run = read_run(inboxes[0])
    settings = CalibrationSettings()
    fitted = fit_passport(run, segment_run(run, settings.segment), settings)
    ref = tilt.calibrate([run], settings).passport
    for key in ("coefficients", "thermal_model", "verification", "method", "status", "plateaus"):
        assert fitted.document[key] == ref[key], key


def test_cli_fleet_unknown_method_is_one_line(tmp_path):
    """``thermocal fleet --method`` takes the library's method names; another is a one-line usage error (exit 2)."""
    import subprocess
    import sys

    thermocal = str(Path(sys.executable).parent / "thermocal")
    proc = subprocess.run(
        [thermocal, "fleet", str(tmp_path), "--registry", str(tmp_path / "reg"), "--method", "sweep"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1 and "unknown method 'sweep'" in proc.stderr


@pytest.mark.slow  # fleet flows
def test_cli_fleet_method_tilt_then_differential(inboxes, tmp_path, monkeypatch, capsys):
    """``thermocal fleet --method`` through the Prefect flow: a tilt fleet, then a differential fleet starting
    from the tilt passports; each passport records its method, the fleet JSON lists the unit done."""
    from tests.conftest import run_main

    short, diff = inboxes
    reg = str(tmp_path / "reg")
    for inbox, method, version in ((short.parent, "tilt", 1), (diff.parent, "differential", 2)):
        code, out, err = run_main(
            monkeypatch, capsys, "fleet", str(inbox), "--registry", reg, "--method", method, "--no-figures", "--json"
        )
        assert code == 0, err
        summary = json.loads(out)
        assert [(d["unit"], d["version"]) for d in summary["done"]] == [("AU-0001", version)] and not summary["failed"]
        doc = json.loads(Path(summary["done"][0]["passport"]).read_text())
        assert doc["method"] == by_name(method).passport_method
    assert doc["base_passport"]["version"] == 1 and doc["base_passport"]["method"] == "tilt_six_position"


@pytest.mark.slow  # fleet flows
def test_cli_fleet_defaults_to_auto(inboxes, tmp_path, monkeypatch, capsys):
    """``thermocal fleet`` without ``--method`` picks each unit's method as ``calibrate`` does (``auto``, the same
    default): the short program by tilt, the differential program by the differential method (starting from the
    tilt passport); a second night skips what any method already made from the same runs."""
    from tests.conftest import run_main

    short, diff = inboxes
    reg = str(tmp_path / "reg")
    picked = {}
    for inbox, version in ((short.parent, 1), (diff.parent, 2)):
        code, out, err = run_main(monkeypatch, capsys, "fleet", str(inbox), "--registry", reg, "--no-figures", "--json")
        assert code == 0, err
        summary = json.loads(out)
        assert [(d["unit"], d["version"]) for d in summary["done"]] == [("AU-0001", version)] and not summary["failed"]
        picked[inbox.name] = json.loads(Path(summary["done"][0]["passport"]).read_text())["method"]
    assert picked == {"in1": "tilt_six_position", "in2": "differential"}
    code, out, _ = run_main(monkeypatch, capsys, "fleet", str(short.parent), "--registry", reg, "--json")
    summary = json.loads(out)
    assert code == 0 and not summary["done"] and [s["why"] for s in summary["skipped"]] == [ALREADY_PROCESSED]
