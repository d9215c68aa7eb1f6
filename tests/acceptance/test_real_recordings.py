"""Real recordings nobody here made (tests/data/real/): what inspect says about them, and the static poses the
segmenter finds against the hand labels of imucal and the periods of the CATS authors."""

from __future__ import annotations

import json
from datetime import UTC, datetime

import numpy as np
import pytest

from pipeline.inspect import format_summary, summarize_run
from pipeline.io.runs import read_run
from tests.conftest import data_path

pytestmark = pytest.mark.slow  # an end-to-end proof on long or many recordings


def _ns(text: str) -> int:
    return int(datetime.fromisoformat(text).replace(tzinfo=UTC).timestamp()) * 10**9


#: the CATS authors' three periods (README of the recording) and the axis vertical (pointing down) in each
CATS_PERIODS = [
    ("2021-09-20T09:00", "2021-09-21T10:33", "-z"),
    ("2021-09-21T10:40", "2021-09-22T11:55", "-x"),
    ("2021-09-22T12:14", "2021-09-23T11:19", "-y"),
]


@pytest.fixture(scope="module")
def cats():
    run = read_run(data_path("real", "cats_tag", "run"))
    return run, summarize_run(run)


@pytest.fixture(scope="module")
def ferraris():
    base = data_path("real", "imucal_ferraris")
    run = read_run(base / "run")
    return run, summarize_run(run), json.loads((base / "labels.json").read_text())


def test_cats_is_a_sweep_with_three_orientations(cats):
    _, s = cats
    rec = s["recording"]
    t = rec["temperature"]
    assert t["kind"] == "sweep"
    assert s["plateaus"] == [] and t["plateaus"] == 0  # not 123 plateaus of a drift
    assert 4.5 < t["range_c"][0] < 5.0 and 27.5 < t["range_c"][1] < 28.0
    assert 40.0 < t["max_rate_c_per_h"] < 150.0
    long = [p for p in rec["poses"] if p["longest_hold_s"] > 20 * 3600]
    assert [p["vertical_axis"] for p in long] == [v for *_, v in CATS_PERIODS]
    assert all(p["temp_range_c"][1] - p["temp_range_c"][0] > 14.0 for p in long)
    m = {x["method"]: x for x in rec["methods"]}
    assert m["differential"]["supported"] and not m["tilt"]["supported"] and not m["scalar"]["supported"]
    assert rec["method_auto"] == "differential"
    assert sum("bias and scale factor separated" in d for d in m["differential"]["determines"]) == 3
    assert any("cross-axis constants: undetermined" in d for d in m["differential"]["determines"])
    text = format_summary(s)
    assert "temperature sweep" in text and "calibrate --method auto: differential" in text


def test_cats_static_poses_cover_the_authors_periods(cats):
    """Each of the authors' periods is static in its one orientation for at least 97 % of its length."""
    _, s = cats
    segs = s["static_positions"]
    for start, end, axis in CATS_PERIODS:
        a, b = _ns(start), _ns(end)
        inside = [g for g in segs if g["t_end_ns"] > a and g["t_start_ns"] < b]
        covered = sum(min(g["t_end_ns"], b) - max(g["t_start_ns"], a) for g in inside)
        assert covered / (b - a) > 0.97
        sign, ax = (1.0 if axis[0] == "+" else -1.0), "xyz".index(axis[1])
        assert all(sign * g["direction_g"][ax] > 0.98 for g in inside)


def test_cats_listing_is_its_poses_not_its_segments(cats):
    """The drift cuts the three day-long holds into 184 static segments (227 before stable runs a moment apart
    within the band were one plateau): the text lists a line per pose (each hold's pieces merged, one line per
    pose with its holds), says how many segments that groups, and --json keeps every segment."""
    _, s = cats
    text = format_summary(s)
    n = len(s["static_positions"])
    assert n > 150 and len(text.splitlines()) < 30, len(text.splitlines())
    poses = [ln for ln in text.splitlines() if ln.lstrip().startswith("pose ")]
    assert len(poses) == len(s["recording"]["poses"]) <= 5
    assert sum(int(ln.split(" hold")[0].rsplit(None, 1)[1]) for ln in poses) < 10
    assert f"0 plateaus, {n} static segments (grouped into the poses above; --json lists each)" in text
    assert "1 holds" not in text and "hold(s)" not in text


def test_ferraris_poses_match_the_hand_labels(ferraris):
    """The six hand-marked orientations of imucal's session: one found static segment of the same position lies
    within each labelled range (its middle inside, covering at least 40 % of it), and inspect says tilt."""
    _, s, labels = ferraris
    rec = s["recording"]
    assert rec["temperature"]["kind"] == "constant"
    assert sorted(p["vertical_axis"] for p in rec["poses"]) == sorted(["+x", "-x", "+y", "-y", "+z", "-z"])
    assert rec["method_auto"] == "tilt"
    segs = s["static_positions"]
    for lab in labels["labels"]:
        if not lab["position"].startswith("TP"):
            continue
        a, b = lab["t_start_ns"], lab["t_end_ns"]
        hits = [g for g in segs if a <= (g["t_start_ns"] + g["t_end_ns"]) // 2 <= b]
        assert len(hits) == 1 and hits[0]["position"] == lab["position"], lab
        overlap = min(hits[0]["t_end_ns"], b) - max(hits[0]["t_start_ns"], a)
        assert overlap / (b - a) > 0.4, lab


def test_ferraris_six_position_constants_from_found_poses(ferraris):
    """Six-position constants from the first found segment of each position (the six-orientation part of the
    session; later ones are pauses in the rotations) land near the README's from the hand-marked ranges."""
    _, s, _ = ferraris
    m = {}
    for g in s["static_positions"]:
        m.setdefault(g["position"], np.array(g["mean_v"]))
    k = [(m["TP6"][0] - m["TP5"][0]) / 2, (m["TP4"][1] - m["TP2"][1]) / 2, (m["TP1"][2] - m["TP3"][2]) / 2]
    u0 = [(m["TP6"][0] + m["TP5"][0]) / 2, (m["TP4"][1] + m["TP2"][1]) / 2, (m["TP1"][2] + m["TP3"][2]) / 2]
    assert np.allclose(k, [9.777, 9.834, 10.039], atol=0.01)
    assert np.allclose(u0, [0.551, -0.620, 0.386], atol=0.02)  # m/s^2: 2 mg, the hand's wobble
