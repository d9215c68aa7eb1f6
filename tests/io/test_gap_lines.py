"""The readers' gap warnings (issue 21): a gap is missing data, said once: one line per set of streams whose gaps
coincide, whatever their rates, naming the streams, the count, the longest gap and its UTC span."""

from __future__ import annotations

import numpy as np
import polars as pl

from pipeline.io.checks import check_streams

T0 = 1_793_491_200 * 10**9  # 2026-11-01 00:00:00 UTC


def _stream(rate_hz: float, cols: list[str], drop_s: list[tuple[float, float]], seconds: float = 3600.0):
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    keep = np.ones(t.size, dtype=bool)
    for a, b in drop_s:
        keep &= (t < a) | (t > b)
    t = t[keep]
    return pl.DataFrame({"t_ns": T0 + np.round(t * 1e9).astype(np.int64), **{c: np.zeros(t.size) for c in cols}})


def test_one_line_for_a_logger_that_stopped_whatever_the_rates():
    drop = [(1500.0, 2100.0)]
    frames = {
        "voltmeter": _stream(10.0, ["ux", "uy", "uz"], drop),
        "au_temperature": _stream(1.0, ["temp_c"], drop),
        "chamber": _stream(0.2, ["setpoint_c", "air_c"], drop),
    }
    warnings: list[str] = []
    check_streams(frames, path="run.mcap", warnings=warnings)
    assert len(warnings) == 1, warnings
    (line,) = warnings
    assert line.startswith("voltmeter, au_temperature, chamber: 1 gap(s) without samples, the longest 600.2 s")
    assert "00:24:59.900 .. 00:35:00.100 UTC" in line and "nothing is made across a gap" in line
    assert "either side" not in line


def test_streams_with_other_gaps_get_a_line_each_and_no_stream_two():
    frames = {
        "voltmeter": _stream(10.0, ["ux", "uy", "uz"], [(100.0, 160.0), (1000.0, 1300.0)]),
        "au_temperature": _stream(1.0, ["temp_c"], [(100.0, 160.0)]),
        "chamber": _stream(1.0, ["setpoint_c", "air_c"], []),
    }
    warnings: list[str] = []
    check_streams(frames, path="run.mcap", warnings=warnings)
    assert len(warnings) == 2, warnings
    assert warnings[0].startswith("voltmeter: 2 gap(s) without samples, the longest 300.2 s")
    assert warnings[1].startswith("au_temperature: 1 gap(s) without samples, the longest 62.0 s")
    assert not any("chamber" in w for w in warnings)
