"""Same data, same passport between ``calibrate`` and ``fleet`` on runs holding several units (issue 22;
contract.md, "Runs with several units"): the fleet calibrates the units whose only run is such a run from the run's
segmentation (the still times by the consensus of its units, pipeline.segment_units), as ``calibrate`` does, so each
unit's passport is the same (every field but ``created_utc`` and what signs it) whichever command made it, and a
unit whose signal disagrees with the others is named by both. Into one registry, the second command finds the
version the first made (no second version of a unit from the same data), in either order.

Variants: 2 to 4 units, MCAP and Parquet, a unit with a 5-min voltmeter dropout, a unit of the other polarity
(every channel's sign reversed), a unit turned on the table (x and y swapped), and a unit with a file of its own
beside the run (calibrated from both files as one recording, segmented alone, as ``calibrate`` does with both)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import polars as pl
import pytest

from pipeline.calibrate.settings import CalibrationSettings
from pipeline.io.runs import write_run
from pipeline.run import UnitRuns
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.units import simulate_units
from tests.conftest import run_piece

pytestmark = pytest.mark.slow  # the calibrate and fleet flows on thermocal's local Prefect server

#: the passport fields that differ between two writings of the same calibration: the time it was written, and
#: the hash and signature over the document that holds that time
WRITTEN = ("created_utc", "content_sha256", "signature")
#: (units, layout, what one unit of the run does)
VARIANTS = [
    (2, "mcap", "dropout"),
    (3, "parquet", "polarity"),
    (4, "mcap", "turned"),
    (4, "parquet", "none"),
    (3, "mcap", "own-file"),
]


def _inbox(tmp_path: Path, n: int, layout: str, odd: str) -> tuple[Path, list[str]]:
    """The inbox folder holding the run of ``n`` units (short program, 5 Hz: at 2 Hz, seed 7, each unit segmented
    alone happened to give the consensus's passports) with the second unit's oddity, and the paths ``calibrate`` is
    given, in the fleet's order."""
    runs = simulate_units(SimConfig(unit_serial="AU-0701", program="short", rate_hz=5.0, seed=3), n)[0]
    units = list(runs.units.values())
    u = units[1]
    v = u.voltmeter
    t0 = int(v["t_ns"][0])
    extra = []
    if odd == "dropout":  # 5 minutes without voltmeter samples at the cold plateau
        gap = (pl.col("t_ns") < t0 + 3000 * 10**9) | (pl.col("t_ns") >= t0 + 3300 * 10**9)
        units[1] = dataclasses.replace(u, voltmeter=v.filter(gap))
    elif odd == "polarity":  # wired with the other polarity: every output of the other sign
        units[1] = dataclasses.replace(u, voltmeter=v.with_columns(-pl.col("ux"), -pl.col("uy"), -pl.col("uz")))
    elif odd == "turned":  # mounted turned by 90 degrees about z
        units[1] = dataclasses.replace(u, voltmeter=v.with_columns(ux=-v["uy"], uy=v["ux"]))
    elif odd == "own-file":  # the run stops at 2 h; the second unit's recording goes on in a file of its own
        cut = t0 + 7200 * 10**9
        run_id = units[0].meta.run_id
        extra.append(run_piece(u, cut, 2**62, "AU-0702-rest"))
        units = [run_piece(r, 0, cut, run_id) for r in units]
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    name = "chamber.mcap" if layout == "mcap" else "chamber"
    paths = [str(write_run(UnitRuns.of_units(units), inbox / name, layout).resolve())]
    paths += [str(write_run(r, inbox / "AU-0702-rest.mcap", "mcap").resolve()) for r in extra]
    return inbox, sorted(paths)  # provenance.inputs lists the files in the order calibrate is given (fleet: sorted)


def _content(passport: str) -> dict:
    doc = json.loads(Path(passport).read_text())
    return {k: v for k, v in doc.items() if k not in WRITTEN}


@pytest.mark.parametrize(("n", "layout", "odd"), VARIANTS, ids=["-".join(map(str, v)) for v in VARIANTS])
def test_calibrate_and_fleet_make_the_same_passports(tmp_path, n, layout, odd):
    from flows.calibrate import run_calibrate
    from flows.fleet import run_fleet

    inbox, paths = _inbox(tmp_path, n, layout, odd)
    settings = CalibrationSettings()
    cal = run_calibrate(paths, str(tmp_path / "reg-c"), settings, method="auto")
    fleet = run_fleet(str(inbox), str(tmp_path / "reg-f"), settings, method="auto", figures=False, pool="thread")
    by_cal = {u["unit"]: u for u in cal["units"]}
    by_fleet = {d["unit"]: d for d in fleet["done"]}
    assert sorted(by_cal) == sorted(by_fleet) == [f"AU-07{k:02d}" for k in range(1, n + 1)]
    assert cal["failed"] == [] and fleet["failed"] == []
    for unit, c in by_cal.items():
        f = by_fleet[unit]
        a, b = _content(c["passport"]), _content(f["passport"])
        assert a["coefficients"] == b["coefficients"] and a["per_plateau"] == b["per_plateau"], unit
        assert a == b, unit
        assert (f["version"], f["status"]) == (c["version"], c["status"]) == (1, c["status"])
        assert f["warnings"] == c["warnings"], unit
    second = by_cal["AU-0702"]
    if odd == "turned":  # named by both commands, in the unit's warnings
        (line,) = [w for w in second["warnings"] if w.startswith("unit AU-0702: its signal names")]
        assert " where they hold TP" in line
    if odd == "polarity":  # named as the fixture log says, its gain of the other sign: plausibility fails
        assert second["status"] == "fail"
    if odd == "own-file":  # both files, one recording
        assert by_fleet["AU-0702"]["runs"] == sorted(paths)
        inputs = json.loads(Path(second["passport"]).read_text())["provenance"]["inputs"]
        assert sorted(i["path"] for i in inputs) == sorted(paths)

    # into one registry, the second command finds what the first made: fleet after calibrate ...
    again = run_fleet(str(inbox), str(tmp_path / "reg-c"), settings, method="auto", figures=False, pool="thread")
    assert again["done"] == [] and again["failed"] == []
    assert [s["run"] for s in again["skipped"]] == paths  # each file once, with the units it holds
    skipped = {(u, s["why"], s.get("version")) for s in again["skipped"] for u in s["units"]}
    assert skipped == {(u, "already processed", 1) for u in by_cal}
    # ... and calibrate after fleet
    back = run_calibrate(paths, str(tmp_path / "reg-f"), settings, method="auto")
    assert {u["unit"]: (u["version"], u["created"]) for u in back["units"]} == {u: (1, False) for u in by_fleet}
    for unit in by_fleet:
        assert not (tmp_path / "reg-f" / "units" / unit / "v0002.json").exists()


@pytest.mark.parametrize("layout", ["mcap", "parquet"])
def test_calibrate_unit_makes_the_passport_of_the_whole_run(tmp_path, layout):
    """``calibrate RUN --unit X`` segments the run by the consensus of all its units, as ``calibrate RUN`` and
    ``fleet`` do: X's passport does not depend on which other units were asked for. Was: only the named units were
    read and voted (one unit: segmented alone), AU-0704's constants 3.9e-9 relative off, every unit's verification
    rows other."""
    from flows.calibrate import run_calibrate

    _, paths = _inbox(tmp_path, 4, layout, "none")
    settings = CalibrationSettings()
    every = {u["unit"]: u for u in run_calibrate(paths, str(tmp_path / "reg"), settings, method="auto")["units"]}
    for k, units in enumerate((["AU-0704"], ["AU-0701", "AU-0704"])):
        some = run_calibrate(paths, str(tmp_path / f"reg{k}"), settings, method="auto", units=units)
        assert [u["unit"] for u in some["units"]] == units and some["failed"] == []
        for u in some["units"]:
            assert _content(u["passport"]) == _content(every[u["unit"]]["passport"]), u["unit"]
            assert u["warnings"] == every[u["unit"]]["warnings"]


#: (the cuts, between the cold TP3 hold's halves, in the -40 C soak, in the ramp after -10 C; the layout)
SPLITS = [(("hold",), "mcap"), (("soak", "ramp"), "parquet")]


@pytest.fixture(scope="module")
def split_units(tmp_path_factory):
    """3 units, short program at 10 Hz, seed 15 (at 2 Hz each unit segmented alone gives the consensus's passports),
    the cut times, and ``calibrate``'s passports of the whole file."""
    from flows.calibrate import run_calibrate

    d = tmp_path_factory.mktemp("fleet-split")
    runs, truths = simulate_units(SimConfig(program="short", rate_hz=10.0, seed=15), 3)
    holds = next(iter(truths.values()))["holds"]
    tp3 = next(h for h in holds if h["setpoint_c"] == -40.0 and h["position"] == "TP3")
    times = {
        "hold": (tp3["t_start_ns"] + tp3["t_end_ns"]) // 2,
        "soak": min(h["t_start_ns"] for h in holds if h["setpoint_c"] == -40.0) - 600 * 10**9,
        "ramp": max(h["t_end_ns"] for h in holds if h["setpoint_c"] == -10.0) + 600 * 10**9,
    }
    whole = write_run(runs, d / "whole.mcap", "mcap")
    ref = run_calibrate([str(whole)], str(d / "ref"), CalibrationSettings(), method="auto", dry_run=True)
    assert ref["failed"] == [] and len(ref["units"]) == 3
    return d, runs, times, {u["unit"]: u["passport_content"] for u in ref["units"]}


@pytest.mark.parametrize(("cuts", "layout"), SPLITS, ids=[f"{len(c) + 1}-{f}" for c, f in SPLITS])
def test_fleet_over_the_pieces_of_a_run_of_several_units_makes_calibrates_passports(split_units, cuts, layout):
    """The pieces of a run with several units (one run_id) in a folder: ``fleet`` calibrates the units whose runs
    are the same pieces together (each unit's pieces joined, the joined units segmented by the consensus), so its
    passports are ``calibrate PIECES``'s, which are the whole file's (every field but when and by what they were
    made). Was: the fleet segmented each unit's joined pieces alone: every unit's per_plateau, verification and
    coefficients other (AU-0001's K off by up to ~0.006 micro-V/g)."""
    from flows.calibrate import run_calibrate
    from flows.fleet import run_fleet

    d, runs, times, whole = split_units
    name = "-".join(cuts) + f"-{layout}"
    inbox = d / name
    edges = [0, *sorted(times[c] for c in cuts), 2**62]
    run_id = next(iter(runs.units.values())).meta.run_id
    paths = sorted(
        str(
            write_run(
                UnitRuns.of_units([run_piece(r, edges[k], edges[k + 1], run_id) for r in runs.units.values()]),
                inbox / (f"part-{k}.mcap" if layout == "mcap" else f"part-{k}"),
                layout,
            ).resolve()
        )
        for k in range(len(edges) - 1)
    )
    settings = CalibrationSettings()
    cal = run_calibrate(paths, str(d / f"reg-c-{name}"), settings, method="auto")
    fleet = run_fleet(str(inbox), str(d / f"reg-f-{name}"), settings, method="auto", figures=False, pool="thread")
    assert cal["failed"] == [] and fleet["failed"] == [] and fleet["skipped"] == []
    by_cal = {u["unit"]: u for u in cal["units"]}
    by_fleet = {u["unit"]: u for u in fleet["done"]}
    assert sorted(by_cal) == sorted(by_fleet) == sorted(whole)
    # when and by what a passport was made, and its version (the whole file's: a dry run, no registry)
    made = ("provenance", "created_utc", "content_sha256", "signature", "parent_sha256", "version")
    for unit, c in by_cal.items():
        f = by_fleet[unit]
        a, b = _content(c["passport"]), _content(f["passport"])
        assert b["per_plateau"] == a["per_plateau"] == whole[unit]["per_plateau"], unit
        assert b["coefficients"] == a["coefficients"] == whole[unit]["coefficients"], unit
        assert a == b, unit
        assert f["runs"] == paths and f["warnings"] == c["warnings"], unit
        differ = sorted(k for k in set(a) | set(whole[unit]) if k not in made and a.get(k) != whole[unit].get(k))
        assert differ == [], f"{unit}: {differ}"
