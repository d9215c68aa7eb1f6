"""The fleet over time (pipeline/passport/trends.py, ``thermocal trends``): clean fleets list nothing, planted
drifts, a reversing drift and outliers of offset, gain and temperature coefficients are found with their sizes,
the thresholds are the stated ones; registries built from simulated passports (pipeline/simulate/history.py) and,
once, from real calibrations of simulated runs."""

from __future__ import annotations

import dataclasses
import json
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from scipy import stats

from pipeline.passport.registry import Registry
from pipeline.passport.trends import (
    SECONDS_PER_YEAR,
    Point,
    TrendSettings,
    UnitHistory,
    analyse,
    fleet_trends,
    grade_limit,
    utc_of,
    version_time,
)
from pipeline.simulate.history import FleetSpec, Plant, fleet_passports, truth_at, write_fleet
from pipeline.simulate.unit import random_unit

FINDINGS = ("drifting", "unsteady", "outliers")
#: planted drift of U0.x: +40 uV per 120 days
U0_RATE = 40e-6 * 365.25 / 120.0


def _histories(spec: FleetSpec) -> list[UnitHistory]:
    """The fleet's histories made in memory (the registry adds version numbers only; no signing needed here)."""
    by_unit: dict[str, list[Point]] = {}
    for serial, n, doc in fleet_passports(spec):
        by_unit.setdefault(serial, []).append(Point.of(n + 1, doc))
    return [UnitHistory(u, pts, pts[-1].version) for u, pts in by_unit.items()]


@pytest.mark.parametrize(("units", "versions", "seed"), [(10, 6, 1), (25, 4, 2), (50, 5, 3), (50, 2, 4)])
def test_clean_fleet_lists_nothing(units, versions, seed):
    report = analyse(_histories(FleetSpec(units=units, versions=versions, seed=seed))).report
    assert report["units"] == units and report["versions"] == units * versions
    assert [report[k] for k in FINDINGS] == [[], [], []]
    m = units * 12  # every unit-constant series is tested
    tests = report["tests"]
    assert tests["drift"]["series_tested"] == m
    assert tests["drift"]["z_threshold"] == pytest.approx(stats.norm.isf(0.01 / (2 * m)))
    assert tests["unsteady"]["series_tested"] == (m if versions >= 3 else 0)
    # outliers: 6 constants and 6 first-order coefficients per unit, one type of `units` units
    assert tests["outliers"]["comparisons"] == 12 * units
    t_q = stats.t.isf(0.01 / (2 * 12 * units), 0.37 * (units - 1))
    assert tests["outliers"]["z_threshold_by_fleet_size"] == {str(units): pytest.approx(max(8.0, t_q))}


def test_false_alarms_stay_within_the_family_wise_probability():
    """30 clean fleets of 12 units x 3 versions (other units than above): each kind of finding has a family-wise
    false-alarm probability of 1 %, so a fleet lists anything with probability at most 3 %; 4 or more fleets of 30
    would happen with probability 0.2 % (none does with these seeds)."""
    listed = 0
    for seed in range(30):
        report = analyse(_histories(FleetSpec(units=12, versions=3, seed=100 + seed, unit_seed0=7000))).report
        listed += any(report[k] for k in FINDINGS)
    assert listed <= 3


PLANTS = {
    "AU-0003": Plant(u0_rate_v_per_year=(U0_RATE, 0.0, 0.0)),
    "AU-0005": Plant(gain_rate_rel_per_year=(0.0, 2e-4, 0.0)),
    "AU-0011": Plant(u0_rate_v_per_year=(0.0, 0.0, 1e-4), reverse_after_days=240.0),
    "AU-0007": Plant(u0_offset_v=(0.0, 0.0, 0.06)),
    "AU-0013": Plant(gain_offset_rel=(0.1, 0.0, 0.0)),
    "AU-0015": Plant(alpha_offset_v_per_c=(0.0, 2e-3, 0.0)),
    "AU-0009": Plant(beta_offset_per_c=(5e-4, 0.0, 0.0)),
}
PLANTED_SPEC = FleetSpec(units=20, versions=4, interval_days=120.0, seed=7, plants=PLANTS)


@pytest.fixture(scope="module")
def planted(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("trends") / "registry"
    written = write_fleet(root, PLANTED_SPEC)
    return {"root": root, "written": written, "report": fleet_trends(root).report}


def test_planted_truths_are_found_and_nothing_else(planted):
    r = planted["report"]
    assert r["units"] == 20 and r["versions"] == 80 and r["not_verified"] == []
    assert {(e["unit"], e["constant"]) for e in r["drifting"]} == {("AU-0003", "U0.x"), ("AU-0005", "K.yy")}
    assert {(e["unit"], e["constant"]) for e in r["unsteady"]} == {("AU-0011", "U0.z")}
    assert {(e["unit"], e["constant"], np.sign(e["robust_z"])) for e in r["outliers"]} == {
        ("AU-0007", "U0.z", 1),
        ("AU-0013", "K.xx", -1),  # a gain of -0.55 V/g made 10 % larger in size
        ("AU-0015", "alpha.y[1]", 1),
        ("AU-0009", "beta.xx[1]", 1),
    }
    json.dumps(r, allow_nan=False)  # the report is plain JSON


def test_drift_rate_sigma_and_due_date(planted):
    entry = next(e for e in planted["report"]["drifting"] if e["constant"] == "U0.x")
    assert abs(entry["rate_per_year"] - U0_RATE) < 4 * entry["sigma_per_year"]
    assert entry["sigma_per_year"] < 3e-3 * U0_RATE  # 0.12 uV per passport over a year
    assert abs(entry["z"]) > entry["z_threshold"] == planted["report"]["tests"]["drift"]["z_threshold"]
    # the evidence: every version with its time, value and sigma; the line refitted from it gives the same rate
    ev = entry["versions"]
    assert [v["version"] for v in ev] == [1, 2, 3, 4]
    t = np.array([datetime.fromisoformat(v["time_utc"].replace("Z", "+00:00")).timestamp() for v in ev])
    y, s = np.array([v["value"] for v in ev]), np.array([v["sigma"] for v in ev])
    b = np.polyfit(t, y, 1, w=1 / s)[0] * SECONDS_PER_YEAR
    assert b == pytest.approx(entry["rate_per_year"], rel=1e-3)
    # the limit: the navigation grade's 3e-4 g at T0 times |Kxx| (V), reached from the current passport's time
    kxx = abs(random_unit(PLANTED_SPEC.unit_seed0 + 3).k_coef[0][0, 0])
    assert entry["grade"] == "navigation" and entry["limit_g"] == 3e-4
    assert entry["limit"] == pytest.approx(3e-4 * kxx, rel=1e-3)
    due = datetime.fromisoformat(ev[-1]["time_utc"].replace("Z", "+00:00")) + timedelta(
        days=entry["limit"] / entry["rate_per_year"] * 365.25
    )
    assert abs((datetime.fromisoformat(entry["due_utc"].replace("Z", "+00:00")) - due).total_seconds()) < 2
    assert entry["rate_scaled_per_year"] == pytest.approx(U0_RATE / kxx * 1e6, rel=0.01)  # micro-g per year
    gain = next(e for e in planted["report"]["drifting"] if e["constant"] == "K.yy")
    kyy = random_unit(PLANTED_SPEC.unit_seed0 + 5).k_coef[0][1, 1]
    assert abs(gain["rate_per_year"] - 2e-4 * kyy) < 4 * gain["sigma_per_year"]
    assert gain["rate_scaled_per_year"] == pytest.approx(2e-4 * 1e6 * np.sign(kyy), rel=0.02)  # ppm of gain


def test_reversing_drift_is_unsteady_with_its_recent_rate(planted):
    """+1e-4 V/year for 240 days, then back: the versions at 0, 120, 240, 360 days do not lie on a line (chi2);
    the report gives the line's rate (the mean over all versions) and the recent one (back down)."""
    e = planted["report"]["unsteady"][0]
    assert e["p_value"] < e["p_threshold"]
    assert e["recent_rate_per_year"] == pytest.approx(-1e-4, abs=4 * e["recent_sigma_per_year"])
    assert 0 < e["line_rate_per_year"] < 1e-4
    assert e["due_utc"] is not None


def test_outliers_state_their_fleet(planted):
    by = {e["unit"]: e for e in planted["report"]["outliers"]}
    off = by["AU-0007"]
    assert off["value"] - off["fleet_median"] == pytest.approx(0.06, abs=0.01)
    assert off["fleet_units"] == 20 and abs(off["robust_z"]) > off["z_threshold"] >= 8.0
    assert off["difference_scaled"] == pytest.approx((off["value"] - off["fleet_median"]) / 0.55 * 1e6, rel=0.02)
    assert "gain -0.55 V/g" in off["unit_type"]
    assert by["AU-0009"]["unit_type"].endswith("polynomial order 2")


def test_an_altered_version_is_not_used(planted, tmp_path, monkeypatch, capsys):
    import shutil

    root = tmp_path / "registry"
    shutil.copytree(planted["root"], root)
    path = Registry(root).version_path("AU-0003", 3)
    doc = json.loads(path.read_text())
    doc["coefficients"]["U0"][0] += 1e-3
    path.write_text(json.dumps(doc, sort_keys=True, indent=2) + "\n")
    r = fleet_trends(root).report
    bad = [e for e in r["not_verified"] if e["unit"] == "AU-0003"]
    assert len(bad) == 1 and 3 not in bad[0]["versions_used"] and bad[0]["problems"]
    assert r["versions"] < 80
    assert fleet_trends(root, workers=2).report == r  # two processes reading a share each: the same, to the bit
    from tests.conftest import run_main

    code, out, _ = run_main(monkeypatch, capsys, "trends", "--registry", str(root))
    assert code == 1 and "NOT VERIFIED AU-0003: " in out


def test_time_and_limit_of_a_passport():
    t_ns = int(datetime(2026, 3, 1, 12, 0, 0, 500000, tzinfo=UTC).timestamp() * 1e9)
    rows = [{"t_start_ns": t_ns + 3600 * 10**9}, {"t_start_ns": t_ns}]
    assert version_time({"verification": rows, "created_utc": "2026-04-01T00:00:00Z"}) == (t_ns / 1e9, "verification")
    assert version_time({"created_utc": "2026-04-01T00:00:00Z"})[1] == "created_utc"
    assert utc_of(datetime(2026, 3, 1, tzinfo=UTC).timestamp()) == "2026-03-01T00:00:00Z"
    assert grade_limit({"unit_grade": "consumer", "tolerances": {"normal_g": 1e-2}}) == (
        "consumer",
        1e-2,
        "the passport's",
    )
    assert grade_limit({"verification": [{"tolerance_g": 1e-3}, {"tolerance_g": 3e-4}]})[1] == 3e-4
    assert grade_limit({})[:2] == ("navigation", 3e-4)


def test_a_recalibration_of_the_same_recording_counts_once():
    spec = FleetSpec(units=1, versions=3, plants={"AU-0001": Plant(u0_rate_v_per_year=(U0_RATE, 0, 0))})
    docs = [doc for _, _, doc in fleet_passports(spec)]
    again = json.loads(json.dumps(docs[-1]))
    again["coefficients"]["U0"][0] += 1e-3  # a second fit of the last recording, far off: replaces it
    pts = [Point.of(v, d) for v, d in enumerate([*docs, again], start=1)]
    report = analyse([UnitHistory("AU-0001", pts, 4)], TrendSettings()).report
    (entry,) = report["drifting"]
    assert [v["version"] for v in entry["versions"]] == [1, 2, 4]


def test_truth_at_moves_what_is_planted():
    base = random_unit(11)
    plant = Plant(u0_rate_v_per_year=(1e-4, 0, 0), reverse_after_days=100.0, gain_offset_rel=(0, 0.1, 0))
    later = truth_at(base, plant, 150.0)
    assert later.u0_coef[0][0] - base.u0_coef[0][0] == pytest.approx(1e-4 * 50 / 365.25)
    assert later.k_coef[0][1, 1] == pytest.approx(1.1 * base.k_coef[0][1, 1])
    assert later.k_coef[0][0, 1] == base.k_coef[0][0, 1]


@pytest.mark.slow  # four short-program simulations and calibrations per unit
def test_real_calibrations_of_a_drifting_and_a_steady_unit(tmp_path):
    """Two units each calibrated four times 120 days apart from simulated short-program runs (1 Hz) by the tilt
    method and published as a calibration is: the unit whose x offset drifts by +40 uV per 120 days (added to its
    recorded voltages) is listed with that rate, the other lists nothing."""
    import polars as pl

    from pipeline.calibrate import tilt
    from pipeline.calibrate.publish import publish
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.io.runs import write_run
    from pipeline.simulate.chamber import SimConfig, simulate

    settings = CalibrationSettings()
    start = datetime(2026, 1, 5, tzinfo=UTC)
    for serial, drift_v in (("AU-0100", 40e-6), ("AU-0101", 0.0)):
        for n in range(4):
            utc = (start + timedelta(days=120 * n)).strftime("%Y-%m-%dT%H:%M:%SZ")
            cfg = SimConfig(unit_serial=serial, program="short", rate_hz=1.0, seed=60 + n, started_utc=utc)
            run = simulate(cfg).run
            run = dataclasses.replace(run, voltmeter=run.voltmeter.with_columns(pl.col("ux") + drift_v * n))
            path = write_run(run, tmp_path / f"{serial}-{n}.mcap", "mcap")
            result = tilt.calibrate_observed([tilt.observe(run)], settings)
            publish(tmp_path / "registry", result, input_paths=[str(path)], settings=settings, figure=False)
    r = fleet_trends(tmp_path / "registry").report
    assert r["versions"] == 8 and r["unsteady"] == [] and r["outliers"] == []
    (entry,) = r["drifting"]
    assert (entry["unit"], entry["constant"]) == ("AU-0100", "U0.x")
    assert abs(entry["rate_per_year"] - U0_RATE) < 4 * entry["sigma_per_year"] + 0.02 * U0_RATE


def test_command_json_text_and_exit_status(planted, monkeypatch, capsys, tmp_path):
    from tests.conftest import run_main

    code, out, err = run_main(monkeypatch, capsys, "trends", "--registry", str(planted["root"]), "--json")
    assert code == 0 and err == ""
    assert json.loads(out) == json.loads(json.dumps(planted["report"]))
    code, out, err = run_main(monkeypatch, capsys, "trends", "--registry", str(planted["root"]))
    assert code == 0 and err == ""
    assert "drifting (|rate|/sigma > " in out and "AU-0003 U0.x: " in out and "AU-0011 U0.z: chi2" in out
    assert "AU-0007 v4 U0.z: " in out
    code, out, err = run_main(monkeypatch, capsys, "trends", "--registry", str(tmp_path / "none"))
    assert (code, out) == (2, "") and err.count("\n") == 1 and "no registry here" in err


@pytest.mark.slow  # a headless browser
def test_page_renders_a_table_per_kind_and_a_figure_per_finding(planted, monkeypatch, capsys, tmp_path):
    """``trends --html``: the page of the planted fleet, rendered by headless Chromium: its 7 figures (2 drifting,
    1 unsteady, 4 outliers) decode (natural size > 0), its 3 tables hold one row per finding."""
    import re
    import subprocess
    import tempfile
    from pathlib import Path

    from pipeline.passport.report import chromium_args
    from tests.conftest import run_main
    from tests.passport.test_report import CHROMIUM, _probe

    if not Path(CHROMIUM).exists():
        pytest.fail("Chromium is not installed (apt-get install chromium): the page cannot be rendered")
    page = tmp_path / "trends.html"
    code, out, err = run_main(monkeypatch, capsys, "trends", "--registry", str(planted["root"]), "--html", str(page))
    assert code == 0 and err == "" and out.rstrip().endswith(f"page: {page}")
    text = page.read_text()
    assert text.count("<table>") == 3 and "<script" not in text
    rows = [t.count("<tr>") - 1 for t in text.split("<table>")[1:]]
    assert rows == [2, 1, 4]
    with tempfile.TemporaryDirectory() as profile:
        dom = subprocess.run(
            [CHROMIUM, *chromium_args(profile), "--virtual-time-budget=10000", "--dump-dom", _probe(page).as_uri()],
            capture_output=True,
            text=True,
            timeout=180,
        )
    assert dom.returncode == 0, dom.stderr[-2000:]
    m = re.search(r'data-images="([^"]*)"', dom.stdout)
    assert m, dom.stdout[:500]
    images = json.loads(m.group(1).replace("&quot;", '"'))
    assert len(images) == 7 and all(done and w > 300 and h > 150 for done, w, h in images), images
