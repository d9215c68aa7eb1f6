"""Run inputs a fleet inbox really holds (issue 15): a truncated copy of a run (same run_id) is never merged, two
recordings under one run_id are both refused, a folder naming another unit warns, a run truncated with no other
copy is calibrated from its complete chunks and the fleet says so; calibrate does the same."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from pipeline.io.runs import write_run
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.large import simulate_run
from tests.conftest import run_main

pytestmark = pytest.mark.slow  # an end-to-end proof on long or many recordings


def sim(serial: str, seed: int):
    return simulate_run(SimConfig(program="short", rate_hz=2.0, seed=seed, unit_serial=serial)).run


def truncated_copy(src: Path, dst: Path, fraction: float = 0.6) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


@pytest.fixture(scope="module")
def inbox(tmp_path_factory):
    root = tmp_path_factory.mktemp("inbox")
    a = write_run(sim("AU-0201", 1), root / "AU-0201" / "tp.mcap", "mcap", chunk_size=1 << 15)
    a_copy = truncated_copy(a, root / "usb-stick" / "AU-0201-tp.mcap")
    b_run = sim("AU-0202", 2)
    b1 = write_run(b_run, root / "AU-0202" / "tp.mcap", "mcap")
    b2 = write_run(replace(sim("AU-0202", 3), meta=b_run.meta), root / "AU-0202" / "tp-again.mcap", "mcap")
    c = write_run(sim("AU-0203", 4), root / "AU-0999" / "tp.mcap", "mcap")
    whole = write_run(sim("AU-0204", 5), root.parent / "AU-0204-whole.mcap", "mcap", chunk_size=1 << 15)
    d = truncated_copy(whole, root / "AU-0204" / "tp.mcap", 0.97)  # its last chunk cut: the only copy there is
    return root, {"a": a, "a_copy": a_copy, "b1": b1, "b2": b2, "c": c, "d": d}


def test_fleet_never_merges_one_run_id(inbox, tmp_path):
    from flows.cli.fleet import fleet_text
    from flows.fleet import run_fleet

    root, p = inbox
    summary = run_fleet(str(root), str(tmp_path / "reg"), pool="thread", workers=2)
    done = {d["unit"]: d for d in summary["done"]}
    failed = {Path(f["run"]): f["reason"] for f in summary["failed"]}
    skipped = {Path(s["run"]): s for s in summary["skipped"]}
    # the complete file is used, the truncated copy skipped (not failed) with why and its unit
    assert done["AU-0201"]["runs"] == [str(p["a"].resolve())]
    assert p["a_copy"].resolve() not in failed
    assert skipped[p["a_copy"].resolve()] == {
        "run": str(p["a_copy"].resolve()),
        "why": "truncated copy of " + str(p["a"].resolve()),
        "units": ["AU-0201"],
    }
    # two recordings under one run_id: neither is used, the unit is not calibrated
    assert "AU-0202" not in done
    assert "neither is used" in failed[p["b1"].resolve()] and str(p["b2"].resolve()) in failed[p["b1"].resolve()]
    assert "neither is used" in failed[p["b2"].resolve()]
    # filed by the metadata's serial, with a warning naming both
    assert done["AU-0203"]["runs"] == [str(p["c"].resolve())]
    [w] = summary["warnings"]
    assert w["run"] == str(p["c"].resolve()) and "says unit AU-0999 but its metadata says AU-0203" in w["warning"]
    assert all("\n" not in r for r in failed.values())
    # a run truncated with no other copy: calibrated from its complete chunks, the reader's warning in the unit's
    # entry and under its line in the text
    assert done["AU-0204"]["runs"] == [str(p["d"].resolve())]
    [cut] = [w for w in done["AU-0204"]["warnings"] if w.startswith("file is truncated at byte ")]
    assert f"      warning: {cut}" in fleet_text(summary).splitlines()
    assert not any("truncated at byte" in w for w in done["AU-0201"]["warnings"])  # the copy's is not its


def test_calibrate_drops_a_truncated_copy_and_refuses_two_recordings(inbox, tmp_path, monkeypatch, capsys):
    _, p = inbox
    code, out, err = run_main(
        monkeypatch, capsys, "calibrate", str(p["a_copy"]), str(p["a"]), "--registry", str(tmp_path / "reg"), "--json"
    )
    assert code == 0, err
    result = json.loads(out)
    assert [i["path"] for i in json.load(open(result["passport"]))["provenance"]["inputs"]] == [str(p["a"].resolve())]
    assert any("a truncated copy of" in w for w in result["warnings"])
    code, out, err = run_main(
        monkeypatch, capsys, "calibrate", str(p["b1"]), str(p["b2"]), "--registry", str(tmp_path / "reg")
    )
    assert code == 2 and out == ""
    [line] = [x for x in err.splitlines() if x.startswith("thermocal:")]
    assert "neither is used" in line and str(p["b2"]) in line


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A short program at 2 Hz recorded whole, and the same recording cut into pieces that keep its run_id."""
    from tests.conftest import run_piece

    run = sim("AU-0205", 6)
    d = tmp_path_factory.mktemp("pieces")
    whole = write_run(run, d / "whole.mcap", "mcap")
    t = run.voltmeter["t_ns"].to_numpy()
    return (
        run,
        whole,
        lambda a, b, name: write_run(
            run_piece(run, int(t[int(a * (len(t) - 1))]), int(t[int(b * (len(t) - 1))]) + 1, run.meta.run_id),
            d / name,
            "mcap",
        ),
    )


#: pieces as fractions of the recording: three, two, one from the middle, the start and the end
PIECES = [((0, 1 / 3), (1 / 3, 2 / 3), (2 / 3, 1)), ((0, 0.5), (0.5, 1)), ((0.3, 0.6),), ((0, 0.2), (0.8, 1))]


@pytest.mark.parametrize("pieces", PIECES, ids=["three", "two", "middle", "start-and-end"])
def test_the_pieces_of_a_recording_beside_its_whole_file_are_one_recording(
    recording, pieces, tmp_path, monkeypatch, capsys
):
    """A folder holding a recording's pieces (one run_id) beside the whole file: the same samples twice, one
    recording. The fleet uses the whole file, lists each piece as skipped (``part of`` the whole file: not a
    failure, exit 0) and so finds the version ``calibrate WHOLE`` made; ``calibrate`` given all the files makes the
    whole file's passport. Was: the first piece failed as 'a truncated copy' (exit 1) and the others were joined
    with the whole file into another identity (a second version of the same data)."""
    _, whole, cut = recording
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    (inbox / "whole.mcap").write_bytes(whole.read_bytes())
    parts = [cut(a, b, f"piece-{k}.mcap") for k, (a, b) in enumerate(pieces)]
    for p in parts:
        p.rename(inbox / p.name)
    parts = [str((inbox / p.name).resolve()) for p in parts]
    reg = str(tmp_path / "reg")
    code, out, err = run_main(monkeypatch, capsys, "calibrate", str(inbox / "whole.mcap"), "--registry", reg, "--json")
    assert code == 0, err
    made = json.loads(out)
    code, out, err = run_main(monkeypatch, capsys, "fleet", str(inbox), "--registry", reg, "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["done"] == [] and summary["failed"] == []
    whole_path = str((inbox / "whole.mcap").resolve())
    assert {(s["run"], s["why"]) for s in summary["skipped"]} == {(whole_path, "already processed")} | {
        (p, f"part of {whole_path}") for p in parts
    }
    # calibrate given the whole file and its pieces (any order): the whole file's passport, found
    code, out, err = run_main(monkeypatch, capsys, "calibrate", *parts[::-1], whole_path, "--registry", reg, "--json")
    assert code == 0, err
    again = json.loads(out)
    assert (again["version"], again["created"], again["passport_sha256"]) == (1, False, made["passport_sha256"])
    assert sum(w.startswith(tuple(parts)) and f": part of {whole_path} " in w for w in again["warnings"]) == len(parts)
