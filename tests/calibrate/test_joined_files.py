"""Files of one unit given together are one recording (pipeline.calibrate.inputs.join_runs), with two warnings:

- the AU temperature steps at the join of two files while the chamber does not (a thermosensor or logger swapped
  between the files: its offset would be taken as the unit's temperature, silently, the error hidden in a 200x
  larger U0 sigma): one line naming both files, the time of the join and the step. A clean run cut anywhere gives
  no line; an offset of 0.2..1 C in the later file always does.
- files of different run_ids (a re-run of the unit a day later) are calibrated as one recording: one line naming
  the run_ids and the time between them; the pieces of one run_id give none.

Real files (MCAP and Parquet) written and read back, joined as ``calibrate`` joins them.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import polars as pl
import pytest

from pipeline.calibrate.inputs import join_runs
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.utc import utc_text
from tests.conftest import run_piece

STEP_LINE = re.compile(
    r"^(?P<a>\S+) -> (?P<b>\S+): the AU temperature steps (?P<step>[+-]\d+\.\d\d) C at the join of the files "
    r"\((?P<when>[^)]*)\), beyond its noise \(\+-(?P<noise>\d\.\d{3}) C\), while the chamber does not "
    r"\(setpoint (?P<set>[+-]\d+\.\d\d) C, air (?P<air>[+-]\d+\.\d\d) C\): a thermosensor or logger changed "
    r"between the files\? The calibration takes the step as the unit's temperature$"
)


@pytest.fixture(scope="module")
def short_run():
    return simulate(SimConfig(program="short", rate_hz=1.0, seed=12)).run


def _cuts(run, n: int, seed: int) -> list[int]:
    """``n`` cut times (ns) drawn over the run's AU temperature readings (soaks, ramps, holds alike)."""
    t = run.au_temperature["t_ns"].to_numpy()
    rng = np.random.default_rng(seed)
    return [int(t[k]) for k in rng.integers(30, t.size - 30, size=n)]


def _pieces(run, cut_ns: int, offset_c: float, tmp_path, k: int):
    """The run cut at ``cut_ns`` into two files of its run_id (MCAP or Parquet by ``k``), the later file's
    thermosensor reading ``offset_c`` higher; read back, with their paths."""
    fmt = "mcap" if k % 2 else "parquet"
    ext = ".mcap" if fmt == "mcap" else ""
    a = run_piece(run, 0, cut_ns, run.meta.run_id)
    b = run_piece(run, cut_ns, 2**62, run.meta.run_id)
    b = dataclasses.replace(b, au_temperature=b.au_temperature.with_columns(pl.col("temp_c") + offset_c))
    paths = [write_run(p, tmp_path / f"piece{k}-{i}{ext}", fmt) for i, p in enumerate((a, b))]
    return [read_run(p) for p in paths], [str(p) for p in paths]


@pytest.mark.parametrize("k", range(12))
def test_a_clean_run_cut_anywhere_gives_no_step_line(short_run, tmp_path, k):
    cut = _cuts(short_run, 12, 1)[k]
    runs, _ = _pieces(short_run, cut, 0.0, tmp_path, k)
    joined = join_runs(runs[::-1])
    assert not [w for w in joined.warnings if "AU temperature steps" in w or "run_ids" in w]
    assert joined.au_temperature.equals(short_run.au_temperature)


@pytest.mark.parametrize("k", range(12))
def test_an_offset_in_the_later_file_is_one_line_naming_files_join_and_step(short_run, tmp_path, k):
    cut = _cuts(short_run, 12, 1)[k]
    rng = np.random.default_rng(100 + k)
    offset = float(rng.uniform(0.2, 1.0) * rng.choice([-1.0, 1.0]))
    runs, paths = _pieces(short_run, cut, offset, tmp_path, k)
    joined = join_runs(runs[::-1])
    lines = [w for w in joined.warnings if "AU temperature steps" in w]
    assert len(lines) == 1, joined.warnings
    m = STEP_LINE.match(lines[0])
    assert m, lines[0]
    assert (m["a"], m["b"]) == (paths[0], paths[1])
    t = short_run.au_temperature["t_ns"].to_numpy()
    before = int(t[t < cut][-1])
    assert m["when"] == utc_text((before + cut) // 2)
    assert float(m["step"]) == pytest.approx(offset, abs=0.04)
    assert float(m["noise"]) < 0.02
    assert abs(float(m["air"])) < 0.1
    # the chamber's setpoint runs on through the join (a ramp's too; a straight line misses a ramp's corner a little)
    assert abs(float(m["set"])) < 0.25
    assert not [w for w in joined.warnings if "run_ids" in w]  # one run_id: its pieces


def test_a_re_run_a_day_later_is_named_as_another_run_calibrated_as_one_recording(short_run, tmp_path):
    day_ns = 86400 * 10**9
    first = write_run(short_run, tmp_path / "day1.mcap", "mcap")
    later = dataclasses.replace(
        short_run,
        meta=dataclasses.replace(short_run.meta, run_id="AU-0001-rerun"),
        **{
            name: df.with_columns(pl.col("t_ns") + day_ns)
            for name in ("voltmeter", "au_temperature", "chamber", "fixture")
            if (df := getattr(short_run, name)) is not None
        },
    )
    second = write_run(later, tmp_path / "day2", "parquet")
    joined = join_runs([read_run(second), read_run(first)])
    t = short_run.voltmeter["t_ns"].to_numpy()
    gap_h = (int(t[0]) + day_ns - int(t[-1])) / 3.6e12
    lines = [w for w in joined.warnings if "run_ids" in w]
    assert lines == [
        f"the files given together are 2 runs of unit AU-0001 (different run_ids: {short_run.meta.run_id!r} "
        f"({first}), 'AU-0001-rerun' ({second})), calibrated as one recording: the time between them "
        f"({gap_h:.1f} h) is a gap within it, and the day-to-day repeatability of the unit is not judged"
    ]
    assert not [w for w in joined.warnings if "AU temperature steps" in w]  # a day apart: not judged
