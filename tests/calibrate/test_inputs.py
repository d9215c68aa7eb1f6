"""Which runs a calibration takes: same run_id never merged (truncated copy dropped, conflicting both dropped);
a folder name naming another unit warns."""

from __future__ import annotations

from dataclasses import replace

import pytest

from pipeline.calibrate.inputs import RunInput, folder_warning, is_prefix_of, resolve_run_ids
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.large import simulate_run


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A short 2 Hz run as MCAP, a truncated copy of it (cut mid-file), and another recording with its run_id."""
    d = tmp_path_factory.mktemp("inputs")
    run = simulate_run(SimConfig(program="short", rate_hz=2.0, seed=1)).run
    full = write_run(run, d / "full.mcap", "mcap", chunk_size=1 << 15)
    cut = d / "copy-truncated.mcap"
    data = full.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    other_run = simulate_run(SimConfig(program="short", rate_hz=2.0, seed=2)).run
    other = write_run(replace(other_run, meta=run.meta), d / "other.mcap", "mcap")
    return run.meta, full, cut, other


def test_truncated_copy_is_a_prefix(runs):
    _, full, cut, other = runs
    a, b, c = read_run(full), read_run(cut), read_run(other)
    assert 0.3 * a.voltmeter.height < b.voltmeter.height < a.voltmeter.height
    assert is_prefix_of(b, a) and is_prefix_of(a, a) and not is_prefix_of(a, b) and not is_prefix_of(c, a)


def test_truncated_copy_is_dropped_and_the_complete_file_used(runs):
    meta, full, cut, _ = runs
    items = [
        RunInput(str(cut), meta.unit_serial, meta.run_id),
        RunInput(str(full), meta.unit_serial, meta.run_id),
        RunInput("/elsewhere/vp.mcap", meta.unit_serial, "another-run"),
    ]
    kept, failed = resolve_run_ids(items, read_run)
    assert [k.path for k in kept] == [str(full), "/elsewhere/vp.mcap"]
    [f] = failed
    assert f["run"] == str(cut) and "truncated copy of " + str(full) in f["reason"] and meta.run_id in f["reason"]
    assert "\n" not in f["reason"]


def test_same_run_id_with_other_samples_uses_neither(runs):
    meta, full, _, other = runs
    items = [RunInput(str(full), meta.unit_serial, meta.run_id), RunInput(str(other), meta.unit_serial, meta.run_id)]
    kept, failed = resolve_run_ids(items, read_run)
    assert kept == [] and [f["run"] for f in failed] == [str(full), str(other)]
    assert str(other) in failed[0]["reason"] and str(full) in failed[1]["reason"]
    assert all("neither is used" in f["reason"] for f in failed)


def test_distinct_run_ids_are_not_read():
    items = [RunInput(f"/x/{k}.mcap", "AU-0001", f"run-{k}") for k in range(3)]
    assert resolve_run_ids(items, read=lambda p: pytest.fail("read")) == (items, [])


@pytest.mark.parametrize(
    "path, serial, warns",
    [
        ("/inbox/AU-0002/tp.mcap", "AU-0001", "says unit AU-0002 but its metadata says AU-0001"),
        ("/inbox/AU-0001/tp.mcap", "AU-0001", None),
        ("/inbox/2026-11-01-ch2-AU-0003.mcap", "AU-0001", "says unit AU-0003"),
        ("/inbox/AU-0002/run-AU-0001.mcap", "AU-0001", None),  # the file names its own unit
        ("/inbox/chamber-2/tp.mcap", "AU-0001", None),  # nothing shaped like a serial
    ],
)
def test_folder_name_naming_another_unit_warns(path, serial, warns):
    got = folder_warning(path, serial, "/inbox")
    assert (got is None) if warns is None else (warns in got and got.startswith(path))
