"""``inspect``: per-stream counts, rates, spans, gaps and non-finite samples of a run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.inspect import format_summary, stream_summary, summarize_run, utc_text
from pipeline.io.runs import read_run, write_run
from pipeline.run import Run, RunMeta, make_frame

T0_NS = 1_793_491_200_000_000_000


@pytest.fixture(scope="module")
def run() -> Run:
    """2000 s at 10 Hz with a 30.1 s hole at 500 s; 1 Hz temperature with a 12 s hole at 1000 s; 4 NaNs."""
    rng = np.random.default_rng(5)
    t_v = T0_NS + np.arange(20_000, dtype=np.int64) * 100_000_000
    t_v = t_v[(t_v <= T0_NS + 500 * 10**9) | (t_v >= T0_NS + 530_100_000_000)]
    u = rng.normal(0.0, 0.5, (len(t_v), 3))
    u[[10, 11, 12], 0] = [np.nan, np.inf, -np.inf]
    u[100, 2] = np.nan
    t_t = T0_NS + np.arange(2000, dtype=np.int64) * 10**9
    t_t = t_t[(t_t <= T0_NS + 1000 * 10**9) | (t_t >= T0_NS + 1012 * 10**9)]
    return Run(
        meta=RunMeta(unit_serial="AU-0003", run_id="inspect-1", station="ch1"),
        voltmeter=make_frame("voltmeter", {"t_ns": t_v, "ux": u[:, 0], "uy": u[:, 1], "uz": u[:, 2]}),
        au_temperature=make_frame("au_temperature", {"t_ns": t_t, "temp_c": np.full(len(t_t), 20.0)}),
        fixture=make_frame(
            "fixture", {"t_ns": [T0_NS, T0_NS + 600 * 10**9, T0_NS + 610 * 10**9], "position": ["TP1", "MOVING", "TP2"]}
        ),
    )


def test_stream_statistics(run):
    s = summarize_run(run)
    v = s["streams"]["voltmeter"]
    assert v["samples"] == 20_000 - 300
    assert v["rate_hz"] == pytest.approx(10.0, rel=1e-12)
    assert v["t_start_ns"] == T0_NS and v["t_end_ns"] == T0_NS + 19_999 * 100_000_000
    assert v["duration_s"] == pytest.approx(1999.9, abs=1e-6)
    assert v["gaps"] == [[T0_NS + 500 * 10**9, pytest.approx(30.1, abs=1e-9)]]
    assert v["non_finite"] == 4
    t = s["streams"]["au_temperature"]
    assert t["samples"] == 2000 - 11 and t["rate_hz"] == pytest.approx(1.0)
    assert t["gaps"] == [[T0_NS + 1000 * 10**9, pytest.approx(12.0)]] and t["non_finite"] == 0
    f = s["streams"]["fixture"]
    assert f["samples"] == 3 and f["rate_hz"] is None and f["gaps"] == []
    assert f["positions"] == ["MOVING", "TP1", "TP2"]
    assert "chamber" not in s["streams"]
    assert s["metadata"]["unit_serial"] == "AU-0003"
    assert isinstance(s["plateaus"], list) and isinstance(s["static_positions"], list)
    json.dumps(s)  # JSON-ready for `inspect --json`


def test_same_summary_from_either_file_layout(run, tmp_path):
    base = summarize_run(run)
    base_streams = base["streams"]
    for fmt, name in (("mcap", "r.mcap"), ("parquet", "r_dir")):
        s = summarize_run(read_run(write_run(run, tmp_path / name, fmt=fmt)))
        assert s["streams"] == base_streams
        assert s["source"] == str(tmp_path / name)


def test_format_summary(run):
    text = format_summary(summarize_run(run))
    assert "run inspect-1  unit AU-0003  station ch1" in text
    assert "voltmeter: 19700 samples, 10 Hz, 33.3 min" in text
    assert f"1 gaps (longest 30.1 s at {utc_text(T0_NS + 500 * 10**9)})" in text
    assert "4 non-finite values" in text
    assert "fixture: 3 events" in text and "positions MOVING TP1 TP2" in text
    assert "segmentation:" in text


def test_short_streams():
    assert stream_summary("chamber", np.array([], dtype=np.int64), 0)["samples"] == 0
    one = stream_summary("chamber", np.array([T0_NS]), 0)
    assert one["samples"] == 1 and one["rate_hz"] is None and one["duration_s"] == 0.0


@pytest.mark.parametrize("sample", ["standard_short.mcap", "standard_short_parquet"])
def test_auto_picks_tilt_on_a_plateau_program_with_or_without_a_fixture_log(sample):
    """The Parquet sample has no fixture log; its poses are named from gravity, and five plateaus hold all six test
    positions: tilt (which fits the thermal model) is chosen, not scalar (constants at T0 only, which left the
    sample's VP errors uncompensated: status fail)."""
    from pipeline.inspect import describe_recording
    from pipeline.segment import segment_run
    from tests.conftest import REPO

    run = read_run(REPO / "sample_data" / sample)
    rec = describe_recording(run, segment_run(run))
    assert rec["temperature"]["kind"] == "plateaus"
    assert rec["method_auto"] == "tilt"
    assert rec["methods"][0]["method"] == "tilt" and rec["methods"][0]["supported"]
