"""The fleet: discovery and metadata of both run layouts, grouping by unit, skipping what is done, isolating bad
runs; the Prefect flow on a local pool, on a real dask LocalCluster (two worker processes on loopback), and the
console script. Short simulated program at 2 Hz so that the whole file stays CI-sized."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate.fleet import ALREADY_PROCESSED, calibrate_group, discover_runs, plan_fleet, read_run_meta
from pipeline.calibrate.tilt import CalibrationSettings
from pipeline.errors import RunFormatError, ThermocalError
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import UnitTruth
from tests.conftest import run_piece

pytestmark = pytest.mark.slow  # fleet flows on Prefect and a dask cluster

RATE_HZ = 2.0
T0 = 20.0


def _sim(serial: str, unit_seed: int, seed: int = 1, **kw):
    return simulate(
        SimConfig(unit_serial=serial, unit_seed=unit_seed, seed=seed, program="short", rate_hz=RATE_HZ, **kw)
    )


def _corrupt_copy(src: Path, dst: Path) -> Path:
    """The run with 64 bytes inverted in the middle of the file (inside a compressed chunk; the metadata record
    at the start stays readable)."""
    data = bytearray(src.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 64] = bytes(b ^ 0xFF for b in data[mid : mid + 64])
    dst.write_bytes(bytes(data))
    return dst


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """An inbox of five units and some rubbish; plus VP-only runs of AU-0203 kept aside (they 'arrive later')."""
    inbox = tmp_path_factory.mktemp("inbox")
    later = tmp_path_factory.mktemp("later")
    truth = {}
    a = _sim("AU-0201", 201)
    truth["AU-0201"] = a.truth
    write_run(a.run, inbox / "ch1" / "AU-0201.mcap", "mcap")
    (inbox / "copies").mkdir()
    shutil.copy(inbox / "ch1" / "AU-0201.mcap", inbox / "copies" / "AU-0201-again.mcap")
    b = _sim("AU-0202", 202, with_fixture_log=False)
    truth["AU-0202"] = b.truth
    write_run(b.run, inbox / "ch2" / "AU-0202_run", "parquet")
    # AU-0203: TP-only recordings now; the VP-only recordings of -10 and +45 C arrive later (see test_calibrate)
    c = _sim("AU-0203", 203)
    truth["AU-0203"] = c.truth
    holds = c.truth["holds"]
    t_start = c.run.voltmeter["t_ns"][0]
    tp_m40_end = max(h["t_end_ns"] for h in holds if h["setpoint_c"] == -40.0)
    tp_70_start = min(h["t_start_ns"] for h in holds if h["setpoint_c"] == 70.0 and h["position"].startswith("TP"))
    tp_a = run_piece(c.run, t_start, tp_m40_end, "AU-0203-tp-a", closed="both")
    write_run(tp_a, inbox / "ch1" / "AU-0203-tp-a.mcap", "mcap")
    write_run(
        run_piece(c.run, tp_70_start - 1_200_000_000_000, 2**62, "AU-0203-tp-b", closed="both"),
        inbox / "ch1" / "AU-0203-tp-b.mcap",
        "mcap",
    )
    for k, sp in enumerate((-10.0, 45.0)):
        hs = [h for h in holds if h["position"].startswith("VP") and h["setpoint_c"] == sp]
        vp = run_piece(
            c.run,
            min(h["t_start_ns"] for h in hs) - 1_200_000_000_000,
            max(h["t_end_ns"] for h in hs),
            f"AU-0203-vp-{k}",
            closed="both",
        )
        write_run(vp, later / f"AU-0203-vp-{k}", "parquet")
    # AU-0204: a good run and a second run whose data is corrupt (its metadata is fine: it is grouped with AU-0204)
    d = _sim("AU-0204", 204)
    truth["AU-0204"] = d.truth
    write_run(d.run, inbox / "ch2" / "AU-0204.mcap", "mcap")
    d2 = _sim("AU-0204", 204, seed=2)
    write_run(d2.run, later / "AU-0204-s2.mcap", "mcap")
    _corrupt_copy(later / "AU-0204-s2.mcap", inbox / "ch2" / "AU-0204-s2-corrupt.mcap")
    # AU-0205: a Parquet run that lost its voltmeter file (the unit fails; the others go on)
    e = _sim("AU-0205", 205)
    write_run(e.run, inbox / "ch3" / "AU-0205_run", "parquet")
    (inbox / "ch3" / "AU-0205_run" / "voltmeter.parquet").unlink()
    # not runs at all, or not yet: junk with the suffix, a writer's hidden temp file, an unrelated file
    (inbox / "ch3" / "junk.mcap").write_bytes(b"this is not an MCAP file\n" * 8)
    (inbox / "ch3" / ".AU-0299.mcap.1234.tmp").write_bytes(b"\x89MCAP0\r\n")
    (inbox / "ch3" / "notes.txt").write_text("chamber 3 serviced\n")
    return {"inbox": inbox, "later": later, "truth": truth}


# ------------------------------------------------------------------------------------------------------ pure parts
def test_discover_and_metadata(fleet, tmp_path):
    inbox = fleet["inbox"]
    runs = [p.relative_to(inbox).as_posix() for p in discover_runs(inbox)]
    assert runs == [
        "ch1/AU-0201.mcap",
        "ch1/AU-0203-tp-a.mcap",
        "ch1/AU-0203-tp-b.mcap",
        "ch2/AU-0202_run",
        "ch2/AU-0204-s2-corrupt.mcap",
        "ch2/AU-0204.mcap",
        "ch3/AU-0205_run",
        "ch3/junk.mcap",
        "copies/AU-0201-again.mcap",
    ]
    assert read_run_meta(inbox / "ch1" / "AU-0201.mcap").unit_serial == "AU-0201"
    assert read_run_meta(inbox / "ch2" / "AU-0202_run").unit_serial == "AU-0202"
    m = read_run_meta(inbox / "ch1" / "AU-0203-tp-b.mcap")
    assert (m.run_id, m.normal_temp_c) == ("AU-0203-tp-b", T0)
    # metadata only: the corrupt chunk and the missing stream are not noticed here
    assert read_run_meta(inbox / "ch2" / "AU-0204-s2-corrupt.mcap").unit_serial == "AU-0204"
    assert read_run_meta(inbox / "ch3" / "AU-0205_run").unit_serial == "AU-0205"
    with pytest.raises(RunFormatError, match="not an MCAP file"):
        read_run_meta(inbox / "ch3" / "junk.mcap")
    # a logger that was not closed cleanly: no summary section, no index
    raw = write_run(read_run(inbox / "ch1" / "AU-0201.mcap"), tmp_path / "no-summary.mcap", "mcap", summary=False)
    assert read_run_meta(raw).run_id == "sim-AU-0201-s1"
    with pytest.raises(ThermocalError, match="not a directory"):
        discover_runs(inbox / "nowhere")


def test_calibrate_group_drops_a_bad_run(fleet, tmp_path):
    """The corrupt run is dropped with its one-line reason; the unit is calibrated from the other, accurately."""
    good = str(fleet["inbox"] / "ch2" / "AU-0204.mcap")
    bad = str(fleet["inbox"] / "ch2" / "AU-0204-s2-corrupt.mcap")
    out = calibrate_group("AU-0204", [good, bad], tmp_path / "reg", CalibrationSettings())
    assert [f["run"] for f in out.failed] == [bad]
    assert "corrupt chunk" in out.failed[0]["reason"] and bad in out.failed[0]["reason"]
    assert out.used_runs == [good] and out.result["version"] == 1 and out.result["status"] == "pass"
    passport = json.loads(Path(out.result["passport"]).read_text())
    assert [i["path"] for i in passport["provenance"]["inputs"]] == [good]
    # the constants at T0 against the simulator's truth: the 2 Hz short program averages ~100 samples of 5 uV
    # noise per position (~0.5 uV per mean) and fits five plateaus; 3e-6 is a few times what is reached (~1e-6)
    # and far below the temperature effects (~1e-4 V/g over the range)
    K_true, U0_true = UnitTruth.from_dict(fleet["truth"]["AU-0204"]["unit"]).constants_at(np.array([T0]))
    assert np.abs(np.array(passport["coefficients"]["K"]) - K_true[0]).max() < 3e-6
    assert np.abs(np.array(passport["coefficients"]["U0"]) - U0_true[0]).max() < 3e-6
    # nothing usable at all: every run fails, nothing is published
    none = calibrate_group("AU-0205", [str(fleet["inbox"] / "ch3" / "AU-0205_run")], tmp_path / "reg")
    assert none.result is None and "voltmeter.parquet" in none.failed[0]["reason"]
    assert not (tmp_path / "reg" / "units" / "AU-0205").exists()


# ---------------------------------------------------------------------------------------------------- the flow
def _by_unit(summary):
    return {d["unit"]: d for d in summary["done"]}


def _api_filter(kind: str, body: dict) -> list[dict]:
    """POST /api/<kind>/filter on the Prefect API the flows used (this session's local server)."""
    import httpx

    return httpx.post(f"{_local_api_url()}/{kind}/filter", json={"limit": 200, **body}, timeout=30).json()


def _local_api_url() -> str:
    """The URL of the Prefect API this test session's flows are recorded on (thermocal's local server for the
    session's PREFECT_HOME, started if need be; stopped at the end of the session by conftest)."""
    from flows.localserver import ensure_server

    return os.environ.get("PREFECT_API_URL") or ensure_server()["api_url"]


def _failed_reason(summary, name):
    hits = [f["reason"] for f in summary["failed"] if Path(f["run"]).name == name]
    assert len(hits) == 1, summary["failed"]
    return hits[0]


def test_fleet_flow_nightly_cycle(fleet, tmp_path):
    """First night (the unit tasks hand their calibration to the flow's process pool): every good unit
    calibrated, bad runs reported with their one-line reasons, one task run per unit, a table artifact.
    Second night (threads), after AU-0203's VP-only runs arrived: only AU-0203 is recalibrated (v2, verified at
    -10 and +45 C by them); units already processed are skipped by content hash."""
    from flows.fleet import ARTIFACT_KEY, run_fleet

    inbox, reg = fleet["inbox"], tmp_path / "reg"
    s1 = run_fleet(str(inbox), str(reg), pool="process", workers=2)
    assert s1["timing"]["runner"] == "ThreadPoolTaskRunner(4) + ProcessPoolExecutor(2)"
    done = _by_unit(s1)
    assert sorted(done) == ["AU-0201", "AU-0202", "AU-0203", "AU-0204"]
    assert all(d["version"] == 1 and d["created"] for d in done.values())
    # AU-0203's TP-only runs verify only at +20 C: not a pass until VP data exercise the thermal model (issue 14)
    assert {u: d["status"] for u, d in done.items()} == {
        "AU-0201": "pass",
        "AU-0202": "pass",
        "AU-0203": "unverified",
        "AU-0204": "pass",
    }
    assert [Path(r).name for r in done["AU-0203"]["runs"]] == ["AU-0203-tp-a.mcap", "AU-0203-tp-b.mcap"]
    assert [Path(r).name for r in done["AU-0204"]["runs"]] == ["AU-0204.mcap"]
    assert "corrupt chunk" in _failed_reason(s1, "AU-0204-s2-corrupt.mcap")
    assert "voltmeter.parquet is missing" in _failed_reason(s1, "AU-0205_run")
    assert "not an MCAP file" in _failed_reason(s1, "junk.mcap")
    assert len(s1["failed"]) == 3 and all("\n" not in f["reason"] for f in s1["failed"])
    assert [(Path(x["run"]).name, x["why"].split(" ")[0]) for x in s1["skipped"]] == [
        ("AU-0201-again.mcap", "duplicate")
    ]
    for unit, d in done.items():
        assert Path(d["passport"]).with_suffix(".png").stat().st_size > 10_000  # the VP figure, as calibrate
        K_true, U0_true = UnitTruth.from_dict(fleet["truth"][unit]["unit"]).constants_at(np.array([T0]))
        passport = json.loads(Path(d["passport"]).read_text())
        assert np.abs(np.array(passport["coefficients"]["K"]) - K_true[0]).max() < 3e-6, unit
    arts = _api_filter(
        "artifacts",
        {"artifacts": {"key": {"any_": [ARTIFACT_KEY]}}, "flow_runs": {"id": {"any_": [s1["flow_run_id"]]}}},
    )
    assert len(arts) == 1 and arts[0]["type"] == "table"
    table = json.loads(arts[0]["data"]) if isinstance(arts[0]["data"], str) else arts[0]["data"]
    assert len(table) == 4 + 3 + 1 and {r["outcome"] for r in table} == {"done", "failed", "skipped"}
    task_runs = _api_filter("task_runs", {"flow_runs": {"id": {"any_": [s1["flow_run_id"]]}}})
    assert sorted(tr["name"] for tr in task_runs) == [f"calibrate-AU-020{k}" for k in range(1, 6)]

    for vp in sorted(fleet["later"].glob("AU-0203-vp-*")):
        shutil.copytree(vp, inbox / "ch1" / vp.name)
    s2 = run_fleet(str(inbox), str(reg), pool="thread", workers=2)
    done2 = _by_unit(s2)
    assert done2["AU-0203"]["version"] == 2 and len(done2["AU-0203"]["runs"]) == 4
    assert done2["AU-0203"]["status"] == "pass"
    passport = json.loads(Path(done2["AU-0203"]["passport"]).read_text())
    # the unit's four files are one recording (issue 21): the VP rows at -10 C lie in the first VP-only file
    recording = "AU-0203-tp-a+AU-0203-vp-0+AU-0203-vp-1+AU-0203-tp-b"
    assert (
        {v["run_id"] for v in passport["verification"]} == {p["run_id"] for p in passport["per_plateau"]} == {recording}
    )
    vp0 = read_run(inbox / "ch1" / "AU-0203-vp-0").voltmeter["t_ns"]
    cold = [v for v in passport["verification"] if abs(v["temp_c"] + 10.0) < 3]
    assert len(cold) >= 6 and all(vp0.min() <= v["t_start_ns"] < vp0.max() for v in cold)
    assert passport["parent_sha256"] == done["AU-0203"]["passport_sha256"]
    skipped = {Path(x["run"]).name: x for x in s2["skipped"]}
    assert skipped["AU-0201.mcap"]["why"] == ALREADY_PROCESSED and skipped["AU-0201.mcap"]["version"] == 1
    assert skipped["AU-0202_run"]["why"] == ALREADY_PROCESSED
    # AU-0204 still has its corrupt run in the inbox: retried, the same passport is found (no new version)
    assert done2["AU-0204"]["version"] == 1 and not done2["AU-0204"]["created"]
    assert "corrupt chunk" in _failed_reason(s2, "AU-0204-s2-corrupt.mcap")
    # the plan of a third night: nothing left to do but the runs that keep failing
    plan = plan_fleet(inbox, reg, CalibrationSettings())
    assert sorted(g.unit for g in plan.groups) == ["AU-0204", "AU-0205"]
    # other settings are another identity: everything is to be done again
    assert len(plan_fleet(inbox, reg, CalibrationSettings(thermal_model="poly1")).groups) == 5


def test_planned_hashes_reused_until_the_run_changes(fleet, tmp_path):
    """The planning's content hashes travel with the groups: the calibration reuses them (no second read of the
    run) while a run's file signature is unchanged, and hashes again a run replaced after planning, so the
    passport names the bytes that were calibrated."""
    from pipeline.passport.provenance import RunDigest, file_signature, hash_run, input_digest

    inbox = tmp_path / "inbox"
    inbox.mkdir()
    shutil.copy(fleet["inbox"] / "ch1" / "AU-0203-tp-a.mcap", inbox / "AU-0203-a.mcap")
    shutil.copytree(fleet["inbox"] / "ch2" / "AU-0202_run", inbox / "AU-0202_run")
    plan = plan_fleet(inbox, tmp_path / "reg", CalibrationSettings())
    for g in plan.groups:
        assert [g.digests[r].sha256 for r in g.runs] == [input_digest(r) for r in g.runs]
    run, pq = str((inbox / "AU-0203-a.mcap").resolve()), str((inbox / "AU-0202_run").resolve())
    # reused while unchanged: a planted hash comes back as it is
    planted = RunDigest("0" * 64, file_signature(run))
    assert input_digest(run, planted) == "0" * 64
    # a Parquet run directory: any file rewritten changes its signature
    before = hash_run(pq)
    meta = Path(pq) / "run.json"
    os.utime(meta, ns=(meta.stat().st_atime_ns, meta.stat().st_mtime_ns + 1_000_000))
    assert file_signature(pq) != before.signature and input_digest(pq, before) == before.sha256
    # a run replaced after planning (a writer's rename onto it): hashed again when its passport is written
    group = next(g for g in plan.groups if g.unit == "AU-0203")
    replacement = inbox / ".incoming.mcap"
    shutil.copy(fleet["inbox"] / "ch1" / "AU-0203-tp-b.mcap", replacement)
    os.replace(replacement, run)
    assert input_digest(run, group.digests[run]) != group.digests[run].sha256
    out = calibrate_group(group.unit, group.runs, tmp_path / "reg", CalibrationSettings(), False, group.digests)
    passport = json.loads(Path(out.result["passport"]).read_text())
    assert passport["provenance"]["inputs"] == [{"path": run, "sha256": input_digest(run)}]
    assert {p["run_id"] for p in passport["per_plateau"]} == {"AU-0203-tp-b"}


def test_fleet_on_dask_localcluster(fleet, tmp_path):
    """The unit tasks run in the worker processes of a real dask LocalCluster on loopback, and report to the
    flow's Prefect API (the task runs are recorded with the flow run)."""
    distributed = pytest.importorskip("distributed")
    from flows.fleet import run_fleet

    inbox = tmp_path / "inbox"
    inbox.mkdir()
    for name in (
        "ch1/AU-0201.mcap",
        "ch1/AU-0203-tp-a.mcap",
        "ch1/AU-0203-tp-b.mcap",
        "ch2/AU-0204.mcap",
        "ch3/junk.mcap",
    ):
        shutil.copy(fleet["inbox"] / name, inbox / Path(name).name)
    shutil.copytree(fleet["inbox"] / "ch2" / "AU-0202_run", inbox / "AU-0202_run")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None, silence_logs=40
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        worker_pids = set(client.run(os.getpid).values())
        summary = run_fleet(str(inbox), str(tmp_path / "reg"), dask_address=cluster.scheduler_address, figures=False)
    assert len(worker_pids) == 2 and os.getpid() not in worker_pids
    done = _by_unit(summary)
    assert sorted(done) == ["AU-0201", "AU-0202", "AU-0203", "AU-0204"]
    assert all(Path(d["passport"]).exists() for d in done.values())
    assert {u: d["status"] for u, d in done.items()} == {
        "AU-0201": "pass",
        "AU-0202": "pass",
        "AU-0203": "unverified",
        "AU-0204": "pass",
    }
    assert not list((tmp_path / "reg").rglob("*.png"))  # figures=False
    assert [Path(f["run"]).name for f in summary["failed"]] == ["junk.mcap"]
    assert summary["timing"]["runner"].startswith("DaskTaskRunner(tcp://127.0.0.1:")
    # the same constants as the local pool computes
    local = calibrate_group("AU-0201", [str(inbox / "AU-0201.mcap")], tmp_path / "reg-local")
    a = json.loads(Path(local.result["passport"]).read_text())["coefficients"]
    b = json.loads(Path(done["AU-0201"]["passport"]).read_text())["coefficients"]
    assert a == b
    task_runs = _api_filter("task_runs", {"flow_runs": {"id": {"any_": [summary["flow_run_id"]]}}})
    assert sorted(tr["name"] for tr in task_runs) == [f"calibrate-{u}" for u in sorted(done)]
    assert {tr["state"]["type"] for tr in task_runs} == {"COMPLETED"}


def _read_all(fd: int) -> str:
    chunks = []
    while True:
        try:
            data = os.read(fd, 65536)
        except OSError:  # EIO: the terminal's other end is closed
            break
        if not data:
            break
        chunks.append(data)
    return b"".join(chunks).decode(errors="replace")


def test_cli_fleet_json_and_exit_status(fleet, tmp_path):
    """`thermocal fleet DIR --registry R --json`: one JSON object on stdout; a failed run gives exit 1 and one
    line on stderr (no progress when stderr is not a terminal), and so does a unit calibrated with status fail; a
    missing folder exits 2 before Prefect starts."""
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    shutil.copy(fleet["inbox"] / "ch1" / "AU-0201.mcap", inbox)
    shutil.copy(fleet["inbox"] / "ch3" / "junk.mcap", inbox)
    exe = str(Path(sys.executable).parent / "thermocal")
    cmd = [exe, "fleet", str(inbox), "--registry", str(tmp_path / "reg"), "--json", "--pool", "thread"]
    env = {**os.environ, "PREFECT_API_URL": _local_api_url()}  # this session's server: no start-up per command
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 1, out.stderr
    summary = json.loads(out.stdout)
    assert set(summary) >= {"done", "failed", "skipped"}
    assert [(d["unit"], d["version"], d["status"]) for d in summary["done"]] == [("AU-0201", 1, "pass")]
    assert summary["done"][0]["runs"] == [str((inbox / "AU-0201.mcap").resolve())]
    assert [Path(f["run"]).name for f in summary["failed"]] == ["junk.mcap"]
    # stderr is not a terminal: no progress bar, no per-unit lines; the one line names the bad run once
    (last,) = [line for line in out.stderr.strip().splitlines() if "created this station's signing key" not in line]
    assert last.startswith("thermocal: fleet: 1 run failed: ") and last.count("junk.mcap") == 1, last
    (inbox / "junk.mcap").unlink()
    # stderr a terminal: progress lines there, stdout still only the JSON
    master, slave = os.openpty()
    try:
        again = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=slave, text=True, timeout=300, env=env)
        os.close(slave)
        tty = _read_all(master)
    finally:
        os.close(master)
    assert again.returncode == 0, tty
    assert "thermocal: fleet: plan" in tty and "1 runs: 0 units to calibrate, 1 runs skipped" in tty, tty
    s2 = json.loads(again.stdout)
    assert s2["done"] == [] and [x["why"] for x in s2["skipped"]] == [ALREADY_PROCESSED]
    # no run failed, but a unit calibrated with status fail (limits no unit meets): exit 1, as calibrate's
    tight = [*cmd[:4], str(tmp_path / "reg-tight"), *cmd[5:], "--tol-normal-g", "1e-9", "--tol-range-g", "1e-9"]
    out = subprocess.run(tight, capture_output=True, text=True, timeout=300, env=env)
    s3 = json.loads(out.stdout)
    assert [(d["unit"], d["status"]) for d in s3["done"]] == [("AU-0201", "fail")] and s3["failed"] == []
    assert out.returncode == 1, out.stderr
    (last,) = [line for line in out.stderr.strip().splitlines() if "created this station's signing key" not in line]
    assert last.startswith("thermocal: fleet: 1 unit with status fail (AU-0201): "), last
    missing = subprocess.run(
        [exe, "fleet", str(tmp_path / "nowhere"), "--registry", str(tmp_path / "reg")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert missing.returncode == 2 and len(missing.stderr.strip().splitlines()) == 1
    assert "nowhere" in missing.stderr


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_fleet_on_dask_workers_elsewhere_with_a_worker_killed(fleet, tmp_path):
    """Issue 26 item 2: a real dask scheduler and two workers started as their own processes in other folders,
    with another key folder; the fleet given a RELATIVE registry from its own folder; one worker killed (SIGKILL)
    once the first passport is published. Every unit ends in the registry the user named (none under the workers'
    or the scheduler's folders), exactly once (v1 each, nothing duplicated), signed with the station's key (the
    workers' key folder stays empty: they never sign), and the registry verifies."""
    import signal
    import time

    pytest.importorskip("distributed")
    from pipeline.passport.registry import Registry
    from pipeline.passport.signing import station_key

    inbox = tmp_path / "inbox"
    inbox.mkdir()
    for name in ("ch1/AU-0201.mcap", "ch1/AU-0203-tp-a.mcap", "ch1/AU-0203-tp-b.mcap", "ch2/AU-0204.mcap"):
        shutil.copy(fleet["inbox"] / name, inbox / Path(name).name)
    shutil.copytree(fleet["inbox"] / "ch2" / "AU-0202_run", inbox / "AU-0202_run")
    for k in range(4):  # more units than workers, so that units are in flight when one worker dies
        write_run(_sim(f"AU-021{k}", 210 + k).run, inbox / f"AU-021{k}.mcap", "mcap")
    units = ["AU-0201", "AU-0202", "AU-0203", "AU-0204"] + [f"AU-021{k}" for k in range(4)]
    folders = {n: tmp_path / n for n in ("station", "scheduler", "worker-a", "worker-b", "worker-keys")}
    for f in folders.values():
        f.mkdir()
    dask = str(Path(sys.executable).parent / "dask")
    api = _local_api_url()
    env = {**os.environ, "PREFECT_API_URL": api}
    worker_env = {**env, "THERMOCAL_KEY_DIR": str(folders["worker-keys"])}
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [
        subprocess.Popen(
            [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            cwd=folders["scheduler"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    ]
    try:
        for name in ("worker-a", "worker-b"):
            procs.append(
                subprocess.Popen(
                    [dask, "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard", "--name", name],
                    cwd=folders[name],
                    env=worker_env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        import distributed

        with distributed.Client(address, timeout=120) as client:
            client.wait_for_workers(2, timeout=180)
        exe = str(Path(sys.executable).parent / "thermocal")
        cmd = [exe, "fleet", str(inbox), "--registry", "reg", "--dask-address", address, "--json", "--no-figures"]
        run = subprocess.Popen(
            cmd, cwd=folders["station"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        deadline = time.monotonic() + 600
        while not list((folders["station"] / "reg").rglob("v0001.json")) and run.poll() is None:
            assert time.monotonic() < deadline, "no passport published"
            time.sleep(0.2)
        published_before_kill = len(list((folders["station"] / "reg").rglob("v0001.json")))
        procs[1].send_signal(signal.SIGKILL)  # worker-a, mid-run
        out, err = run.communicate(timeout=900)
    finally:
        for p in procs:
            p.kill()
            p.wait(timeout=60)
    assert run.returncode == 0, err
    summary = json.loads(out)
    assert published_before_kill < len(units)  # the kill came while units were still being calibrated
    assert sorted(d["unit"] for d in summary["done"]) == sorted(units) and summary["failed"] == []
    assert all(d["version"] == 1 and d["created"] for d in summary["done"])
    reg = Registry(folders["station"] / "reg")
    assert reg.units() == sorted(units)
    for unit in units:
        assert [p.name for p in sorted(reg.unit_dir(unit).glob("v*.json"))] == ["v0001.json"]
        doc, state = reg.load_state(unit)
        assert state.verification.verified and state.verification.key_id == station_key().key_id
        assert Path(summary["done"][0]["passport"]).is_absolute()
    assert reg.verify().ok
    for name in ("scheduler", "worker-a", "worker-b"):
        assert not list(folders[name].rglob("*.json")), name  # nothing written where the workers run
    assert not any(folders["worker-keys"].iterdir())  # the workers never made or used a key
