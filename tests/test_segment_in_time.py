"""Segmentation works in time, not samples (issue 21, item 2): windows, thresholds and minimum durations are seconds
that hold for any stream rate, and a gap is missing data: no static stretch spans one."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.positions import ALL_POSITIONS
from pipeline.run import NS_PER_S
from pipeline.segment import SegmentSettings, find_static, for_rate, gap_spans, split_runs


@pytest.mark.parametrize("rate_hz", [0.5, 1.0, 10.0, 100.0, 1000.0])
def test_no_static_stretch_spans_a_gap_at_any_rate(rate_hz):
    """TP1 held for 5 min, a 2-min gap in which the unit was turned to TP2, TP2 held for 5 min: two stretches, the
    gap between them, each of one position (before: one stretch from TP1 across the gap into TP2)."""
    rng = np.random.default_rng(1)
    t_s = np.arange(0.0, 720.0, 1.0 / rate_hz)
    g = np.where((t_s < 360.0)[:, None], ALL_POSITIONS["TP1"], ALL_POSITIONS["TP2"])
    u = -0.55 * g + rng.normal(0.0, 5e-6, g.shape)
    keep = (t_s < 300.0) | (t_s > 420.0)
    t_ns = (t_s[keep] * NS_PER_S).astype(np.int64)
    runs = find_static(t_ns, u[keep], for_rate(SegmentSettings(), t_ns))
    assert len(runs) == 2, runs
    (a0, b0), (a1, b1) = runs
    assert t_ns[b0 - 1] < 300.5 * NS_PER_S and t_ns[a1] > 419.5 * NS_PER_S
    for a, b in runs:
        assert np.ptp(u[keep][a:b, 1]) < 1e-3  # one position each


def test_a_short_gap_does_not_cut_a_stretch():
    """A gap shorter than half the static window (2 s at 10 Hz; a 0.7-s gap, which inspect lists) is no cut."""
    t_s = np.arange(0.0, 300.0, 0.1)
    keep = (t_s < 150.0) | (t_s > 150.55)
    t_ns = (t_s[keep] * NS_PER_S).astype(np.int64)
    u = np.tile(-0.55 * np.asarray(ALL_POSITIONS["TP1"]), (t_ns.size, 1))
    u += np.random.default_rng(2).normal(0.0, 5e-6, u.shape)
    assert len(find_static(t_ns, u, for_rate(SegmentSettings(), t_ns))) == 1


def test_split_runs_and_gap_spans():
    runs = np.array([[0, 10], [12, 20]])
    assert split_runs(runs, np.array([5, 12, 15])).tolist() == [[0, 5], [5, 10], [12, 15], [15, 20]]
    assert split_runs(runs, np.array([], dtype=np.int64)).tolist() == runs.tolist()
    assert gap_spans(np.array([0, 1, 2, 30, 31, 32]) * NS_PER_S, 2.0).tolist() == [[2 * NS_PER_S, 30 * NS_PER_S]]
    assert gap_spans(np.array([0, 1, 2, 30, 31, 32]) * NS_PER_S, 30.0).tolist() == []
