"""The files a run of several units was cut into (log-format.md, "Runs with several units": one run_id in several
files), as ``inspect``, ``diagnose``, ``calibrate`` and ``fleet`` see them: each unit's pieces one recording, the
units of the same files segmented together (the consensus of their still times), as the whole file is.

Real files: a 3-unit short program at 10 Hz (at 2 Hz a unit segmented alone finds the consensus's holds, at 10 Hz
it does not), written by the project's writers and cut with :func:`tests.conftest.run_piece`.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.io.runs import write_run
from pipeline.run import UnitRuns
from pipeline.simulate.chamber import SimConfig
from tests.conftest import run_main, run_piece

S = 10**9
#: the examples of the properties here (each writes the pieces and reads them back: a few seconds)
EXAMPLES = int(os.environ.get("THERMOCAL_HYPOTHESIS_EXAMPLES", "4"))


@pytest.fixture(scope="module")
def units3(tmp_path_factory):
    """Three units through the short program at 10 Hz (seed 15) in one run: the folder, the runs, the whole file
    and its run's (first, last) voltmeter ns."""
    from pipeline.simulate.units import simulate_units

    d = tmp_path_factory.mktemp("units3")
    runs, _ = simulate_units(SimConfig(program="short", rate_hz=10.0, seed=15), 3)
    whole = write_run(runs, d / "whole.mcap", "mcap")
    t = next(iter(runs.units.values())).voltmeter["t_ns"]
    return d, runs, whole, (int(t[0]), int(t[-1]))


def _missing_line(runs, piece, unit: str, edges_ns: list[int], k: int) -> str:
    """The warning naming ``unit`` missing from piece ``k`` (its file ``piece``) of ``runs`` cut at ``edges_ns``:
    the piece's time span is that of the other units' samples in it."""
    from pipeline.utc import utc_text

    t = next(iter(runs.units.values())).voltmeter["t_ns"].to_numpy()
    first, last = int(t[t >= edges_ns[k]][0]), int(t[t < edges_ns[k + 1]][-1])
    return (
        f"{piece}: unit {unit} is missing from this piece of run {runs.units[unit].meta.run_id!r} "
        f"({utc_text(first)} .. {utc_text(last)}), which holds the other units: its recording has no samples over "
        "that time"
    )


def _pieces(runs: UnitRuns, cuts_ns: list[int], folder: Path, fmt: str, drop: dict[int, str] | None = None):
    """The run cut at ``cuts_ns`` into files of the same run_id (``drop``: piece index -> a unit left out of it)."""
    run_id = next(iter(runs.units.values())).meta.run_id
    edges = [0, *sorted(cuts_ns), 2**62]
    out = []
    for k in range(len(edges) - 1):
        units = [
            run_piece(r, edges[k], edges[k + 1], run_id) for s, r in runs.units.items() if (drop or {}).get(k) != s
        ]
        name = f"part-{k}.mcap" if fmt == "mcap" else f"part-{k}"
        out.append(write_run(UnitRuns.of_units(units), folder / name, fmt))
    return out


def _inspect(monkeypatch, capsys, *paths) -> dict:
    code, out, err = run_main(monkeypatch, capsys, "inspect", *map(str, paths), "--json")
    assert code == 0, err
    return json.loads(out)


@pytest.fixture(scope="module")
def whole_inspected(units3):
    from pipeline.inspect import summarize_units
    from pipeline.io.runs import read_units

    return summarize_units(read_units(units3[2]))


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    cuts=st.lists(st.floats(0.02, 0.98), min_size=1, max_size=2, unique=True),
    fmt=st.sampled_from(["mcap", "parquet"]),
    reverse=st.booleans(),
)
def test_inspect_of_the_pieces_gives_each_unit_the_whole_files_poses(
    units3, whole_inspected, monkeypatch, capsys, cuts, fmt, reverse
):
    """``inspect PART...`` (any order) of a 3-unit run cut at 1-2 random times: every unit's poses, plateaus and
    static segments are the whole file's, each unit listing the files it was joined from. Was: exit 2, "the run
    holds 3 units (AU-0001, AU-0002, AU-0003): name one with --unit" (inspect read each file as one unit)."""
    d, runs, _, (t0, t1) = units3
    folder = Path(tempfile.mkdtemp(dir=d))
    paths = _pieces(runs, [t0 + int(c * (t1 - t0)) for c in cuts], folder, fmt)
    got = _inspect(monkeypatch, capsys, *(reversed(paths) if reverse else paths))
    assert got["failed"] == [] and got["warnings"] == whole_inspected["warnings"]
    assert got["source"] == " + ".join(str(p) for p in paths)
    assert [u["metadata"]["unit_serial"] for u in got["units"]] == ["AU-0001", "AU-0002", "AU-0003"]
    for unit, whole in zip(got["units"], whole_inspected["units"]):
        assert [f["source"] for f in unit["files"]] == [str(p) for p in paths]
        assert unit["recording"]["poses"] == whole["recording"]["poses"], unit["metadata"]["unit_serial"]
        assert len(unit["recording"]["poses"]) == 12
        for key in ("plateaus", "static_positions", "segmentation_warnings", "recording"):
            assert unit[key] == whole[key], (unit["metadata"]["unit_serial"], key)
        assert unit["streams"]["voltmeter"]["samples"] == whole["streams"]["voltmeter"]["samples"]


@pytest.mark.parametrize("unit", ["AU-0001", "AU-0003"])
def test_diagnose_of_a_unit_of_the_pieces_uses_the_consensus_of_the_units(units3, monkeypatch, capsys, unit, tmp_path):
    """``diagnose PART2 PART1 --unit S`` and ``diagnose WHOLE --unit S``: the same report, that of the unit's
    recording segmented with the other units of the run (``segment_units``, as ``calibrate`` segments it), not
    alone: the passport it fits from the run (and writes extended) is the tilt fit of the consensus's holds,
    ``calibrate``'s coefficients. Was: the unit's recording
    segmented alone, whole file or pieces (at 10 Hz AU-0001's fitted K and the residual RMS differ: rms_before_v
    3.87425e-7 V alone, 3.87393e-7 V with the consensus)."""
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.diagnose.diagnosis import fit_passport
    from pipeline.diagnose.signal import segment_settings_for
    from pipeline.io.runs import read_units
    from pipeline.segment_units import segment_units

    d, runs, whole, (t0, t1) = units3
    paths = _pieces(runs, [t0 + (t1 - t0) * 2 // 5], tmp_path, "mcap")
    reports = []
    for k, files in enumerate(([whole], paths[::-1])):
        out_dir = str(tmp_path / f"out-{k}")
        code, out, err = run_main(
            monkeypatch, capsys, "diagnose", *map(str, files), "--unit", unit, "--json", "--out", out_dir
        )
        assert code == 0, err
        reports.append(json.loads(out))
    got = read_units(whole)
    run = got.units[unit]
    segs, _ = segment_units(got.units)
    fitted = fit_passport(run, segs[unit], CalibrationSettings(segment=segment_settings_for(run)))
    a, b = reports
    assert a["unit"] == b["unit"] == unit and a["verdict"] == b["verdict"]
    for key in ("findings", "rms_before_v", "rms_after_v", "rms_noise_v", "vp", "blocks", "located"):
        assert a[key] == b[key], key
    assert a["extended_model"]["base"] == b["extended_model"]["base"]
    for rep in reports:  # the passport diagnose fitted from the run and wrote extended
        written = json.loads(Path(rep["extended_passport"]).read_text())["coefficients"]
        assert written["K"] == fitted.K.tolist() and written["U0"] == fitted.U0.tolist()


@pytest.fixture(scope="module")
def units3_2hz(tmp_path_factory):
    """Three units through the short program at 2 Hz (seed 15) in one run, and its (first, last) voltmeter ns."""
    from pipeline.simulate.units import simulate_units

    runs, _ = simulate_units(SimConfig(program="short", rate_hz=2.0, seed=15), 3)
    t = next(iter(runs.units.values())).voltmeter["t_ns"]
    return tmp_path_factory.mktemp("units3-2hz"), runs, (int(t[0]), int(t[-1]))


@pytest.mark.slow
@pytest.mark.parametrize(("cuts", "drop"), [((0.4,), {1: "AU-0003"}), ((0.3, 0.7), {1: "AU-0001"})])
def test_a_unit_missing_from_a_piece_of_its_run_is_named_by_calibrate_and_fleet(units3_2hz, cuts, drop):
    """The pieces of a 3-unit run (one run_id), one unit left out of one piece: ``calibrate PIECES`` and ``fleet``
    name it in that unit's warnings, first, one line naming the unit, the piece and the piece's time span; the
    other units' warnings name nothing. Was: the warnings were [] (the unit calibrated from the pieces it is in,
    nothing said about the hole)."""
    from flows.calibrate import run_calibrate
    from flows.fleet import run_fleet
    from pipeline.calibrate.settings import CalibrationSettings

    d, runs, (t0, t1) = units3_2hz
    name = "-".join(f"{c}" for c in cuts)
    inbox = d / name
    cut_ns = [t0 + int(c * (t1 - t0)) for c in cuts]
    paths = [str(p.resolve()) for p in _pieces(runs, cut_ns, inbox, "mcap", drop)]
    [(k, unit)] = drop.items()
    line = _missing_line(runs, paths[k], unit, [t0, *cut_ns, t1 + 1], k)
    settings = CalibrationSettings()
    cal = run_calibrate(paths, str(d / f"reg-c-{name}"), settings, method="auto", dry_run=True)
    fleet = run_fleet(str(inbox), str(d / f"reg-f-{name}"), settings, method="auto", figures=False, pool="thread")
    for got in ({u["unit"]: u for u in cal["units"]}, {u["unit"]: u for u in fleet["done"]}):
        assert sorted(got) == ["AU-0001", "AU-0002", "AU-0003"]
        assert got[unit]["warnings"][0] == line
        assert [w for w in got[unit]["warnings"] if "is missing from this piece" in w] == [line]
        for other in set(got) - {unit}:
            assert not any("is missing from this piece" in w for w in got[other]["warnings"]), other
    assert cal["failed"] == [] and fleet["failed"] == []


@pytest.mark.parametrize(
    ("cuts", "drop", "fmt"),
    [((0.4,), {1: "AU-0003"}, "mcap"), ((0.3, 0.7), {1: "AU-0001"}, "parquet"), ((0.5,), {0: "AU-0002"}, "mcap")],
)
def test_inspect_names_a_unit_missing_from_a_piece_as_calibrate_does(units3_2hz, monkeypatch, capsys, cuts, drop, fmt):
    """``inspect PIECES`` of a 3-unit run, one unit left out of one piece: that unit's warnings begin with the line
    ``calibrate`` and ``fleet`` give it (the piece, its time span), in any order of the files; the other units'
    name nothing; beside the whole file, no unit is said missing. Was: the unit's warnings were [] (its plateaus
    and poses fewer than the others', nothing said why)."""

    d, runs, (t0, t1) = units3_2hz
    folder = d / f"inspect-{'-'.join(map(str, cuts))}-{fmt}"
    cut_ns = [t0 + int(c * (t1 - t0)) for c in cuts]
    paths = [p.resolve() for p in _pieces(runs, cut_ns, folder, fmt, drop)]
    [(k, unit)] = drop.items()
    line = _missing_line(runs, paths[k], unit, [t0, *cut_ns, t1 + 1], k)
    for order in (paths, paths[::-1]):
        got = {u["metadata"]["unit_serial"]: u for u in _inspect(monkeypatch, capsys, *order)["units"]}
        assert sorted(got) == ["AU-0001", "AU-0002", "AU-0003"]
        assert got[unit]["warnings"][0] == line
        for serial, u in got.items():
            assert [w for w in u["warnings"] if "is missing from this piece" in w] == ([line] if serial == unit else [])
    whole = write_run(runs, folder / ("whole.mcap" if fmt == "mcap" else "whole"), fmt)
    beside = _inspect(monkeypatch, capsys, *paths, whole)["units"]
    assert not any("is missing from this piece" in w for u in beside for w in u["warnings"])


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["mcap", "parquet"])
def test_a_unit_missing_from_a_piece_is_not_said_missing_beside_the_whole_file(units3_2hz, fmt):
    """The pieces of a 3-unit run, AU-0003 left out of the second, beside the whole file they were cut from (one
    run_id): every unit is calibrated from the whole file, AU-0003 included, so no unit's warnings say it "has no
    samples over that time" (``calibrate`` and ``fleet`` alike); each unit's first warning is the same "part of"
    line as the others'. Was: AU-0003's first warning said it missing from the second piece, its recording without
    samples there, though the whole file's samples over that time were calibrated."""
    from flows.calibrate import run_calibrate
    from flows.fleet import run_fleet
    from pipeline.calibrate.settings import CalibrationSettings

    d, runs, (t0, t1) = units3_2hz
    inbox = d / f"whole-beside-{fmt}"
    paths = [str(p.resolve()) for p in _pieces(runs, [t0 + int(0.4 * (t1 - t0))], inbox, fmt, {1: "AU-0003"})]
    whole = str(write_run(runs, inbox / ("whole.mcap" if fmt == "mcap" else "whole"), fmt).resolve())
    settings = CalibrationSettings()
    cal = run_calibrate([*paths, whole], str(d / f"reg-cw-{fmt}"), settings, method="auto", dry_run=True)
    fleet = run_fleet(str(inbox), str(d / f"reg-fw-{fmt}"), settings, method="auto", figures=False, pool="thread")
    for got in ({u["unit"]: u for u in cal["units"]}, {u["unit"]: u for u in fleet["done"]}):
        assert sorted(got) == ["AU-0001", "AU-0002", "AU-0003"]
        for unit, done in got.items():
            assert [w for w in done["warnings"] if "is missing from this piece" in w] == [], unit
            assert done["status"] == "pass", unit
    assert cal["failed"] == [] and fleet["failed"] == []


@pytest.mark.slow
@pytest.mark.parametrize(("cuts", "drop"), [((0.4,), {1: "AU-0003"}), ((0.3, 0.7), {1: "AU-0001"})])
def test_a_unit_missing_from_a_piece_is_selectable_with_unit(units3_2hz, monkeypatch, capsys, cuts, drop):
    """``calibrate PIECES --unit S`` where S is missing from one piece (the other units in it): S calibrated from
    the pieces that hold it, the same passport and warnings (the "missing from this piece" line first) as
    ``calibrate PIECES`` gives it; a serial in no piece is still exit 2, one line naming it and the files. Was: exit
    2, "PIECE: --unit: no unit S in this run (units: ...)" (the serial checked file by file)."""
    from flows.calibrate import run_calibrate
    from pipeline.calibrate.settings import CalibrationSettings

    d, runs, (t0, t1) = units3_2hz
    name = "sel-" + "-".join(f"{c}" for c in cuts)
    paths = [str(p) for p in _pieces(runs, [t0 + int(c * (t1 - t0)) for c in cuts], d / name, "mcap", drop)]
    [(k, unit)] = drop.items()
    settings = CalibrationSettings()
    every = run_calibrate(paths, str(d / f"reg-all-{name}"), settings, method="auto", dry_run=True)
    one = run_calibrate(paths, str(d / f"reg-one-{name}"), settings, method="auto", dry_run=True, units=[unit])
    assert one["failed"] == [] and [u["unit"] for u in one["units"]] == [unit]
    (got,) = one["units"]
    (want,) = [u for u in every["units"] if u["unit"] == unit]
    assert "is missing from this piece" in got["warnings"][0] and paths[k] in got["warnings"][0]
    assert got["warnings"] == want["warnings"] and got["status"] == want["status"]
    made = ("created_utc", "content_sha256")
    assert {key: v for key, v in got["passport_content"].items() if key not in made} == {
        key: v for key, v in want["passport_content"].items() if key not in made
    }
    code, out, err = run_main(
        monkeypatch, capsys, "calibrate", *paths, "--unit", "AU-0999", "--registry", str(d / f"reg-x-{name}")
    )
    assert (code, out) == (2, "")
    assert err.strip().splitlines()[-1] == (
        f"thermocal: error: {' + '.join(paths)}: --unit: no unit AU-0999 in any of these runs "
        "(units: AU-0001, AU-0002, AU-0003)"
    )


def test_diagnose_of_a_unit_missing_from_a_piece_uses_the_pieces_holding_it(units3_2hz, monkeypatch, capsys):
    """``diagnose PART0 PART1 --unit AU-0003`` where AU-0003 is missing from PART1 (the other units in it): the
    report of ``diagnose PART0 --unit AU-0003`` (its recording is PART0's, segmented with PART0's units, as
    ``calibrate`` segments it); a serial in no piece: exit 2, one line naming it. Was: exit 2, "PART1: --unit: no
    unit AU-0003 in this run (units: AU-0001, AU-0002)"."""
    d, runs, (t0, t1) = units3_2hz
    paths = [str(p) for p in _pieces(runs, [t0 + (t1 - t0) * 2 // 5], d / "diag-missing", "mcap", {1: "AU-0003"})]
    reports = []
    for k, files in enumerate((paths, paths[:1])):
        code, out, err = run_main(
            monkeypatch, capsys, "diagnose", *files, "--unit", "AU-0003", "--json", "--out", str(d / f"diag-out-{k}")
        )
        assert code == 0, err
        reports.append(json.loads(out))
    a, b = reports
    assert a["unit"] == b["unit"] == "AU-0003" and a["verdict"] == b["verdict"]
    for key in ("findings", "rms_before_v", "rms_after_v", "rms_noise_v", "vp", "blocks", "located", "notes"):
        assert a[key] == b[key], key
    code, out, err = run_main(monkeypatch, capsys, "diagnose", *paths, "--unit", "AU-0999", "--json")
    assert (code, out) == (2, "")
    assert err.strip().splitlines()[-1] == (
        f"thermocal: error: {' + '.join(paths)}: --unit: no unit AU-0999 in any of these runs "
        "(units: AU-0001, AU-0002, AU-0003)"
    )


@pytest.mark.slow
def test_a_truncated_copy_of_a_run_of_several_units_is_skipped_once_with_its_units(units3_2hz, monkeypatch, capsys):
    """A 3-unit run and a truncated copy of it (its first 60 % of bytes, a USB stick's) in one inbox: every unit
    calibrated from the complete file; the copy is skipped once, not failed once per unit, with the units it
    holds, and the fleet exits 0. Was: ``"failed"`` listed the copy 3 times (once per unit) and the fleet exited
    1 though every unit got its passport."""
    d, runs, _ = units3_2hz
    inbox = d / "copy"
    whole = write_run(runs, inbox / "chamber.mcap", "mcap", chunk_size=1 << 15).resolve()
    copy = inbox / "usb" / "chamber.mcap"
    copy.parent.mkdir(parents=True)
    data = whole.read_bytes()
    copy.write_bytes(data[: int(len(data) * 0.6)])
    code, out, err = run_main(monkeypatch, capsys, "fleet", str(inbox), "--registry", str(d / "reg-copy"), "--json")
    got = json.loads(out)
    assert code == 0, err
    assert got["failed"] == []
    assert [(u["unit"], u["runs"]) for u in got["done"]] == [(s, [str(whole)]) for s in runs.units]
    assert got["skipped"] == [
        {"run": str(copy.resolve()), "why": f"truncated copy of {whole}", "units": ["AU-0001", "AU-0002", "AU-0003"]}
    ]


@pytest.mark.slow
def test_the_fleet_skips_a_file_of_several_units_once_with_its_units(units3_2hz, monkeypatch, capsys):
    """A 3-unit run, its 2 pieces beside it and a byte-identical copy of it: the fleet, run twice, lists each file it
    skips once, with the units it is skipped for (``"part of"``, ``"duplicate of"`` and, on the rerun, ``"already
    processed"`` with the version), as it lists a truncated copy. Was: one row per unit (the rerun: 12 rows for 4
    files, each with ``"unit"``)."""
    import shutil

    d, runs, (t0, t1) = units3_2hz
    inbox = d / "skip-once"
    whole = str(write_run(runs, inbox / "chamber.mcap", "mcap").resolve())
    pieces = [str(p.resolve()) for p in _pieces(runs, [t0 + int(0.4 * (t1 - t0))], inbox / "parts", "mcap")]
    copy = inbox / "usb" / "chamber.mcap"
    copy.parent.mkdir()
    shutil.copyfile(whole, copy)
    units = ["AU-0001", "AU-0002", "AU-0003"]
    beside = [{"run": p, "why": f"part of {whole}", "units": units} for p in pieces]
    beside += [{"run": str(copy.resolve()), "why": f"duplicate of {whole}", "units": units}]
    for k, first in enumerate((True, False)):
        code, out, err = run_main(monkeypatch, capsys, "fleet", str(inbox), "--registry", str(d / "reg-skip"), "--json")
        got = json.loads(out)
        assert code == 0, err
        assert got["failed"] == []
        assert [(u["unit"], u["runs"]) for u in got["done"]] == ([(s, [whole]) for s in units] if first else [])
        done = [] if first else [{"run": whole, "why": "already processed", "units": units, "version": 1}]
        assert got["skipped"] == sorted(beside + done, key=lambda s: s["run"]), k


def _turned_with_own_file(tmp_path):
    """A 3-unit run (5 Hz, to 2 h) whose AU-0702 is mounted turned (x and y swapped) and goes on in a file of its
    own: (the inbox, the own file, the run, the run's consensus line naming AU-0702 as ``inspect`` says it)."""
    import dataclasses

    from pipeline.inspect import summarize_units
    from pipeline.io.runs import read_units
    from pipeline.simulate.units import simulate_units

    runs = simulate_units(SimConfig(unit_serial="AU-0701", program="short", rate_hz=5.0, seed=3), 3)[0]
    units = list(runs.units.values())
    v = units[1].voltmeter
    units[1] = dataclasses.replace(units[1], voltmeter=v.with_columns(ux=-v["uy"], uy=v["ux"]))
    cut = int(v["t_ns"][0]) + 7200 * S
    inbox = tmp_path / "inbox"
    own = write_run(run_piece(units[1], cut, 2**62, "AU-0702-rest"), inbox / "AU-0702-rest.mcap", "mcap")
    run_id = units[0].meta.run_id
    chamber = write_run(UnitRuns.of_units([run_piece(r, 0, cut, run_id) for r in units]), inbox / "chamber.mcap")
    [line] = summarize_units(read_units(chamber))["warnings"]
    assert line.startswith("unit AU-0702: its signal names ")
    return inbox, own, chamber, line


@pytest.mark.slow
def test_a_unit_named_by_a_runs_consensus_but_calibrated_elsewhere_is_reported_by_calibrate(
    tmp_path, monkeypatch, capsys
):
    """The run and AU-0702's own file of :func:`_turned_with_own_file` given to ``calibrate`` (either order):
    the run's consensus line naming AU-0702 is in the top-level ``warnings`` of ``--json``, by run, as the fleet
    reports it, and a ``warning: RUN: LINE`` line of the text; in no unit's warnings; the same with
    ``--unit AU-0702``. Was: only in the flow run's log (no ``warnings`` key)."""
    inbox, own, chamber, line = _turned_with_own_file(tmp_path)
    for k, files in enumerate(([own, chamber], [chamber, own])):
        args = [
            "calibrate",
            *map(str, files),
            "--registry",
            str(tmp_path / f"reg-{k}"),
            "--dry-run",
            "--method",
            "auto",
        ]
        code, out, err = run_main(monkeypatch, capsys, *args, "--json")
        got = json.loads(out)
        assert code in (0, 1), err
        assert sorted(u["unit"] for u in got["units"]) == ["AU-0701", "AU-0702", "AU-0703"] and got["failed"] == []
        assert got["warnings"] == [{"run": str(chamber), "warning": line}]
        assert all(line not in u["warnings"] for u in got["units"])
    code, out, err = run_main(monkeypatch, capsys, *args)
    assert f"warning: {chamber}: {line}" in out.splitlines()
    code, out, err = run_main(monkeypatch, capsys, *args, "--unit", "AU-0702", "--json")
    got = json.loads(out)
    assert [u["unit"] for u in got["units"]] == ["AU-0702"] and got["warnings"] == [
        {"run": str(chamber), "warning": line}
    ]


@pytest.mark.slow
def test_a_unit_named_by_a_runs_consensus_but_calibrated_elsewhere_is_reported_by_the_fleet(tmp_path):
    """A 3-unit run (5 Hz, to 2 h) whose AU-0702 is mounted turned (x and y swapped) and goes on in a file of its
    own: AU-0702 is calibrated from both files (segmented alone), AU-0701/0703 from the run's consensus, which names
    AU-0702. The fleet reports that line once, by run, in its top-level ``warnings``, word for word as ``inspect``
    says it of the run. Was: dropped (``segment_units(...)[0]``): the fleet's warnings were []."""
    from flows.fleet import run_fleet

    inbox, own, chamber, line = _turned_with_own_file(tmp_path)
    got = run_fleet(str(inbox), str(tmp_path / "reg"), method="auto", figures=False, pool="thread")
    done = {d["unit"]: d for d in got["done"]}
    assert sorted(done) == ["AU-0701", "AU-0702", "AU-0703"] and got["failed"] == []
    assert done["AU-0702"]["runs"] == sorted([str(own.resolve()), str(chamber.resolve())])
    assert got["warnings"] == [{"run": str(chamber.resolve()), "warning": line}]
    assert all(line not in d["warnings"] for d in done.values())
