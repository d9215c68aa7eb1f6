"""Unit grades (issue 21, item 5; physics.md "Unit grades"): the run's ``unit_grade`` or ``--grade`` sets the
verification limits; the passport, ``calibrate``'s output (text and --json) and the certificate state the grade and
the limits; a consumer unit that meets consumer limits passes.

The unit: a hand-turned consumer MEMS part (``--unit-type consumer``: 0.3 V/g, zero-g offsets of tens of mg, 0.5 mV
of noise per sample) with a second-order scale factor of 3-5 mg at 1 g, 24 poses of 5 s at 100 Hz with jittery
timestamps, calibrated by the scalar method: its compensated |dg| at the VP poses is about 0.9 mg, three times the
navigation limit and a tenth of the consumer one."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from pipeline.io.runs import write_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.program import handheld_program
from tests.conftest import run_main

K2_V_PER_G2 = (1.5e-3, -1.2e-3, 1.0e-3)


@pytest.fixture(scope="module")
def consumer_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("grades")
    res = simulate(
        SimConfig(
            unit_serial="MEMS-0007",
            unit_type="consumer",
            unit_seed=7,
            program=handheld_program(rounds=2, hold_s=5.0),
            rate_hz=100.0,
            noise_v=5e-4,
            jitter_s=2e-3,
            seed=7,
            effects=[("scale_nonlinearity", {"k2_v_per_g2": K2_V_PER_G2})],
        )
    )
    assert res.run.meta.unit_grade == "consumer" and res.run.meta.nominal_gain_v_per_g == pytest.approx(0.3)
    return write_run(res.run, d / "mems.mcap", "mcap")


def test_the_grade_table_is_physics_md():
    from pipeline.verify import DEFAULT_GRADE, GRADES

    assert DEFAULT_GRADE == "navigation"
    assert {g: (t.normal_g, t.operating_range_g) for g, t in GRADES.items()} == {
        "navigation": (3e-4, 1e-3),
        "tactical": (1e-3, 3e-3),
        "industrial": (3e-3, 1e-2),
        "consumer": (1e-2, 3e-2),
    }


def test_a_consumer_unit_meeting_consumer_limits_passes(consumer_run, tmp_path, monkeypatch, capsys):
    """Judged against its own grade (the run's unit_grade) the unit passes; the same data judged as navigation grade
    fail (exit 1), as they did before grades; both passports state the grade, its limits and where they came from."""
    reg = str(tmp_path / "reg")
    code, out, err = run_main(monkeypatch, capsys, "calibrate", str(consumer_run), "--registry", reg, "--json")
    assert code == 0, err
    res = json.loads(out)
    worst = max(abs(v["dg_method1_g"]) for v in res["verification"])
    assert res["status"] == "pass" and res["unit_grade"] == "consumer" and 3e-4 < worst < 1e-2
    assert res["tolerances"] == {
        "normal_g": 1e-2,
        "operating_range_g": 3e-2,
        "normal_band_c": 3.0,
        "grade": "consumer",
        "basis": "unit_grade of the run",
    }
    doc = json.loads(Path(res["passport"]).read_text())
    assert doc["unit_grade"] == "consumer" and doc["tolerances"] == res["tolerances"]
    assert {r["tolerance_g"] for r in doc["verification"]} == {1e-2} and all(r["passed"] for r in doc["verification"])

    code, out, err = run_main(
        monkeypatch, capsys, "calibrate", str(consumer_run), "--registry", reg, "--grade", "navigation"
    )
    assert code == 1
    assert "grade navigation: |dg| <= 0.0003 g within 3 C of T0, 0.001 g over the range (--grade)" in out
    assert re.search(r"\+20\.0 C .* 300 +FAIL", out)
    [line] = [x for x in err.splitlines() if x.startswith("thermocal:")]
    assert "status fail" in line


def test_the_command_line_and_the_certificate_state_grade_and_limits(consumer_run, tmp_path, monkeypatch, capsys):
    """Text output, ``passport show`` and the certificate: the grade line; ``--tol-range-g`` replaces one limit of
    the grade and says so; the settings (the passport's identity) record what was asked."""
    reg = str(tmp_path / "reg")
    code, out, err = run_main(
        monkeypatch,
        capsys,
        "calibrate",
        str(consumer_run),
        "--registry",
        reg,
        "--grade",
        "tactical",
        "--tol-range-g",
        "0.005",
    )
    assert code == 0, err
    line = "grade tactical: |dg| <= 0.001 g within 3 C of T0, 0.005 g over the range (--grade; --tol-range-g given)"
    assert line in out
    code, show, err = run_main(monkeypatch, capsys, "passport", "show", "MEMS-0007", "--registry", reg)
    assert code == 0 and line in show
    html_path = tmp_path / "cert.html"
    code, _, err = run_main(monkeypatch, capsys, "report", "MEMS-0007", "--registry", reg, "--out", str(html_path))
    assert code == 0, err
    page = html_path.read_text()
    assert "Unit grade tactical: |dg| &lt;= 0.001 g within 3 C of T0, 0.005 g over the range" in page
    assert "grade=tactical" in page and "tol_range_g=0.005" in page
    doc = json.loads(next((tmp_path / "reg" / "units" / "MEMS-0007").glob("v0001.json")).read_text())
    settings = doc["provenance"]["settings"]
    assert settings["grade"] == "tactical" and settings["tol_range_g"] == 0.005 and settings["tol_normal_g"] is None


def test_a_grade_that_is_none_is_one_line_exit_2(consumer_run, tmp_path, monkeypatch, capsys):
    code, out, err = run_main(
        monkeypatch, capsys, "calibrate", str(consumer_run), "--registry", str(tmp_path / "r"), "--grade", "military"
    )
    assert code == 2 and out == ""
    assert err.strip().splitlines() == [
        "thermocal: error: --grade: unknown unit grade 'military' (navigation, tactical, industrial, consumer)"
    ]
    bad = tmp_path / "bad"
    path = write_run(
        simulate(SimConfig(program="handheld", rate_hz=20.0, unit_grade="tactical")).run, bad / "run", "parquet"
    )
    meta = json.loads((path / "run.json").read_text())
    assert meta["unit_grade"] == "tactical"
    meta["unit_grade"] = "launcher"  # a grade that is none, as a lab's logger might write
    (path / "run.json").write_text(json.dumps(meta))
    code, out, err = run_main(monkeypatch, capsys, "inspect", str(path))
    assert code == 2 and out == ""
    [line] = err.strip().splitlines()
    assert str(path) in line and "metadata" in line and "'unit_grade' is not a unit grade: 'launcher'" in line
