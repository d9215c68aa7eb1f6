"""A voltmeter channel stuck, flat or clipped for part of a recording (pipeline.io.checks.stuck_stretches): the
stretch is named (stream and unit, channel, value, start as t_ns and seconds from the start, duration in s) and
treated as missing, so no hold in it is used; the constants from the rest stay within a few stated standard
uncertainties of the simulator's truth, in a single-unit run and in one unit of a 4-unit run, whose other units'
passports are those of the clean run. Live channels (noise-free-ish simulated runs at 0.5-100 Hz, quantised noise,
the real recordings) are never called stuck."""

from __future__ import annotations

import dataclasses
import re
import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.calibrate.methods import by_name, resolve_auto
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.io.checks import MIN_STUCK_SAMPLES, STUCK_FALSE_RATE, check_stream, stuck_stretches
from pipeline.io.runs import read_units, write_run
from pipeline.segment_units import segment_units
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import UnitTruth
from pipeline.simulate.units import simulate_units

REPO = Path(__file__).resolve().parents[2]
REAL = Path("/work/shared/reference/real")
#: the constants at T0 within this many stated standard uncertainties of the truth (measured: at most 2.4)
K_SIGMA = 4.0
STUCK_UNIT = {"single": "AU-0001", "multi": "AU-0302"}
#: (kind, start s from the recording's start, duration s, clip level V); the short program's -40 C holds start at
#: 2940 s, its last plateau ends at 12 710 s
VARIANTS = {
    "last value 20 min": ("hold", 2900.0, 1200.0, None),
    "last value 2 h": ("hold", 2900.0, 7200.0, None),
    "last value to the end": ("hold", 6000.0, None, None),
    "0 V 20 min": ("zero", 2900.0, 1200.0, None),
    "clipped at +0.3 V": ("clip", 0.0, None, 0.3),
}


def _simulated(tmp: Path, kind: str) -> tuple[Path, dict]:
    config = SimConfig(unit_serial=STUCK_UNIT["single"], program="short", rate_hz=2.0, seed=3)
    if kind == "single":
        res = simulate(config)
        return write_run(res.run, tmp / kind, "parquet"), {res.run.meta.unit_serial: res.truth}
    runs, truths = simulate_units(SimConfig(unit_serial="AU-0301", program="short", rate_hz=2.0, seed=3), 4)
    return write_run(runs, tmp / kind, "parquet"), truths


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("stuck")
    out = {}
    for kind in ("single", "multi"):
        path, truths = _simulated(tmp, kind)
        out[kind] = (path, truths, _calibrate(path))
    return tmp, out


def _variant(src: Path, dst: Path, unit: str, channel: str, spec) -> tuple[float, float, float]:
    """A copy of the run at ``src`` with ``channel`` of ``unit`` spoiled as ``spec`` says (real Parquet files edited
    with polars); returns (start s, duration s, the value read there)."""
    kind, a_s, dur_s, clip_v = spec
    shutil.copytree(src, dst)
    v = pl.read_parquet(dst / "voltmeter.parquet")
    t = v["t_ns"].to_numpy()
    t0 = int(t[0])
    end_s = (int(t[-1]) - t0) / 1e9 + 0.5 if dur_s is None else a_s + dur_s
    rel = (pl.col("t_ns") - t0) / 1e9
    mine = (pl.col("unit") == unit) if "unit" in v.columns else pl.lit(True)
    sel = mine & (rel >= a_s) & (rel < end_s)
    if kind == "hold":
        before = v.filter(mine & (rel < a_s))
        value, a_s = (
            float(before[channel][-1]),
            (int(before["t_ns"][-1]) - t0) / 1e9,
        )  # the last value, from its own sample
        new = pl.when(sel).then(pl.lit(value))
    elif kind == "zero":
        value, new = 0.0, pl.when(sel).then(pl.lit(0.0))
    else:
        value, new = clip_v, pl.when(sel & (pl.col(channel) > clip_v)).then(pl.lit(clip_v))
    v.with_columns(new.otherwise(pl.col(channel)).alias(channel)).write_parquet(dst / "voltmeter.parquet")
    return a_s, end_s - a_s, value


def _calibrate(path: Path) -> dict:
    """Each unit's (constants' max z against nothing yet: the passport document, the warnings) read from real
    files, segmented as the calibrate flow does (the units' consensus), by the method auto picks."""
    runs = read_units(path)
    settings = CalibrationSettings()
    segs, _ = segment_units(runs.units, settings.segment)
    out = {}
    for serial, run in runs.units.items():
        method, _, seg, _ = resolve_auto(run, settings, None, segs[serial])
        m = by_name(method)
        res = m.calibrate_observed([m.observe(run, settings, segmentation=seg)], settings)
        out[serial] = (res.passport, res.warnings)
    return out


def _max_z(doc: dict, truth: dict) -> float:
    k, u0 = UnitTruth.from_dict(truth["unit"]).constants_at(np.array([doc["normal_temp_c"]]))
    sigma = doc["uncertainty"]["coefficients"]
    z_k = np.abs(np.array(doc["coefficients"]["K"]) - k[0]) / np.array(sigma["K"])
    z_u = np.abs(np.array(doc["coefficients"]["U0"]) - u0[0]) / np.array(sigma["U0"])
    return float(max(z_k.max(), z_u.max()))


@pytest.mark.parametrize("kind", ["single", "multi"])
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_a_stuck_stretch_is_named_and_left_out(clean, kind, variant):
    """The stuck unit's warning names the channel, the stuck value (and a rail when clipped), the first stretch's
    start (t_ns, s after the start) and duration (s); its constants are within K_SIGMA of the truth; no warning
    calls it turned on the fixture or not still (before: a 20-min stretch at the last value in a 4-unit run read
    'not still in 2 of the 65 holds ... (fixture: VP6)', 2 h 'names 25 of its 117 positions otherwise than the
    other units: mounted turned on the fixture, or a slipped clamp?', and clipping at +0.3 V gave K off by
    0.15 V/g with no word of clipping); the other units' passports are the clean run's."""
    tmp, runs = clean
    src, truths, before = runs[kind]
    unit = STUCK_UNIT[kind]
    dst = tmp / f"{kind}-{re.sub(r'[^a-z0-9]+', '-', variant)}"
    a_s, dur_s, value = _variant(src, dst, unit, "uy", VARIANTS[variant])
    after = _calibrate(dst)
    doc, warnings = after[unit]
    said = [w for w in warnings if ": uy stuck (one reading repeated for >= " in w]
    assert len(said) == 1, warnings
    line = said[0]
    assert ("unit AU-0302" in line) == (kind == "multi")
    first = re.search(
        r"the first at (\S+) V(.*?) for ([\d.]+) s from t_ns=(\d+) \(.*?, ([\d.]+) s after the start\)", line
    )
    assert first, line
    assert float(first.group(1)) == pytest.approx(value, abs=5e-8)
    if VARIANTS[variant][0] == "clip":
        assert "clipped at a rail" in first.group(2)
        assert re.search(r"in \d+ stretch\(es\)", line)
    else:
        assert "in 1 stretch(es)" in line
        assert float(first.group(5)) == pytest.approx(a_s, abs=0.6)
        assert float(first.group(3)) == pytest.approx(dur_s, abs=1.1)
    assert not [w for w in warnings if "not still in" in w or "otherwise than the other units" in w]
    assert _max_z(doc, truths[unit]) < K_SIGMA
    for serial, (other, _) in after.items():
        if serial != unit:
            assert other["coefficients"] == before[serial][0]["coefficients"]
            assert other["status"] == before[serial][0]["status"]


def _stuck_lines(run) -> list[str]:
    w: list[str] = []
    check_stream("voltmeter", run.voltmeter, path="x", warnings=w)
    return [x for x in w if "stuck" in x]


@pytest.mark.parametrize(
    ("program", "rate_hz"),
    [("short", 0.5), ("short", 2.0), ("short", 10.0), ("differential", 20.0), ("handheld", 100.0)],
)
def test_clean_simulated_runs_have_no_stuck_channel(program, rate_hz):
    """Noise-free-ish simulated runs from 0.5 to 100 Hz, as simulated and quantised to a 24-bit +-1 V voltmeter's
    LSB (1.19e-7 V: 5 uV of noise repeats a reading ~1 % of the time): nothing called stuck."""
    run = simulate(SimConfig(program=program, rate_hz=rate_hz, seed=7)).run
    assert _stuck_lines(run) == []
    lsb = 2.0 / 2**24
    q = run.voltmeter.with_columns([(pl.col(c) / lsb).round() * lsb for c in ("ux", "uy", "uz")])
    assert _stuck_lines(dataclasses.replace(run, voltmeter=q)) == []


@pytest.mark.parametrize("run", ["imucal_ferraris/run", "cats_tag/run"])
def test_real_recordings_have_no_stuck_channel(run):
    """The real recordings (their readings repeat 2-12 % of the time, at most 4-6 in a row): no stuck warning."""
    if not (REAL / run).exists():
        pytest.skip("the real recordings are not on this machine")
    runs = read_units(REAL / run)
    assert not [w for r in runs.units.values() for w in r.warnings if "stuck" in w]


@pytest.mark.parametrize("sample", ["standard_short.mcap", "standard_short_parquet"])
def test_sample_data_has_no_stuck_channel(sample):
    runs = read_units(REPO / "sample_data" / sample)
    assert not [w for r in runs.units.values() for w in r.warnings if "stuck" in w]


@pytest.mark.parametrize("lsb_over_sigma", [0.1, 1.0, 2.0])
def test_the_threshold_follows_the_channel_s_own_repeats(lsb_over_sigma):
    """Coarsely quantised Gaussian noise (a step of 0.1 .. 2 sigma: consecutive readings equal 3 .. 52 % of the
    time), 400 000 samples: no live run is called stuck, and a run of the threshold's length planted in it is
    found with its exact bounds; the threshold is 1 + ceil(log(STUCK_FALSE_RATE / N) / log p) for the measured p."""
    rng = np.random.default_rng(int(lsb_over_sigma * 10))
    n = 400_000
    x = np.round(rng.normal(0.0, 1.0, n) / lsb_over_sigma) * lsb_over_sigma * 1e-5
    runs, n_min, hi, lo = stuck_stretches(pl.Series(x))
    assert runs.shape == (0, 2)
    p = float(np.mean(x[1:] == x[:-1]))
    if p >= 0.5:
        assert n_min == n
        return
    expected = max(MIN_STUCK_SAMPLES, 1 + int(np.ceil(np.log(STUCK_FALSE_RATE / n) / np.log(p))))
    assert abs(n_min - expected) <= 1  # p measured without the runs called stuck (none here)
    x[1000 : 1000 + n_min] = 0.123
    runs, _, hi, _ = stuck_stretches(pl.Series(x))
    assert runs.tolist() == [[1000, 1000 + n_min]] and hi == 0.123


def test_stuck_runs_are_the_maximal_runs_across_slabs(monkeypatch):
    """Against a plain loop over the samples: quantised noise with planted runs of 1-40 equal readings and NaNs,
    slabs of 1000 samples (runs crossing their edges): the stretches found are exactly the maximal runs of one
    finite reading at least the threshold long."""
    import pipeline.io.checks as checks

    monkeypatch.setattr(checks, "SLAB_SAMPLES", 1000)
    rng = np.random.default_rng(1)
    for _ in range(100):
        n = int(rng.integers(1, 5000))
        y = np.round(rng.normal(0.0, 1.0, n) * rng.choice([0.5, 1.0, 3.0]))
        for _ in range(3):
            a = int(rng.integers(0, n))
            y[a : a + int(rng.integers(1, 40))] = 7.0
        if rng.random() < 0.3:
            y[rng.integers(0, n, 5)] = np.nan
        runs, n_min, _, _ = checks.stuck_stretches(pl.Series(y))
        loop, i = [], 0
        while i < n:
            j = i + 1
            while j < n and y[j] == y[i]:
                j += 1
            if j - i >= n_min:
                loop.append([i, j])
            i = j
        assert runs.tolist() == loop
