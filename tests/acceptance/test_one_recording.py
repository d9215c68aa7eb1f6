"""Several files of one unit are one recording (issue 21, item 3; contract.md "Runs with several units", log-format.md
"Other rates and gaps"): ``inspect RUN...`` and ``--method auto`` judge them together, and the files a recording was
split into give the passport of the whole file, in any order.

- the real CATS tag recording cut into three files, one per orientation: each file alone holds one orientation (no
  method fits it); the three together are the sweep of three orientations, calibrated by the differential method to
  the whole file's passport;
- a simulated short program cut at several points (in a soak, in a test position's hold, in a ramp), the files
  given in two orders: ``calibrate`` and ``fleet`` make the whole file's passport;
- files with other samples over one stretch of time: one line, exit 2, nothing written.
"""

from __future__ import annotations

import dataclasses
import json
import random
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate
from tests.conftest import data_path, run_main, run_piece

#: the CATS README's periods (UTC): one orientation each; the files are cut halfway between them
CATS_PERIODS = [("2021-09-20T09:00", "2021-09-21T10:33"), ("2021-09-21T10:40", "2021-09-22T11:55")]


def _ns(text: str) -> int:
    from pipeline.simulate.chamber import parse_utc_ns

    return parse_utc_ns(text + "Z")


@pytest.fixture(scope="module")
def cats_files(tmp_path_factory):
    whole = read_run(data_path("real", "cats_tag", "run"))
    d = tmp_path_factory.mktemp("cats3")
    (a0, a1), (b0, b1) = [(_ns(a), _ns(b)) for a, b in CATS_PERIODS]
    cuts = [0, (a1 + b0) // 2, (b1 + _ns("2021-09-22T12:14")) // 2, 2**62]
    paths = [
        write_run(run_piece(whole, cuts[k], cuts[k + 1], f"cats-part-{k + 1}"), d / f"cats-{'zxy'[k]}", "parquet")
        for k in range(3)
    ]
    return whole, paths


@pytest.mark.slow
def test_cats_in_three_files_is_judged_and_calibrated_as_the_whole(cats_files, tmp_path, monkeypatch, capsys):
    from pipeline.calibrate import differential

    whole, paths = cats_files
    alone = []
    for p in paths:
        code, out, err = run_main(monkeypatch, capsys, "inspect", str(p), "--json")
        assert code == 0, err
        alone.append(json.loads(out)["recording"]["method_auto"])
    assert alone == [None, None, None]  # one orientation each: no method fits a file alone
    given = [paths[2], paths[0], paths[1]]
    code, out, err = run_main(monkeypatch, capsys, "inspect", *map(str, given), "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert [f["run_id"] for f in summary["files"]] == ["cats-part-1", "cats-part-2", "cats-part-3"]
    rec = summary["recording"]
    assert rec["method_auto"] == "differential"
    held = sorted(p["vertical_axis"] for p in rec["poses"] if p["longest_hold_s"] > 20 * 3600)
    assert held == ["-x", "-y", "-z"]

    code, out, err = run_main(
        monkeypatch, capsys, "calibrate", *map(str, given), "--registry", str(tmp_path / "reg"), "--json", "--dry-run"
    )
    assert code == 0, err
    res = json.loads(out)
    doc = res["passport_content"]
    assert res["method"] == "differential" and res["method_auto"].startswith("differential")
    ref = differential.calibrate([whole]).passport
    sig = doc["uncertainty"]["coefficients"]
    K, K_ref = np.array(doc["coefficients"]["K"]), np.array(ref["coefficients"]["K"])
    U0, U0_ref = np.array(doc["coefficients"]["U0"]), np.array(ref["coefficients"]["U0"])
    # the same samples: the same passport (to rounding), far within its uncertainty
    assert np.abs(U0 - U0_ref).max() < 1e-3 * np.array(sig["U0"]).min()
    assert np.abs(K - K_ref).max() < 1e-9
    assert _numbers(doc["thermal_model"]) == pytest.approx(_numbers(ref["thermal_model"]), rel=1e-6, abs=1e-12)
    assert sorted(doc["undetermined"]) == sorted(ref["undetermined"])


@pytest.fixture(scope="module")
def split_short(tmp_path_factory):
    """The short program at 1 Hz, whole and cut into four files: in the first soak (before its positions), in
    the hold of a test position at -40 C, in the ramp after the VP positions at -10 C."""
    d = tmp_path_factory.mktemp("split")
    res = simulate(SimConfig(program="short", rate_hz=1.0, seed=12))
    holds = res.truth["holds"]
    tp_m40 = next(h for h in holds if h["setpoint_c"] == -40.0 and h["position"] == "TP3")
    soak = min(h["t_start_ns"] for h in holds if h["setpoint_c"] == -40.0) - 600 * 10**9
    ramp = max(h["t_end_ns"] for h in holds if h["setpoint_c"] == -10.0) + 600 * 10**9
    cuts = [0, soak, (tp_m40["t_start_ns"] + tp_m40["t_end_ns"]) // 2, ramp, 2**62]
    whole = write_run(res.run, d / "whole.mcap", "mcap")
    files = [
        write_run(run_piece(res.run, cuts[k], cuts[k + 1], f"short-part-{k}"), d / f"part-{k}.mcap", "mcap")
        for k in range(4)
    ]
    return whole, files


def _numbers(tree) -> list[float]:
    """Every number of a JSON tree, in a fixed order (dict keys sorted)."""
    if isinstance(tree, dict):
        return [x for k in sorted(tree) for x in _numbers(tree[k])]
    if isinstance(tree, list):
        return [x for v in tree for x in _numbers(v)]
    return [float(tree)] if isinstance(tree, (int, float)) and not isinstance(tree, bool) else []


def _same_passport(doc: dict, ref: dict) -> None:
    assert doc["status"] == ref["status"] and doc["method"] == ref["method"]
    assert np.array(doc["coefficients"]["K"]) == pytest.approx(np.array(ref["coefficients"]["K"]), abs=1e-12)
    assert np.array(doc["coefficients"]["U0"]) == pytest.approx(np.array(ref["coefficients"]["U0"]), abs=1e-12)
    assert _numbers(doc["thermal_model"]) == pytest.approx(_numbers(ref["thermal_model"]), abs=1e-12)
    assert [(r["position"], r["t_start_ns"]) for r in doc["verification"]] == [
        (r["position"], r["t_start_ns"]) for r in ref["verification"]
    ]
    dg = lambda d: [r["dg_method1_g"] for r in d["verification"]]  # noqa: E731
    assert dg(doc) == pytest.approx(dg(ref), abs=1e-12)
    sig, sig_ref = doc["uncertainty"]["coefficients"], ref["uncertainty"]["coefficients"]
    assert _numbers(sig) == pytest.approx(_numbers(sig_ref), rel=1e-6)


def test_a_run_split_into_files_gives_the_whole_files_passport(split_short, tmp_path):
    from flows.calibrate import run_calibrate
    from pipeline.calibrate.settings import CalibrationSettings

    whole, files = split_short
    ref = run_calibrate([str(whole)], str(tmp_path / "ref"), CalibrationSettings(), method="auto", dry_run=True)
    assert ref["method"] == "tilt_six_position" and ref["status"] == "pass"
    for seed in (1, 2):
        given = [str(f) for f in files]
        random.Random(seed).shuffle(given)
        out = run_calibrate(given, str(tmp_path / f"reg{seed}"), CalibrationSettings(), method="auto", dry_run=True)
        doc = out["passport_content"]
        _same_passport(doc, ref["passport_content"])
        assert {r["run_id"] for r in doc["verification"]} == {"+".join(f"short-part-{k}" for k in range(4))}


def test_the_fleet_reads_a_units_files_as_one_recording(split_short, tmp_path):
    from pipeline.calibrate.fleet import calibrate_group
    from pipeline.calibrate.settings import CalibrationSettings

    whole, files = split_short
    ref = calibrate_group("AU-0001", [str(whole)], tmp_path / "ref", CalibrationSettings(), figure=False, method="auto")
    out = calibrate_group(
        "AU-0001", [str(f) for f in files[::-1]], tmp_path / "reg", CalibrationSettings(), figure=False, method="auto"
    )
    assert out.failed == [] and out.result["status"] == ref.result["status"] == "pass"
    _same_passport(
        json.loads(Path(out.result["passport"]).read_text()), json.loads(Path(ref.result["passport"]).read_text())
    )


def test_files_with_other_samples_at_one_time_exit_2(split_short, tmp_path, monkeypatch, capsys):
    whole, files = split_short
    run = read_run(files[1])
    t = run.voltmeter["t_ns"].to_numpy()
    other = dataclasses.replace(
        run_piece(run, int(t[100]), int(t[-1]) + 1, "another-recording"),
        voltmeter=run_piece(run, int(t[100]), int(t[-1]) + 1, "x").voltmeter.with_columns(pl.col("ux") * 1.001),
    )
    clash = write_run(other, tmp_path / "clash.mcap", "mcap")
    reg = tmp_path / "reg"
    code, out, err = run_main(monkeypatch, capsys, "calibrate", str(files[1]), str(clash), "--registry", str(reg))
    assert code == 2 and out == "" and not reg.exists()
    [line] = err.strip().splitlines()
    assert f"{files[1]} and {clash} hold other samples over the same stretch of time" in line
    assert f"t_ns={t[100]}" in line


def test_diagnose_reads_a_units_files_as_one_recording(split_short, tmp_path, monkeypatch, capsys):
    """``thermocal diagnose RUN...``: the four files, in any order, are the whole file's recording: the same report
    (verdict, findings, residuals, the extended model but for its source) and the figure and extended passport
    named after the first file in time. Before: exit 2 'Got unexpected extra argument(s)'."""
    whole, files = split_short
    code, out, err = run_main(monkeypatch, capsys, "diagnose", str(whole), "--out", str(tmp_path / "w"), "--json")
    assert code == 0, err
    ref = json.loads(out)
    given = [str(f) for f in files]
    random.Random(3).shuffle(given)
    code, out, err = run_main(monkeypatch, capsys, "diagnose", *given, "--out", str(tmp_path / "p"), "--json")
    assert code == 0, err
    rep = json.loads(out)
    assert rep["figure"] == str(tmp_path / "p" / "part-0.diagnose.png") and Path(rep["figure"]).is_file()
    assert rep["extended_passport"] == str(tmp_path / "p" / "part-0.diagnose.passport.json")
    assert rep["extended_model"]["source"]["run"] == " + ".join(str(f) for f in files)
    assert rep["run_id"] == "+".join(f"short-part-{k}" for k in range(4))
    for r in (rep, ref):
        for key in ("figure", "extended_passport", "run_id"):
            r.pop(key)
        r["extended_model"].pop("source")
    assert rep == ref


@pytest.fixture(scope="module")
def short_units(tmp_path_factory):
    """Three units through the short program at 10 Hz in one run, the whole file's dry-run results by unit, and the
    program's times to cut at: in the -40 C soak (before its positions), in the hold of TP3 at -40 C, in the ramp
    after the VP positions at -10 C."""
    from flows.calibrate import run_calibrate
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.simulate.units import simulate_units

    d = tmp_path_factory.mktemp("units-split")
    runs, truths = simulate_units(SimConfig(program="short", rate_hz=10.0, seed=15), 3)
    holds = next(iter(truths.values()))["holds"]
    tp_m40 = next(h for h in holds if h["setpoint_c"] == -40.0 and h["position"] == "TP3")
    times = {
        "soak": min(h["t_start_ns"] for h in holds if h["setpoint_c"] == -40.0) - 600 * 10**9,
        "hold": (tp_m40["t_start_ns"] + tp_m40["t_end_ns"]) // 2,
        "ramp": max(h["t_end_ns"] for h in holds if h["setpoint_c"] == -10.0) + 600 * 10**9,
    }
    whole = write_run(runs, d / "whole.mcap", "mcap")
    ref = run_calibrate([str(whole)], str(d / "ref"), CalibrationSettings(), method="auto", dry_run=True)
    assert not ref["failed"] and len(ref["units"]) == 3
    return d, runs, times, {u["unit"]: u for u in ref["units"]}


#: the passport fields a do-nothing split may change: when and by what it was made, and the hashes of that
_MADE = ("provenance", "created_utc", "content_sha256", "signature", "parent_sha256")


@pytest.mark.slow
@pytest.mark.parametrize(
    "cuts, fmt, order, unit",
    [
        (("hold",), "mcap", (0, 1), None),
        (("soak",), "parquet", (1, 0), None),
        (("ramp",), "mcap", (1, 0), "AU-0002"),
        (("soak", "ramp"), "parquet", (2, 0, 1), None),
        (("hold", "ramp"), "mcap", (1, 2, 0), "AU-0003"),
    ],
)
def test_a_run_of_several_units_split_into_files_gives_the_whole_files_passports(short_units, cuts, fmt, order, unit):
    """The pieces of a run with several units (one run_id), in any order, either layout, every unit or one
    (``--unit``): each unit's passport is the whole file's, every field but when and by what it was made (the
    units' joined recordings are segmented together, by the consensus of their still times, as the whole file is;
    before, each unit's joined recording was segmented alone: AU-0001's per-plateau K at 20 C and 70 C differed by
    ~0.006 micro-V/g)."""
    from flows.calibrate import run_calibrate
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.run import UnitRuns

    d, runs, times, ref = short_units
    edges = [0, *sorted(times[c] for c in cuts), 2**62]
    run_id = next(iter(runs.units.values())).meta.run_id
    name = "-".join(cuts) + f"-{fmt}"
    files = [
        write_run(
            UnitRuns.of_units([run_piece(r, edges[k], edges[k + 1], run_id) for r in runs.units.values()]),
            d / name / (f"part-{k}.mcap" if fmt == "mcap" else f"part-{k}"),
            fmt,
        )
        for k in range(len(edges) - 1)
    ]
    given = [str(files[k]) for k in order]
    units = [unit] if unit else None
    out = run_calibrate(given, str(d / f"reg-{name}"), CalibrationSettings(), method="auto", dry_run=True, units=units)
    assert not out["failed"]
    assert sorted(u["unit"] for u in out["units"]) == (units or sorted(ref))
    for u in out["units"]:
        doc, whole = u["passport_content"], ref[u["unit"]]["passport_content"]
        assert doc["status"] == whole["status"] and doc["method"] == whole["method"] == "tilt_six_position"
        strip = lambda p: {k: v for k, v in p.items() if k not in _MADE}  # noqa: E731
        differ = sorted(k for k in set(doc) | set(whole) if k not in _MADE and doc.get(k) != whole.get(k))
        assert differ == [], f"{u['unit']}: {differ}"
        assert strip(doc) == strip(whole)
