"""Runs with several units from the command line (contract.md, "Runs with several units"): calibrate gives one
passport per unit, each unit's constants its own truth's within 3 micro-V, a dead unit and a unit without
thermosensor fail alone with their reasons (exit 2, the JSON printed), --unit selects, both layouts; fleet counts
every unit; inspect lists each unit's poses and methods; diagnose --unit."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.io.runs import write_run
from pipeline.run import UnitRuns
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.unit import UnitTruth
from pipeline.simulate.units import simulate_units

# the console script in a subprocess; calibrate and fleet start thermocal's local Prefect server
pytestmark = pytest.mark.slow

EXE = str(Path(sys.executable).parent / "thermocal")
GOOD = ("AU-0301", "AU-0304")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([EXE, *args], capture_output=True, text=True, env=dict(os.environ), timeout=900)


@pytest.fixture(scope="module")
def chamber(tmp_path_factory):
    """Four units through the short program at 2 Hz in one run, both layouts: AU-0302's uy channel dead (NaN),
    AU-0303 without thermosensor samples."""
    d = tmp_path_factory.mktemp("units")
    runs, truths = simulate_units(SimConfig(unit_serial="AU-0301", program="short", rate_hz=2.0), 4)
    u = runs.units
    units = [
        u["AU-0301"],
        dataclasses.replace(u["AU-0302"], voltmeter=u["AU-0302"].voltmeter.with_columns(uy=pl.lit(float("nan")))),
        dataclasses.replace(u["AU-0303"], au_temperature=u["AU-0303"].au_temperature.head(0)),
        u["AU-0304"],
    ]
    bad = UnitRuns.of_units(units)
    (d / "fleet").mkdir()
    mcap = write_run(bad, d / "fleet" / "chamber4.mcap", "mcap")
    parquet = write_run(bad, d / "chamber4", "parquet")
    return d, mcap, parquet, truths


def _check_constants(result: dict, truths: dict) -> None:
    """Every plateau's K and U0 within 3 micro-V (per g) of the unit's own true constants."""
    doc = json.loads(Path(result["passport"]).read_text())
    truth = UnitTruth.from_dict(truths[result["unit"]]["unit"])
    assert len(doc["per_plateau"]) >= 3
    for p in doc["per_plateau"]:
        k, u0 = truth.constants_at(np.array([p["temp_c"]]))
        np.testing.assert_allclose(p["K"], k[0], atol=3e-6)
        np.testing.assert_allclose(p["U0"], u0[0], atol=3e-6)


def test_calibrate_gives_one_passport_per_unit_and_bad_units_fail_alone(chamber):
    d, mcap, _, truths = chamber
    p = _cli("calibrate", str(mcap), "--registry", str(d / "reg"), "--json")
    assert p.returncode == 2, p.stderr  # the worst of the units': a bad input
    r = json.loads(p.stdout)
    assert [u["unit"] for u in r["units"]] == list(GOOD)
    assert all(u["status"] == "pass" and u["version"] == 1 for u in r["units"])
    failed = {f["unit"]: f["reason"] for f in r["failed"]}
    assert set(failed) == {"AU-0302", "AU-0303"}
    assert "dead channel: uy has no finite sample" in failed["AU-0302"] and str(mcap) in failed["AU-0302"]
    assert "/unit/AU-0303/" in failed["AU-0303"]
    ours = [line for line in p.stderr.splitlines() if line.startswith("thermocal: calibrate:")]
    assert len(ours) == 2 and all("\n" not in x for x in ours)
    for u in r["units"]:
        _check_constants(u, truths)
        for key, suffix in (("figure", ".png"), ("constants_figure", ".constants.png")):  # drawn in a second process
            assert u[key] == str(Path(u["passport"]).with_suffix(suffix))
            assert Path(u[key]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        inputs = json.loads(Path(u["passport"]).read_text())["provenance"]["inputs"]
        assert inputs == [
            {
                "path": str(mcap.resolve()),
                "sha256": inputs[0]["sha256"],
                "unit": u["unit"],
                "run_id": inputs[0]["run_id"],
            }
        ]
    assert (
        len({json.loads(Path(u["passport"]).read_text())["provenance"]["inputs"][0]["sha256"] for u in r["units"]}) == 1
    )
    # one task run a unit (its choose, observe, fit and write inside), beside the run's ingest and segment
    assert _task_runs_beside("calibrate-AU-0301") == {
        "ingest": "COMPLETED",
        "segment": "COMPLETED",
        "calibrate-AU-0301": "COMPLETED",
        "calibrate-AU-0304": "COMPLETED",
    }


def _task_runs_beside(name: str) -> dict[str, str]:
    """Name -> state of every task run of the latest flow run holding a task run named ``name`` (Prefect's suffix
    of a task run not named by its task left out), from the Prefect API the command recorded it on (this session's
    local server)."""
    import httpx

    from flows.localserver import ensure_server

    api = os.environ.get("PREFECT_API_URL") or ensure_server()["api_url"]

    def runs(body: dict) -> list[dict]:
        return httpx.post(f"{api}/task_runs/filter", json={"limit": 200, **body}, timeout=30).json()

    (latest,) = runs({"task_runs": {"name": {"any_": [name]}}, "sort": "EXPECTED_START_TIME_DESC", "limit": 1})
    flow_run = latest["flow_run_id"]
    named = {tr["name"]: tr["state"]["type"] for tr in runs({"flow_runs": {"id": {"any_": [flow_run]}}})}
    return {n if n.startswith("calibrate-") else n.rsplit("-", 1)[0]: state for n, state in named.items()}  # ingest-3df


def test_calibrate_unit_selects_on_the_parquet_layout(chamber):
    d, _, parquet, truths = chamber
    p = _cli("calibrate", str(parquet), "--unit", "AU-0304", "--registry", str(d / "reg-pq"), "--json")
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert [u["unit"] for u in r["units"]] == ["AU-0304"] and r["failed"] == []
    _check_constants(r["units"][0], truths)
    p = _cli("calibrate", str(parquet), "--unit", "AU-0999", "--registry", str(d / "reg-pq"), "--json")
    assert p.returncode == 2 and "no unit AU-0999 in this run" in p.stderr and p.stdout == ""


def test_fleet_counts_every_unit(chamber):
    d, mcap, _, _ = chamber
    single = simulate_units(SimConfig(unit_serial="AU-0400", program="short", rate_hz=2.0), 1)[0].units["AU-0400"]
    write_run(dataclasses.replace(single, source=""), d / "fleet" / "single.mcap")
    p = _cli("fleet", str(d / "fleet"), "--registry", str(d / "reg-fleet"), "--json")
    assert p.returncode == 1, p.stderr  # a fleet with failed units
    r = json.loads(p.stdout)
    assert sorted(u["unit"] for u in r["done"]) == ["AU-0301", "AU-0304", "AU-0400"]
    assert sorted(f["unit"] for f in r["failed"]) == ["AU-0302", "AU-0303"]
    assert all(f["run"] == str(mcap.resolve()) for f in r["failed"])
    again = json.loads(_cli("fleet", str(d / "fleet"), "--registry", str(d / "reg-fleet"), "--json").stdout)
    assert sorted((s["run"], s["units"]) for s in again["skipped"] if s["why"] == "already processed") == [
        (str(mcap.resolve()), ["AU-0301", "AU-0304"]),
        (str((d / "fleet" / "single.mcap").resolve()), ["AU-0400"]),
    ]


def test_inspect_lists_each_unit_and_diagnose_one(chamber):
    d, mcap, _, _ = chamber
    p = _cli("inspect", str(mcap), "--json")
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert [u["metadata"]["unit_serial"] for u in r["units"]] == list(GOOD)
    assert {f["unit"] for f in r["failed"]} == {"AU-0302", "AU-0303"}
    for u in r["units"]:
        assert u["recording"]["method_auto"] == "tilt"
        assert {m["method"] for m in u["recording"]["methods"]} >= {"tilt", "scalar"}
        assert len(u["plateaus"]) >= 3 and len(u["static_positions"]) > 20
    text = _cli("inspect", str(mcap)).stdout
    assert "unit AU-0301:" in text and "unit AU-0302: not usable" in text
    out = d / "diagnosed"
    p = _cli("diagnose", str(mcap), "--unit", "AU-0304", "--json", "--out", str(out))
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert r["verdict"] == "consistent"
    assert (out / "chamber4.AU-0304.diagnose.png").exists()


def _state(pid: int | str) -> tuple[str, bytes, bytes] | None:
    """A process's state letter, command line and environment; None when it is gone."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        return state, Path(f"/proc/{pid}/cmdline").read_bytes(), Path(f"/proc/{pid}/environ").read_bytes()
    except (OSError, IndexError):
        return None


def _alive(pid: int) -> bool:
    return (s := _state(pid)) is not None and s[0] != "Z"


def _figure_workers(mark: str) -> list[int]:
    """The live figure worker processes (pipeline.calibrate.figure_worker) whose environment holds ``mark``."""
    found = []
    for proc in Path("/proc").glob("[0-9]*"):
        s = _state(proc.name)
        if s and s[0] != "Z" and b"pipeline.calibrate.figure_worker" in s[1] and mark.encode() in s[2].split(b"\0"):
            found.append(int(proc.name))
    return found


def test_ctrl_c_leaves_no_figure_worker(chamber):
    """calibrate of a run with several units draws its figures in a second process (started by the command's job
    process, flows.jobserver); Ctrl-C while it lives ends it with the command."""
    import signal
    import time
    import uuid

    d, mcap, _, _ = chamber
    mark = f"THERMOCAL_TEST_MARK={uuid.uuid4()}"  # passed on to the job process and the worker it starts
    cli = subprocess.Popen(
        [EXE, "calibrate", str(mcap), "--registry", str(d / "reg-int"), "--json"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**os.environ, mark.split("=")[0]: mark.split("=")[1]},
    )
    try:
        workers: list[int] = []
        while not workers and cli.poll() is None:
            workers = _figure_workers(mark)
            time.sleep(0.01)
        assert workers, "no figure worker seen while calibrate ran"
        cli.send_signal(signal.SIGINT)
        _, err = cli.communicate(timeout=120)
        assert cli.returncode == 130 and "thermocal: aborted" in err.decode()
        deadline = time.monotonic() + 10  # an orphan would live on: give it the time to show
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [w for w in workers if _alive(w)]
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.wait()
