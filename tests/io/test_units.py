"""Runs with several units (log-format.md): both layouts written and read back, the mcap library's own reader on a
file simulate writes, and the per-unit input checks (a unit without samples, samples of an unlisted unit, a unit's
gaps, a dead channel: each one line, the other units read)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from mcap.reader import make_reader

from pipeline.errors import RunFormatError
from pipeline.io.runs import read_run, read_units, read_units_meta, write_run
from pipeline.run import Run, UnitRuns
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.units import simulate_units, unit_serials
from tests.conftest import run_main

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def three():
    """Three units through the short program at 2 Hz (the second with another nominal gain: an override)."""
    runs, truths = simulate_units(SimConfig(unit_serial="AU-0101", program="short", rate_hz=2.0), 3)
    r = runs.units["AU-0102"]
    runs = UnitRuns.of_units(
        [
            runs.units["AU-0101"],
            dataclasses.replace(r, meta=dataclasses.replace(r.meta, nominal_gain_v_per_g=-0.5)),
            runs.units["AU-0103"],
        ]
    )
    return runs, truths


def _edit(runs: UnitRuns, serial: str, **changes) -> UnitRuns:
    units = [dataclasses.replace(r, **changes) if s == serial else r for s, r in runs.units.items()]
    return UnitRuns.of_units(units)


def test_serials_count_up():
    assert unit_serials("AU-0101", 3) == ["AU-0101", "AU-0102", "AU-0103"]
    assert unit_serials("AU-0099", 2) == ["AU-0099", "AU-0100"]
    assert unit_serials("X", 2) == ["X-1", "X-2"]


@pytest.mark.parametrize("fmt", ["mcap", "parquet"])
def test_both_layouts_round_trip(three, tmp_path, fmt):
    runs, truths = three
    assert runs.meta_values["units"] == "AU-0101,AU-0102,AU-0103"
    assert runs.meta_values["AU-0102.nominal_gain_v_per_g"] == "-0.5"
    assert "unit_serial" not in runs.meta_values
    path = write_run(runs, tmp_path / ("r.mcap" if fmt == "mcap" else "r"), fmt)
    got = read_units(path)
    assert got.several and not got.failed and list(got.units) == ["AU-0101", "AU-0102", "AU-0103"]
    for serial, run in got.units.items():
        want = runs.units[serial]
        assert run.voltmeter.equals(want.voltmeter) and run.au_temperature.equals(want.au_temperature)
        assert run.meta == want.meta and run.meta.unit_serial == serial
        assert run.fixture is got.units["AU-0101"].fixture  # shared tables: decoded once, one object
        assert run.chamber is got.units["AU-0101"].chamber
    assert got.units["AU-0102"].meta.nominal_gain_v_per_g == -0.5
    assert got.units["AU-0103"].meta.nominal_gain_v_per_g == -0.55
    metas, several = read_units_meta(path)
    assert several and [m.unit_serial for m in metas] == ["AU-0101", "AU-0102", "AU-0103"]
    # each unit its own constants and thermosensor
    k = [np.array(truths[s]["unit"]["K_coef"]) for s in truths]
    assert len({a.tobytes() for a in k}) == 3
    temps = [got.units[s].au_temperature["temp_c"].to_numpy() for s in got.units]
    assert not np.array_equal(temps[0], temps[1])
    # one unit, only its streams decoded
    one = read_run(path, "AU-0103")
    assert one.meta.unit_serial == "AU-0103" and one.voltmeter.equals(runs.units["AU-0103"].voltmeter)
    with pytest.raises(RunFormatError, match=r"holds 3 units .*name one with --unit"):
        read_run(path)
    with pytest.raises(RunFormatError, match=r"no unit AU-0999 in this run \(units: AU-0101, AU-0102, AU-0103\)"):
        read_run(path, "AU-0999")


def test_serials_with_a_slash_or_a_space_round_trip(three, tmp_path):
    """Serials are the metadata's strings: one with a '/' (its MCAP topics /unit/IMU/A1/voltmeter) or a space reads
    back with its samples (the MCAP reader took 'IMU' for the serial: every unit 'listed but no samples')."""
    runs, _ = three
    names = ["IMU/A1", "SN 1002", "IMU/A/3"]
    renamed = UnitRuns.of_units(
        [
            dataclasses.replace(r, meta=dataclasses.replace(r.meta, unit_serial=n))
            for r, n in zip(runs.units.values(), names)
        ]
    )
    for fmt, name in (("mcap", "s.mcap"), ("parquet", "s")):
        got = read_units(write_run(renamed, tmp_path / name, fmt))
        assert not got.failed and list(got.units) == names
        assert all(got.units[n].voltmeter.equals(renamed.units[n].voltmeter) for n in names)


def test_simulate_units_mcap_read_by_the_mcap_library(tmp_path):
    """A file written by ``thermocal simulate --units`` read back by the mcap library's own reader: the topics of
    log-format.md, every unit's samples, the shared streams once, the metadata."""
    out = tmp_path / "four.mcap"
    proc = subprocess.run(
        [sys.executable, "-m", "flows.cli", "simulate", "--out", str(out), "--units", "4", "--unit", "AU-0201",
         "--program", "short", "--rate-hz", "2", "--json"],
        capture_output=True, text=True, cwd=REPO, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["units"] == ["AU-0201", "AU-0202", "AU-0203", "AU-0204"]
    truth = json.loads(Path(doc["truth"]).read_text())
    assert sorted(truth["units"]) == doc["units"]
    ours = read_units(out)
    samples: dict[str, int] = {}
    values: dict[str, list] = {}
    with open(out, "rb") as f:
        reader = make_reader(f)
        meta = [dict(m.metadata) for m in reader.iter_metadata() if m.name == "run"]
        for schema, channel, message in reader.iter_messages():
            block = json.loads(message.data)
            samples[channel.topic] = samples.get(channel.topic, 0) + len(np.atleast_1d(block["t_ns"]))
            if channel.topic.endswith("/voltmeter"):
                values.setdefault(channel.topic, []).extend(block["ux"])
            assert schema.name.startswith("thermocal.")
    assert meta[0]["units"] == "AU-0201,AU-0202,AU-0203,AU-0204" and "unit_serial" not in meta[0]
    expected = {"/chamber", "/fixture"} | {
        f"/unit/{s}/{t}" for s in doc["units"] for t in ("voltmeter", "au/temperature")
    }
    assert set(samples) == expected
    for s, run in ours.units.items():
        assert samples[f"/unit/{s}/voltmeter"] == run.voltmeter.height
        assert samples[f"/unit/{s}/au/temperature"] == run.au_temperature.height
        assert np.array_equal(np.array(values[f"/unit/{s}/voltmeter"]), run.voltmeter["ux"].to_numpy())
    assert samples["/fixture"] == ours.fixture.height and samples["/chamber"] == ours.chamber.height
    assert doc["samples"] == sum(r.voltmeter.height for r in ours.units.values())


@pytest.mark.parametrize("fmt", ["mcap", "parquet"])
def test_unit_checks_fail_alone(three, tmp_path, fmt):
    """A unit listed without samples, samples of an unlisted unit, a unit without a thermosensor, a dead channel: a
    one-line reason each naming the file and the unit's stream; the good unit is read, its gap warned about by name."""
    runs, _ = three
    good = runs.units["AU-0101"]
    v = good.voltmeter
    gappy = v.filter((pl.col("t_ns") < v["t_ns"][200]) | (pl.col("t_ns") > v["t_ns"][400]))
    dead = runs.units["AU-0102"].voltmeter.with_columns(uy=pl.lit(float("nan")))
    units = [
        dataclasses.replace(good, voltmeter=gappy),
        dataclasses.replace(runs.units["AU-0102"], voltmeter=dead),
        runs.units["AU-0103"],
        dataclasses.replace(
            runs.units["AU-0103"], meta=dataclasses.replace(runs.units["AU-0103"].meta, unit_serial="AU-0104")
        ),
    ]
    bad = UnitRuns.of_units(units)
    bad.meta_values["units"] = "AU-0101,AU-0102,AU-0104,AU-0105"  # AU-0103 unlisted, AU-0105 without samples
    path = write_run(bad, tmp_path / ("b.mcap" if fmt == "mcap" else "b"), fmt)
    got = read_units(path)
    assert list(got.units) == ["AU-0101", "AU-0104"]
    assert set(got.failed) == {"AU-0102", "AU-0103", "AU-0105"}
    for serial, line in got.failed.items():
        assert "\n" not in line and line.startswith(str(path)) and serial in line
    assert "dead channel: uy has no finite sample" in got.failed["AU-0102"]
    assert "which the metadata's 'units' does not list" in got.failed["AU-0103"]
    assert "t_ns=" in got.failed["AU-0103"]
    assert "listed in the metadata's 'units' but the file has no samples of it" in got.failed["AU-0105"]
    gap = [w for w in got.warnings if "gap" in w]
    assert len(gap) == 1 and "AU-0101" in gap[0]
    with pytest.raises(RunFormatError, match="dead channel"):
        read_run(path, "AU-0102")
    # no thermosensor
    nothermo = _edit(runs, "AU-0103", au_temperature=runs.units["AU-0103"].au_temperature.head(0))
    path2 = write_run(nothermo, tmp_path / ("c.mcap" if fmt == "mcap" else "c"), fmt)
    got2 = read_units(path2)
    assert list(got2.units) == ["AU-0101", "AU-0102"]
    assert "AU-0103" in got2.failed and ("no thermosensor samples" in got2.failed["AU-0103"]
                                         or "no samples of it" in got2.failed["AU-0103"])  # fmt: skip


@pytest.mark.parametrize("fmt", ["mcap", "parquet"])
@pytest.mark.parametrize(
    "channel, value, says",
    [
        ("uy", 0.0, "uy reads 0.0 V in every sample"),
        ("ux", float("nan"), "ux has no finite sample"),
        ("uz", 0.4375, "uz reads 0.4375 V in every sample"),
    ],
)
def test_a_dead_channel_is_refused_alike_in_a_single_unit_run(
    three, tmp_path, monkeypatch, capsys, fmt, channel, value, says
):
    """A single-unit run with a channel at one value (or NaN) throughout is refused as a unit of a run with several
    is, through the one check (checks.refuse_dead_channel): one line naming the file, the stream, the unit and the
    channel, exit 2 from inspect, calibrate and diagnose. Was: a single-unit run was read, and calibrate said "no
    temperature plateau with the six test positions ... (missing TP2, TP4)" (0 V) or "no named static position"
    (NaN), inspect printed its plateaus."""
    runs, _ = three
    unit = runs.units["AU-0102"]
    dead = unit.voltmeter.with_columns(pl.lit(value).alias(channel))
    single = write_run(dataclasses.replace(unit, voltmeter=dead), tmp_path / ("s.mcap" if fmt == "mcap" else "s"), fmt)
    several = write_run(_edit(runs, "AU-0102", voltmeter=dead), tmp_path / ("m.mcap" if fmt == "mcap" else "m"), fmt)
    multi_line = read_units(several).failed["AU-0102"]
    with pytest.raises(RunFormatError) as info:
        read_run(single)
    line = info.value.one_line()
    assert line == f"{single}: voltmeter: unit AU-0102 has a dead channel: {says}"
    assert multi_line.endswith(f": unit AU-0102 has a dead channel: {says}")  # the same reason, its stream labelled
    monkeypatch.setenv("THERMOCAL_CACHE_DIR", str(tmp_path / "cache"))
    commands = [("inspect", str(single)), ("diagnose", str(single))]
    if fmt == "mcap" and channel == "uy":
        commands.append(("calibrate", str(single), "--registry", str(tmp_path / "reg")))
    for args in commands:
        code, out, err = run_main(monkeypatch, capsys, *args)
        assert (code, err) == (2, f"thermocal: error: {line}\n"), args


def test_truncated_file_warns_every_unit(three, tmp_path):
    """A truncated file with several units keeps its complete chunks, and each unit's run says so (its passport's
    warnings come from its run's, as a single-unit run's do): a calibrate of such a file once said nothing."""
    runs, _ = three
    path = write_run(runs, tmp_path / "t.mcap", "mcap")
    whole = read_units(path)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 3 // 5])
    got = read_units(cut)
    (line,) = [w for w in got.warnings if "truncated" in w]
    assert list(got.units) == list(whole.units) and not got.failed
    for serial, run in got.units.items():
        assert 0 < run.voltmeter.height < whole.units[serial].voltmeter.height
        assert run.warnings == [line]


def test_single_unit_run_keeps_its_layout(tmp_path):
    runs, _ = simulate_units(SimConfig(program="short", rate_hz=2.0), 1)
    run = runs.units["AU-0001"]
    single = Run(run.meta, run.voltmeter, run.au_temperature, run.chamber, run.fixture)
    path = write_run(single, tmp_path / "one.mcap")
    with open(path, "rb") as f:
        reader = make_reader(f)
        topics = {c.topic for c in reader.get_summary().channels.values()}
    assert topics == {"/voltmeter", "/au/temperature", "/chamber", "/fixture"}
    got = read_units(path)
    assert not got.several and list(got.units) == ["AU-0001"]
    assert read_run(path).voltmeter.equals(run.voltmeter)


@pytest.mark.parametrize("fmt", ["mcap", "parquet"])
def test_a_single_unit_run_read_by_read_units_is_written_back_readable(tmp_path, fmt):
    """read_units on a single-unit run gives a UnitRuns (several False); write_run wrote it with a unit column or
    per-unit topics and no 'units' key, a file every reader refuses ('metadata: the file has streams of units AU-0001
    but its metadata has no 'units' key'). Now it is written as the single-unit run it was read from: read back, the
    same unit, metadata and streams."""
    runs, _ = simulate_units(SimConfig(program="short", rate_hz=2.0), 1)
    run = runs.units["AU-0001"]
    first = write_run(Run(run.meta, run.voltmeter, run.au_temperature, run.chamber, run.fixture), tmp_path / "a.mcap")
    read = read_units(first)
    assert not read.several
    again = read_units(write_run(read, tmp_path / f"b.{fmt}", fmt))
    assert not again.several and list(again.units) == ["AU-0001"]
    (back,) = again.units.values()
    assert back.meta == read.units["AU-0001"].meta
    for stream, df in read.units["AU-0001"].streams().items():
        assert back.streams()[stream].equals(df), stream
