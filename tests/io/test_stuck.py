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
from pipeline.errors import ThermocalError
from pipeline.io.checks import MIN_STUCK_SAMPLES, STUCK_FALSE_RATE, check_stream, rail_stretches, stuck_stretches
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
    # too little left: the first plateau only, before the stretch
    "last value from 15 min to the end": ("hold", 900.0, None, None),
    "0 V 20 min": ("zero", 2900.0, 1200.0, None),
    "clipped at +0.3 V": ("clip", 0.0, None, 0.3),
    "clipped at 0 V": ("clip", 0.0, None, 0.0),
    # the rail at the median of the -40 C TP2 hold (uy at +1 g): that hold half clipped, no long run of one value there
    "clipped at a hold's median": ("clip", 3020.0, 40.0, None),
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
        if clip_v is None:  # the median of the stretch given; the whole run clipped there
            clip_v = float(np.median(v.filter(sel)[channel].to_numpy()))
        value, new = clip_v, pl.when(mine & (pl.col(channel) > clip_v)).then(pl.lit(clip_v))
    v.with_columns(new.otherwise(pl.col(channel)).alias(channel)).write_parquet(dst / "voltmeter.parquet")
    return a_s, end_s - a_s, value


def _calibrate(path: Path) -> dict:
    """Each unit's (passport document or None, warnings, the refusal's one line or None), read from real files,
    segmented as the calibrate flow does (the units' consensus), by the method auto picks."""
    runs = read_units(path)
    settings = CalibrationSettings()
    segs, _ = segment_units(runs.units, settings.segment)
    out: dict[str, tuple[dict | None, list[str], str | None]] = {}
    for serial, run in runs.units.items():
        try:
            method, _, seg, _ = resolve_auto(run, settings, None, segs[serial])
            m = by_name(method)
            res = m.calibrate_observed([m.observe(run, settings, segmentation=seg)], settings)
        except ThermocalError as e:
            out[serial] = (None, list(run.warnings), e.one_line())
        else:
            out[serial] = (res.passport, res.warnings, None)
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
    doc, warnings, refused = after[unit]
    clip = VARIANTS[variant][0] == "clip"
    head = (
        f": uy clipped at {value:.7g} V, its highest reading (" if clip else ": uy stuck (one reading repeated for >= "
    )
    said = [w for w in warnings if head in w]
    assert len(said) == 1, warnings
    assert not [w for w in warnings if ": uy " in w and w not in said]
    line = said[0]
    assert ("unit AU-0302" in line) == (kind == "multi")
    first = re.search(
        r"the first at (\S+) V(.*?) for ([\d.]+) s from t_ns=(\d+) \(.*?, ([\d.]+) s after the start\)", line
    )
    assert first, line
    assert float(first.group(1)) == pytest.approx(value, abs=5e-8)
    if clip:
        assert re.search(r"\((\d+) samples read it, (\d+) the next lower value: a rail", line)
    else:
        assert "in 1 stretch(es)" in line
        assert float(first.group(5)) == pytest.approx(a_s, abs=0.6)
        assert float(first.group(3)) == pytest.approx(dur_s, abs=1.1)
    assert not [w for w in warnings if "not still in" in w or "otherwise than the other units" in w]
    if doc is None:  # too little left: this unit refused alone, in one line naming the channel left out
        assert refused and "\n" not in refused
        total = re.search(r" ([\d.]+) s in all", line)
        assert total
        clause = rf": uy (stuck|clipped at [^;]*) in \d+ stretch\(es\), {total.group(1)} s in all"
        assert re.search(rf"; left out as stuck or clipped: [^;]*{clause}", refused)
    elif len(doc["per_plateau"]) >= 2:
        assert _max_z(doc, truths[unit]) < K_SIGMA
    else:  # one plateau left (clipped at 0 V, AU-0302: -40 C): T0's constants extrapolated from it, undetermined
        assert doc["status"] == "fail"
        assert doc["uncertainty"]["coefficients"]["K"] == [[None] * 3] * 3
        assert "extrapolated by the thermal model" in doc["uncertainty"]["undetermined"]["K.xx"]
    for serial, (other, _, _) in after.items():
        if serial != unit:
            assert other is not None and before[serial][0] is not None
            assert other["coefficients"] == before[serial][0]["coefficients"]
            assert other["status"] == before[serial][0]["status"]


def _stuck_lines(run) -> list[str]:
    w: list[str] = []
    check_stream("voltmeter", run.voltmeter, path="x", warnings=w)
    return [x for x in w if "stuck" in x or "clipped" in x]


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


@pytest.mark.parametrize(("program", "rate_hz"), [("short", 10.0), ("standard", 1.0), ("fast", 5.0), ("sweep", 2.0)])
@pytest.mark.parametrize(("step_v", "average"), [(1e-3, 1), (3e-4, 1), (5e-5, 1), (3e-4, 10), (1e-5, 10)])
def test_coarsely_quantised_clean_runs_have_no_stuck_channel(program, rate_hz, step_v, average):
    """A clean run read by a coarse voltmeter (1 mV or 0.3 mV steps: 5 uV of noise is 0.005-0.1 of a step), or
    averaged over 10 samples then quantised: every quiet hold reads one value for most of its length. Before, the
    stuck test measured p outside the runs it called stuck, so it called 40-1600 stretches at 6-1600 different
    values stuck (short 10 Hz at 1 mV: 12 100 s of 12 700 on each channel, and the +1 g holds a rail) and
    ``calibrate`` refused the run ('no named static position on any of the 7 temperature plateau(s)'). Now a
    channel whose stretches hold more than MAX_STUCK_VALUES values is not judged: nothing called stuck or clipped."""
    run = simulate(SimConfig(program=program, rate_hz=rate_hz, seed=11)).run
    v = run.voltmeter
    box = np.ones(average) / average
    q = v.with_columns(
        [
            pl.Series(c, np.round(np.convolve(v[c].to_numpy(), box, mode="same") / step_v) * step_v)
            for c in ("ux", "uy", "uz")
        ]
    )
    assert _stuck_lines(dataclasses.replace(run, voltmeter=q)) == []


def test_a_channel_that_freezes_at_its_last_value_four_times_is_named_each_time():
    """Short program, 2 Hz: uy frozen at its last value for 300 s from 2000, 4000, 6000 and 8000 s (four stretches
    at four values; before: none named, the clause for coarse voltmeters taking them for quiet holds): one line
    naming 4 stretches, 1200 s in all, and those 2400 samples missing."""
    run = simulate(SimConfig(program="short", rate_hz=2.0, seed=3)).run
    v = run.voltmeter
    t = v["t_ns"].to_numpy()
    rel = (t - t[0]) / 1e9
    y = v["uy"].to_numpy().copy()
    frozen = np.zeros(y.size, dtype=bool)
    for a in (2000.0, 4000.0, 6000.0, 8000.0):
        s = (rel > a) & (rel <= a + 300.0)
        y[s] = y[np.flatnonzero(rel <= a)[-1]]
        frozen |= s
    w: list[str] = []
    out = check_stream("voltmeter", v.with_columns(pl.Series("uy", y)), path="x", warnings=w)
    said = [x for x in w if "stuck" in x or "clipped" in x]
    assert (
        len(said) == 1
        and said[0].startswith("voltmeter: uy stuck (")
        and " in 4 stretch(es), 1202.0 s in all" in said[0]
    )
    gone = np.isnan(out["uy"].to_numpy())
    assert gone.sum() == frozen.sum() + 4 and not (frozen & ~gone).any()  # each from the last live sample, its value


@pytest.mark.parametrize("run", ["imucal_ferraris/run", "cats_tag/run"])
def test_real_recordings_have_no_stuck_channel(run):
    """The real recordings (their readings repeat 2-12 % of the time, at most 4-6 in a row): no stuck warning."""
    if not (REAL / run).exists():
        pytest.skip("the real recordings are not on this machine")
    runs = read_units(REAL / run)
    assert not [w for r in runs.units.values() for w in r.warnings if "stuck" in w or "clipped" in w]


@pytest.mark.parametrize("sample", ["standard_short.mcap", "standard_short_parquet"])
def test_sample_data_has_no_stuck_channel(sample):
    runs = read_units(REPO / "sample_data" / sample)
    assert not [w for r in runs.units.values() for w in r.warnings if "stuck" in w or "clipped" in w]


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
    finite reading at least the threshold long (before the local test, which
    test_clean_quantised_holds_have_no_stuck_stretch_and_a_freeze_in_them_is_named checks, drops those that the
    readings beside them explain: here the plain loop's runs of a common value)."""
    import pipeline.io.checks as checks

    monkeypatch.setattr(checks, "SLAB_SAMPLES", 1000)
    monkeypatch.setattr(
        checks, "_locally_unlikely", lambda col, runs, n, interval_s=0.0: np.ones(runs.shape[0], dtype=bool)
    )
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


@pytest.mark.parametrize("rate_hz", [2.0, 10.0, 100.0])
def test_a_hold_clipped_within_its_noise_is_left_out_whole(rate_hz):
    """A 60-s hold whose signal lies at the rail (5 uV noise, every reading above the rail read as the rail: half
    its readings) between live holds 1 mV below: the readings at the rail come in short runs (a run of 4 or more
    only 1 in 8), so the stuck test alone kept most of them and every reading below the rail, a mean biased by
    -0.4 sigma or more. Now the whole hold, from its first reading at the rail to its last, is missing and named as
    clipped with the rail's value; the live holds are untouched."""
    rng = np.random.default_rng(5)
    n = int(60 * rate_hz)
    rail = 0.55
    u = np.concatenate([rail - 1e-3 + 5e-6 * rng.normal(size=n), rail + 5e-6 * rng.normal(size=n)])
    u = np.concatenate([u, rail - 1e-3 + 5e-6 * rng.normal(size=n)])
    u = np.minimum(u, rail)
    t_ns = 1_793_491_200_000_000_000 + (np.arange(u.size) * 1e9 / rate_hz).astype(np.int64)
    live = 1e-3 + 5e-6 * rng.normal(size=u.size)
    df = pl.DataFrame({"t_ns": t_ns, "ux": live, "uy": u, "uz": -live})
    w: list[str] = []
    out = check_stream("voltmeter", df, path="x", warnings=w)
    gone = np.flatnonzero(np.isnan(out["uy"].to_numpy()))
    at = np.flatnonzero(u == rail)
    assert gone.tolist() == list(range(at[0], at[-1] + 1))
    assert at[0] < n + 5 and at[-1] > 2 * n - 5
    assert [x for x in w if x.startswith(f"voltmeter: uy clipped at {rail:.7g} V, its highest reading")]
    assert not np.isnan(out["ux"].to_numpy()).any() and not np.isnan(out["uz"].to_numpy()).any()


def _quantised_holds(seed: int, rate_hz: float, step_sigmas: float, sigma_v: float = 5e-4) -> tuple[np.ndarray, int]:
    """A clean channel (V) as a chamber run makes it: 40 holds of 60 s at levels drawn in -0.5..0.5 V (so at every
    place within a quantisation bin), each after a 30-s ramp; noise ``sigma_v``, read with a step of
    ``step_sigmas`` sigma. Returns the readings and the index of the middle of the 6th hold."""
    rng = np.random.default_rng(seed)
    hold, ramp = int(60 * rate_hz), int(30 * rate_hz)
    parts, level = [], 0.0
    for _ in range(40):
        nxt = rng.uniform(-0.5, 0.5)
        parts += [np.linspace(level, nxt, ramp, endpoint=False), np.full(hold, nxt)]
        level = nxt
    x = np.concatenate(parts)
    q = step_sigmas * sigma_v
    return np.round((x + rng.normal(0.0, sigma_v, x.size)) / q) * q, 5 * (hold + ramp) + ramp + hold // 2


@pytest.mark.parametrize("rate_hz", [0.5, 2.0, 10.0])
@pytest.mark.parametrize("step_sigmas", [0.25, 0.5, 1.0, 1.5, 2.0])
def test_clean_quantised_holds_have_no_stuck_stretch_and_a_freeze_in_them_is_named(rate_hz, step_sigmas):
    """A coarse step's chance of repeating a reading depends on where the hold's mean sits in its bin (68 % of a
    hold's readings in one bin at the middle of it, with a step of 2 sigma): the channel-wide p of the test before
    called 1-4 runs of 10-27 samples in 53 of these 300 channels (and a consumer unit on a 1-mV voltmeter 'uy
    stuck ... 2.7 s'). Seeds 0..19: no stuck stretch; the same channels frozen at their last value for 120 s from
    the middle of a hold: that stretch named (a run holding it)."""
    for seed in range(20):
        x, a = _quantised_holds(seed, rate_hz, step_sigmas)
        runs, _, _, _ = stuck_stretches(pl.Series(x), 1.0 / rate_hz)
        assert runs.tolist() == [], (seed, runs.tolist())
        end = a + int(120 * rate_hz)
        x[a:end] = x[a - 1]
        runs, _, _, _ = stuck_stretches(pl.Series(x), 1.0 / rate_hz)
        assert [[s, e] for s, e in runs.tolist() if s <= a - 1 and e >= end], (seed, runs.tolist())


@pytest.mark.parametrize("seed", range(20))
def test_a_consumer_unit_on_a_coarse_voltmeter_has_no_stuck_channel(seed):
    """A consumer unit (0.5 mV of noise), short program at 10 Hz, its voltages read with a step of 0.25-2 sigma
    (0.125-1 mV): nothing called stuck or clipped (before: 25 of these 300 channels, e.g. seed 2 at 1 mV: 'uy stuck
    (one reading repeated for >= 2.6 s, 26 samples ...) ... for 2.7 s')."""
    run = simulate(SimConfig(program="short", rate_hz=10.0, seed=seed, unit_type="consumer", noise_v=5e-4)).run
    for step_sigmas in (0.25, 0.5, 1.0, 1.5, 2.0):
        q = step_sigmas * 5e-4
        v = run.voltmeter.with_columns([(pl.col(c) / q).round() * q for c in ("ux", "uy", "uz")])
        assert _stuck_lines(dataclasses.replace(run, voltmeter=v)) == [], step_sigmas


@pytest.mark.parametrize("seed", range(20))
def test_a_short_hold_at_a_coarse_channel_s_extreme_is_not_a_rail(seed):
    """Short program at 0.5 Hz (a hold is ~30 readings), 5 uV of noise read with a step of 0.25-2 sigma: the +1 g
    hold at the hottest plateau is a channel's highest reading and its mean may sit in the top bin, read about
    twice as often as the next lower one. Before, the bare factor 2 called 3 of these 100 runs' holds a rail and
    set them to NaN (seed 11 at 10 uV: 'ux clipped at 0.56256 V, its highest reading (21 samples read it, 10 the
    next lower value ...'): nothing called stuck or clipped."""
    run = simulate(SimConfig(program="short", rate_hz=0.5, seed=seed)).run
    for step_sigmas in (0.25, 0.5, 1.0, 1.5, 2.0):
        q = step_sigmas * 5e-6
        v = run.voltmeter.with_columns([(pl.col(c) / q).round() * q for c in ("ux", "uy", "uz")])
        assert _stuck_lines(dataclasses.replace(run, voltmeter=v)) == [], step_sigmas


@pytest.mark.parametrize(("found", "n_next", "rail"), [(21, 10, False), (10, 5, False), (60, 1, True), (40, 5, True)])
def test_a_rail_reads_more_than_twice_the_next_value_by_three_poisson_sigmas(found, n_next, rail):
    """The rail rule on counts: k readings at the extreme, j at the next value inwards; a rail when
    k - 2 j >= 3 sqrt(k + 4 j) (21 and 10, 10 and 5: a live hold in the top bin; 60 and 1, 40 and 5: clipped; the
    bare factor 2 called the first two a rail). The hold's readings mixed, between live readings."""
    rng = np.random.default_rng(0)
    hold = rng.permutation(np.concatenate([np.full(found, 1.0), np.full(n_next, 0.9), rng.uniform(0.7, 0.8, 10)]))
    x = np.concatenate([rng.uniform(-0.5, 0.5, 200), hold, rng.uniform(-0.5, 0.5, 200)])
    clipped, k, j = rail_stretches(pl.Series(x), 1.0, 4)
    assert (k, j) == (found, n_next)
    assert clipped.tolist() == (
        [[200 + int(np.argmax(hold == 1.0)), 200 + hold.size - int(np.argmax(hold[::-1] == 1.0))]] if rail else []
    )


@pytest.mark.parametrize("fmt", ["parquet", "mcap"])
def test_a_frozen_thermosensor_is_named_and_makes_no_plateau(tmp_path, fmt):
    """Short program at 2 Hz: the AU thermosensor frozen at its last reading (-10.0 C, on the way down to -40 C) for
    an hour from 4500 s. Before: not a word, and a -10 C plateau that is not there (6 plateaus: 20, -40, -10, 45,
    70, 20 C) with a 'reading creeps after each move' correction of the holds. Now one warning names it, those
    readings are missing (a gap in the thermosensor: no voltmeter sample there has a temperature), not counted again
    as non-finite, and the plateaus are the program's other five."""
    from pipeline.segment import segment_run

    res = simulate(SimConfig(program="short", rate_hz=2.0, seed=3))
    t = res.run.au_temperature
    rel = (t["t_ns"].to_numpy() - int(t["t_ns"][0])) / 1e9
    a = int(np.flatnonzero(rel < 4500)[-1])  # the last reading before: its value repeated
    frozen = (rel >= 4500) & (rel < 8100)
    temp = t["temp_c"].to_numpy().copy()
    temp[frozen] = temp[a]
    run = dataclasses.replace(res.run, au_temperature=t.with_columns(pl.Series("temp_c", temp)))
    path = write_run(run, tmp_path / f"r.{fmt}" if fmt == "mcap" else tmp_path / "r", fmt)
    read = next(iter(read_units(path).units.values()))
    said = [w for w in read.warnings if "temp_c" in w]
    b = int(np.flatnonzero(frozen)[-1])
    start = int(t["t_ns"][a])
    assert len(said) == 1 and said[0].startswith(
        "au_temperature: temp_c stuck (one reading repeated for >= 4 s, 4 samples, which its noise does not give) "
        f"in 1 stretch(es), {b - a + 1:.1f} s in all: the first at {temp[a]:.7g} C for {b - a + 1:.1f} s from "
        f"t_ns={start} ("
    ), said
    gone = np.isnan(read.au_temperature["temp_c"].to_numpy())
    assert np.flatnonzero(gone).tolist() == list(range(a, b + 1))
    seg = segment_run(read)
    assert [round(p.temp_c) for p in seg.plateaus] == [20, -40, 45, 70, 20]
    assert not [w for w in seg.warnings if "non-finite" in w]


@pytest.mark.parametrize(
    ("program", "rate_hz"), [("short", 2.0), ("standard", 1.0), ("sweep", 2.0), ("handheld", 100.0)]
)
def test_a_live_thermosensor_is_never_called_stuck(program, rate_hz):
    """Simulated thermosensors, as simulated and read in steps of 0.001-0.5 C (a 0.0625-C sensor at a plateau reads
    one value for minutes; the 160-s handheld record's reads 20 C in all but one reading): nothing called stuck or
    clipped, the readings untouched."""
    for seed in range(3):
        t = simulate(SimConfig(program=program, rate_hz=rate_hz, seed=seed)).run.au_temperature
        for q in (0.0, 0.001, 0.01, 0.0625, 0.1, 0.5):
            x = t["temp_c"].to_numpy()
            x = np.round(x / q) * q if q else x
            w: list[str] = []
            out = check_stream("au_temperature", t.with_columns(pl.Series("temp_c", x)), path="x", warnings=w)
            assert [line for line in w if "stuck" in line or "clipped" in line] == [], (seed, q)
            assert np.array_equal(out["temp_c"].to_numpy(), x)


@pytest.mark.parametrize(
    ("rate_hz", "step_sigmas", "freeze_s", "caught"),
    [
        (10.0, 1.0, 5.0, 20),
        (10.0, 2.0, 5.0, 20),
        (10.0, 2.0, 10.0, 20),
        (2.0, 1.0, 10.0, 18),
        (2.0, 1.0, 20.0, 20),
        (2.0, 2.0, 10.0, 11),
        (2.0, 2.0, 20.0, 19),
        (2.0, 2.0, 30.0, 20),
    ],
)
def test_a_short_freeze_in_a_quantised_hold_is_named(rate_hz, step_sigmas, freeze_s, caught):
    """The local f of :func:`_locally_unlikely` taken from at least STUCK_WINDOW_S (30 s) on each side,
    both sides pooled. Taken from a window only as long as the freeze, the larger of the two sides, it was biased
    upward and kept short freezes as live: of 20 seeds, 10 Hz at 2 sigma 5 s 17 caught, 2 Hz at 1 sigma 10 s 15, at
    2 sigma 10 s 10 and 20 s 18. (A freeze as short as the live runs its hold's own f gives, e.g. 5 s at 2 Hz with
    f 0.4-0.7, cannot be told from them: the remaining misses at 2 Hz are those.)"""
    n = 0
    for seed in range(20):
        x, a = _quantised_holds(seed, rate_hz, step_sigmas)
        end = a + int(freeze_s * rate_hz)
        x[a:end] = x[a - 1]
        runs, _, _, _ = stuck_stretches(pl.Series(x), 1.0 / rate_hz)
        n += any(s <= a - 1 and e >= end for s, e in runs.tolist())
    assert n >= caught
