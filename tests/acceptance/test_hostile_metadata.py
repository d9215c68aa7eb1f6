"""Every metadata number plausible, every bad sample named, no internal error (issue 26 items 4 and 6): gravity of
-9.8, 1 or 980.665 m/s^2 (calibrated as pass, exported sign-flipped or scaled), T0 in kelvin, a -2^63 timestamp
(exit 3), one 1e308 temperature sample (a failure with an unrelated reason), a thermosensor with no finite sample
(exit 3), numpy's raw warnings on stderr."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.calibrate import tilt
from pipeline.errors import RunFormatError
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate

EXE = str(Path(sys.executable).parent / "thermocal")


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """A short program at 2 Hz (a clean pass) and where to write its variants."""
    return simulate(SimConfig(program="short", rate_hz=2.0, seed=11, unit_serial="AU-0801")).run, (
        tmp_path_factory.mktemp("variants")
    )


def _read_back(run, folder: Path, name: str):
    return read_run(write_run(run, folder / f"{name}.mcap", "mcap"))


@pytest.mark.parametrize(
    ("g", "hint"),
    [(980.665, "cm/s^2"), (-9.80665, "negative"), (1.0, "in g rather than m/s^2"), (9.5, "9.7..9.9")],
)
def test_gravity_outside_the_earths_fails_the_calibration(clean, g, hint):
    run, folder = clean
    read = _read_back(replace(run, meta=replace(run.meta, g_local_mps2=g)), folder, f"g{g}")
    found = [w for w in read.warnings if w.startswith("implausible: g_local_mps2")]
    assert len(found) == 1 and hint in found[0], read.warnings
    result = tilt.calibrate([read], tilt.CalibrationSettings())
    assert result.status == "fail" and found[0] in result.warnings
    assert result.passport["implausible"] == found


def test_gravity_with_a_reason_and_the_clean_run_pass(clean):
    run, folder = clean
    meta = replace(run.meta, g_local_mps2=9.5, extra={**run.meta.extra, "g_local_reason": "stand on a mountain"})
    read = _read_back(replace(run, meta=meta), folder, "g-reason")
    assert not [w for w in read.warnings if w.startswith("implausible")]
    assert tilt.calibrate([read], tilt.CalibrationSettings()).status == "pass"
    assert not [w for w in _read_back(run, folder, "clean").warnings if w.startswith("implausible")]


def test_t0_far_outside_the_recording_and_rates_in_other_units(clean):
    run, folder = clean
    read = _read_back(replace(run, meta=replace(run.meta, normal_temp_c=293.15)), folder, "t0-kelvin")
    assert any("normal_temp_c (T0) = 293.15 C lies outside" in w for w in read.warnings)
    assert tilt.calibrate([read], tilt.CalibrationSettings()).status == "fail"
    # within a chamber's reach, but far from every temperature the run holds: the calibration says so and fails
    far = _read_back(replace(run, meta=replace(run.meta, normal_temp_c=150.0)), folder, "t0-far")
    assert not [w for w in far.warnings if w.startswith("implausible")]
    result = tilt.calibrate([far], tilt.CalibrationSettings())
    assert result.status == "fail"
    assert any(
        "normal_temp_c (T0) = 150 C lies outside the AU temperatures the runs hold" in w for w in result.warnings
    )
    t0 = run.voltmeter["t_ns"][0]
    squeezed = {  # timestamps in milliseconds read as nanoseconds: hours of program in milliseconds
        name: df.with_columns(((pl.col("t_ns") - t0) // 1_000_000 + t0).alias("t_ns"))
        for name, df in run.streams().items()
    }
    fast = replace(run, **squeezed)
    assert any(
        "voltmeter is sampled at" in w and "not in nanoseconds" in w for w in _read_back(fast, folder, "us").warnings
    )


def _parquet_variant(src: Path, folder: Path, stream: str, change, tag: str = "") -> Path:
    import shutil

    dst = folder / f"{src.name}-{stream}{tag}"
    shutil.copytree(src, dst)
    path = dst / f"{stream}.parquet"
    path.chmod(0o644)
    change(pl.read_parquet(path)).write_parquet(path)
    return dst


@pytest.mark.parametrize("stream", ["voltmeter", "au_temperature", "chamber"])
def test_a_minus_2_to_the_63_timestamp_is_one_line(clean, stream):
    run, folder = clean
    src = write_run(run, folder / "pq", "parquet") if not (folder / "pq").exists() else folder / "pq"
    bad = _parquet_variant(
        src,
        folder,
        stream,
        lambda df: df.with_columns(
            pl.when(pl.int_range(df.height) == 5).then(-(2**63)).otherwise(pl.col("t_ns")).alias("t_ns")
        ),
    )
    p = subprocess.run([EXE, "inspect", str(bad)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and p.stdout == "", p.stderr
    assert p.stderr.count("\n") == 1 and f"{stream}: row 5: t_ns=-9223372036854775808" in p.stderr


def test_a_1e308_sample_is_named_and_treated_as_missing(clean):
    run, folder = clean
    temp = run.au_temperature.with_columns(
        pl.when(pl.int_range(run.au_temperature.height) == 40).then(1e308).otherwise(pl.col("temp_c")).alias("temp_c")
    )
    read = _read_back(replace(run, au_temperature=temp), folder, "t1e308")
    t40 = run.au_temperature["t_ns"][40]
    [named] = [w for w in read.warnings if "outside what it can be" in w]
    assert f"t_ns={t40} (row 40): 1e+308" in named and named.startswith("au_temperature: 1 sample(s) of temp_c")
    assert np.isnan(read.au_temperature["temp_c"][40])
    assert tilt.calibrate([read], tilt.CalibrationSettings()).status == "pass"


def test_no_finite_temperature_and_numpy_warnings_are_one_line(clean):
    """A thermosensor with no finite sample made inspect an internal error; a voltmeter stuck at 0 V printed numpy's
    RuntimeWarning with its source line on stderr."""
    run, folder = clean
    src = folder / "pq" if (folder / "pq").exists() else write_run(run, folder / "pq", "parquet")
    nan = _parquet_variant(
        src, folder, "au_temperature", lambda df: df.with_columns(pl.lit(float("nan")).alias("temp_c")), "-nan"
    )
    p = subprocess.run([EXE, "inspect", str(nan)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "no finite temperature" in p.stderr, p.stderr
    stuck = _parquet_variant(
        src,
        folder,
        "voltmeter",
        lambda df: df.with_columns(*(pl.lit(0.0).alias(c) for c in ("ux", "uy", "uz"))),
        "-stuck",
    )
    p = subprocess.run([EXE, "inspect", str(stuck)], capture_output=True, text=True, timeout=300)
    assert "Warning" not in p.stderr and "np." not in p.stderr, p.stderr
    with pytest.raises(RunFormatError):
        read_run(nan)
