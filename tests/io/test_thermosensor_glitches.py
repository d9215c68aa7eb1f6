"""A thermosensor that reads a glitch now and then (a DS18B20's 85 C power-on value, -127 C on a bus error): the
glitched readings are missing data, said in a warning, so a soak keeps its plateau."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import polars as pl
import pytest

from pipeline.io.runs import read_run, write_run
from pipeline.run import NS_PER_S
from pipeline.segment import find_plateaus
from pipeline.simulate.chamber import SimConfig, simulate

# (s from the start, value C, readings in a row): in the TP holds at -40 C and at +70 C, in the ramp to -10 C
GLITCHES = {
    "85 C once at +70 C": [(10_000, 85.0, 1)],
    "-127 C once at -40 C": [(3_100, -127.0, 1)],
    "85 C three times at +70 C": [(10_050, 85.0, 3)],
    "several kinds": [(1_500, 85.0, 1), (3_100, -127.0, 2), (4_250, 85.0, 1), (10_000, 85.0, 1), (12_000, -127.0, 3)],
    # d9bcf11 counted readings (at most 3) and needed a reading on each side: none of these was named
    "85 C as the first reading (power-on)": [(0, 85.0, 1)],
    "85 C as the last reading": [(1e9, 85.0, 1)],
    "85 C twice at the start": [(0, 85.0, 2)],
    "-127 C as the last three readings": [(1e9, -127.0, 3)],
    "85 C four times at +70 C": [(10_050, 85.0, 4)],
    "-127 C for 10 s at -40 C": [(3_100, -127.0, 11)],
    "85 C then 125 C at +70 C": [(10_050, 85.0, 2), (10_052, 125.0, 2)],
    # the readings between two glitches are not a glitch (below both, which agree)
    "85 C twice, 5 s apart, at +70 C": [(10_050, 85.0, 1), (10_055, 85.0, 1)],
}


@cache
def _short_1hz():
    return simulate(SimConfig(seed=5, rate_hz=1.0, program="short")).run


def _with(run, glitches, value=None):
    """``run`` with the thermosensor's readings at ``glitches`` set to their value (or to ``value``); their rows."""
    th = run.au_temperature
    t_s = (th["t_ns"].to_numpy() - int(th["t_ns"][0])) / NS_PER_S
    y = th["temp_c"].to_numpy().copy()
    rows = []
    for at_s, v, n in glitches:
        i = min(int(np.argmin(np.abs(t_s - at_s))), y.size - n)  # past the end: the last n readings
        y[i : i + n] = v if value is None else value
        rows += range(i, i + n)
    return dataclasses.replace(run, au_temperature=th.with_columns(pl.Series("temp_c", y))), rows


@pytest.mark.parametrize("fmt", ["mcap", "parquet"])
@pytest.mark.parametrize("case", list(GLITCHES))
def test_thermosensor_glitches_read_as_missing_and_the_plateaus_stay(tmp_path, fmt, case):
    """Before: the glitched readings were kept as temperatures, with no warning; one 85 C reading in the +70 C soak
    lost that plateau (6 plateaus), and the short program with the "several kinds" glitches (20 of 12,711 readings
    at 10 Hz) was calibrated by the ramp method and failed (dK 14 uV/g, against 0.2 with no glitch)."""
    run = _short_1hz()
    glitched, rows = _with(run, GLITCHES[case])
    missing, _ = _with(run, GLITCHES[case], value=float("nan"))
    ext = ".mcap" if fmt == "mcap" else ""
    got = read_run(write_run(glitched, tmp_path / f"glitched{ext}", fmt))
    want = read_run(write_run(missing, tmp_path / f"missing{ext}", fmt))
    # the same tables as the run with those readings missing, bit for bit
    assert got.au_temperature.equals(want.au_temperature)
    assert got.voltmeter.equals(want.voltmeter)
    rows.sort()
    first = rows[0]
    th = glitched.au_temperature
    (line,) = [w for w in got.warnings if "glitch" in w]
    assert line == (
        f"au_temperature: {len(rows)} reading(s) of temp_c that leave the readings around them and come back, or "
        f"begin or end the record away from the readings beside them (a "
        f"glitch: more than 5 C plus 0.25 C/s) treated as missing; the first at t_ns={th['t_ns'][first]} (row "
        f"{first}): {th['temp_c'][first]!r}"
    )
    clean = find_plateaus(run.au_temperature["t_ns"].to_numpy(), run.au_temperature["temp_c"].to_numpy())
    found = find_plateaus(got.au_temperature["t_ns"].to_numpy(), got.au_temperature["temp_c"].to_numpy())
    assert [round(p.temp_c, 1) for p in found] == [round(p.temp_c, 1) for p in clean]
    assert [round(p.temp_c) for p in found] == [20, -40, -10, 20, 45, 70, 20]


@pytest.mark.parametrize(
    "change",
    [
        "a step that stays",  # a sensor whose offset moved: not a glitch
        "a fast ramp read once a minute",  # 15 C between readings, and a corner: the case can move that far
        "noise of 1 C",
    ],
)
def test_what_is_not_a_glitch_is_left_alone(tmp_path, change):
    run = _short_1hz()
    th = run.au_temperature
    t_s = (th["t_ns"].to_numpy() - int(th["t_ns"][0])) / NS_PER_S
    y = th["temp_c"].to_numpy().copy()
    t_ns = th["t_ns"].to_numpy()
    if change == "a step that stays":
        y[t_s >= 3_100] += 8.0
    elif change == "a fast ramp read once a minute":
        keep = np.arange(0, t_s.size, 60)
        t_ns = t_ns[keep]
        y = np.where(t_s[keep] < 600, 20.0, np.maximum(-40.0, 20.0 - 15.0 * (t_s[keep] - 600) / 60))
    else:
        y += np.random.default_rng(1).normal(0.0, 1.0, y.size)
    changed = dataclasses.replace(run, au_temperature=pl.DataFrame({"t_ns": t_ns, "temp_c": y}))
    got = read_run(write_run(changed, tmp_path / "run.mcap"))
    assert not [w for w in got.warnings if "glitch" in w]
    assert np.array_equal(got.au_temperature["temp_c"].to_numpy(), y)
