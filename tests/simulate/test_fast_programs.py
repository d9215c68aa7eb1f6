"""Programs that spend little chamber time (issue 23): stepped programs written as text (``parse_program``), the fast
program (positions cycled on continuous ramps up and then down, ``Tour``), and ``thermocal simulate`` with them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.positions import MOVING
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.program import (
    TP,
    VP,
    Program,
    Stage,
    Tour,
    fast_program,
    parse_program,
    program_from,
    standard_program,
)
from tests.conftest import run_main

ISSUE = "20@0:TP; -40@0:TP; -10@0:VP; 20@0:TP+VP; 45@0:VP; 70@0:TP; 20@0:TP+VP"


def test_the_issues_stepped_program():
    """Issue 23's program: the standard sequence without soaks, ramps at 2 C/min, 120-s holds: 3.93 h."""
    prog = parse_program(ISSUE, rate_c_per_min=2.0, hold_s=120.0, move_s=20.0)
    tt = prog.timetable()
    expected = [(20.0, TP), (-40.0, TP), (-10.0, VP), (20.0, TP + VP), (45.0, VP), (70.0, TP), (20.0, TP + VP)]
    assert [(h.setpoint_start_c, h.position) for h in tt.holds()] == [(sp, p) for sp, ps in expected for p in ps]
    assert all(h.t_end_s - h.t_start_s == 120.0 for h in tt.holds())
    assert not [s for s in tt.segments if s.kind == "soak"]
    ramps = [s for s in tt.segments if s.kind == "ramp"]
    assert all(
        s.t_end_s - s.t_start_s == pytest.approx(abs(s.setpoint_end_c - s.setpoint_start_c) * 30.0) for s in ramps
    )
    # 220 C of ramps at 2 C/min, 54 holds, 53 moves (the unit starts in TP1)
    assert tt.duration_s == pytest.approx(220 * 30.0 + 54 * 120.0 + 53 * 20.0)
    assert prog.start_position == "TP1" and prog.start_setpoint_c == 20.0 and prog.case_lag_s == 600.0
    # a soak after a ramp, single positions, the default timing (1 C/min, 300-s holds)
    other = parse_program("20:TP1+TP3; -10@15:VP2").timetable()
    assert [(h.setpoint_start_c, h.position) for h in other.holds()] == [(20.0, "TP1"), (20.0, "TP3"), (-10.0, "VP2")]
    assert [s.t_end_s - s.t_start_s for s in other.segments if s.kind in ("soak", "ramp")] == [1800.0, 900.0]


@pytest.mark.parametrize(
    "spec, says",
    [
        ("", "at least one stage"),
        ("20@0", "expected SETPOINT@SOAK_MIN:POSITIONS"),
        ("warm@0:TP", "stage 'warm@0:TP'"),
        ("20@-5:TP", "stage '20@-5:TP'"),
        ("20@0:TP; -40@0:TP7", "unknown position 'TP7'"),
    ],
)
def test_bad_stepped_programs(spec, says):
    with pytest.raises(ValueError, match=says):
        parse_program(spec)


def test_the_fast_program_cycles_positions_on_ramps_up_and_down():
    prog = fast_program()
    tt = prog.timetable()
    assert tt.duration_s == pytest.approx(220 / 1.5 * 60.0 + 2 * 1800.0)  # 3.44 h: 21 % of the standard program
    assert tt.duration_s < standard_program().timetable().duration_s / 4
    assert {s.kind for s in tt.segments} == {"hold", "move"}  # the fixture never stops turning
    holds, moves = tt.holds(), tt.moves()
    names = TP + VP
    # the positions in turn, without a break from one stage to the next
    assert [h.position for h in holds] == [names[k % 12] for k in range(len(holds))]
    assert all(m.t_end_s - m.t_start_s == 20.0 for m in moves)
    lengths = np.array([h.t_end_s - h.t_start_s for h in holds])
    assert np.all(lengths >= 240.0 - 1e-6) and np.all(lengths < 2 * 240.0 + 20.0)
    assert np.sum(lengths > 240.0 + 1e-6) <= len(prog.stages)  # only the last hold of a stage is stretched to its end
    t = np.arange(0.0, tt.duration_s, 30.0)
    sp = tt.setpoint_c(t)
    assert sp.max() == pytest.approx(70.0) and sp.min() == pytest.approx(-40.0)
    # every setpoint between the ends passed heating and cooling, each position held on both legs
    rate = np.diff(sp) / np.diff(t) * 60.0
    assert np.all(np.abs(rate) <= 1.5 + 1e-9) and np.isclose(np.abs(rate), 1.5).mean() > 0.6
    sign = tt.ramp_sign((t[1:] + t[:-1]) / 2)
    full = np.isclose(np.abs(rate), 1.5)  # intervals wholly inside a ramp
    assert np.all(sign[full & (rate > 0)] == 1.0) and np.all(sign[full & (rate < 0)] == -1.0)
    mid = np.array([(h.t_start_s + h.t_end_s) / 2 for h in holds])
    leg = tt.ramp_sign(mid)
    for p in names:
        on = np.array([h.position == p for h in holds])
        assert (on & (leg > 0)).sum() >= 1 and (on & (leg < 0)).sum() >= 1
    # other ends, rate and timing; a tour that only stays
    short = fast_program(low_c=0.0, high_c=40.0, rate_c_per_min=4.0, dwell_s=0.0, hold_s=60.0, move_s=10.0)
    assert short.timetable().duration_s == pytest.approx(80 / 4 * 60.0) and len(short.stages) == 3
    stay = Program("stay", (Stage("x", (Tour(("TP1", "TP2"), duration_s=300.0, hold_s=100.0, move_s=10.0),)),))
    segs = stay.timetable().segments
    assert [(s.kind, s.position) for s in segs] == [("hold", "TP1"), ("move", MOVING), ("hold", "TP2")]
    assert segs[-1].t_end_s == 300.0 and segs[-1].t_end_s - segs[-1].t_start_s == 190.0
    with pytest.raises(ValueError, match="either side"):
        fast_program(low_c=25.0)


def test_hysteresis_follows_the_legs_of_a_fast_program():
    """``thermal_hysteresis`` on a fast program: U0 + h on the heating legs, - h on the cooling leg."""
    prog = fast_program(low_c=0.0, high_c=40.0, rate_c_per_min=4.0, dwell_s=0.0, hold_s=60.0, move_s=10.0)
    h = (50e-6, -40e-6, 30e-6)
    base = simulate(SimConfig(program=prog, rate_hz=1.0, noise_v=0.0, temp_noise_c=0.0))
    hyst = simulate(
        SimConfig(
            program=prog, rate_hz=1.0, noise_v=0.0, temp_noise_c=0.0, effects=[("thermal_hysteresis", {"h_v": h})]
        )
    )
    d = hyst.run.u_v() - base.run.u_v()
    sign = prog.timetable().ramp_sign(hyst.context.t_s)
    assert set(np.unique(sign)) == {-1.0, 1.0}
    np.testing.assert_allclose(d, sign[:, None] * np.array(h), atol=1e-12)


def test_program_from_names_texts_and_timing():
    assert program_from("standard").name == "standard"
    assert program_from(ISSUE, rate_c_per_min=2.0, hold_s=120.0).name == "stepped"
    fast = program_from("fast", rate_c_per_min=1.5, hold_s=90.0, move_s=10.0, soak_s=600.0)
    assert fast.timetable().duration_s == pytest.approx(220 / 1.5 * 60.0 + 2 * 600.0)
    with pytest.raises(ValueError, match="not for 'standard'"):
        program_from("standard", hold_s=60.0)
    with pytest.raises(ValueError, match="unknown chamber program 'nope'"):
        program_from("nope")
    for kw in ({"hold_s": 0.0}, {"rate_c_per_min": float("inf")}, {"move_s": float("nan")}):
        with pytest.raises(ValueError, match=f"{next(iter(kw))} must be a finite number above 0"):
            program_from("fast", **kw)


def test_cli_simulates_a_stepped_and_the_fast_program(tmp_path, monkeypatch, capsys):
    out = tmp_path / "s.mcap"
    code, text, err = run_main(
        monkeypatch,
        capsys,
        "simulate",
        "--out",
        str(out),
        "--program",
        "20@0:TP; 45@0:VP",
        "--ramp-c-per-min",
        "5",
        "--hold-s",
        "30",
        "--move-s",
        "5",
        "--rate-hz",
        "1",
        "--json",
    )
    assert code in (0, None), err
    truth = json.loads((tmp_path / "s.truth.json").read_text())
    assert truth["program"] == "stepped"
    assert [(h["setpoint_c"], h["position"]) for h in truth["holds"]] == [(20.0, p) for p in TP] + [
        (45.0, p) for p in VP
    ]
    assert truth["duration_s"] == pytest.approx(25 / 5 * 60.0 + 12 * 30.0 + 11 * 5.0)
    for args, says in [
        (("--program", "20@0:TQ"), "--program: stage '20@0:TQ': unknown position 'TQ'"),
        (("--program", "short", "--hold-s", "30"), "--program: ramp rate, holds and moves can be chosen"),
        (("--program", "fast", "--drop", "TP1@20"), "--drop: program 'fast' holds no such position"),
        (("--program", "fast", "--ramp-c-per-min", "0"), "--ramp-c-per-min: must be a finite number above 0, got 0"),
        (("--program", "fast", "--ramp-c-per-min", "inf"), "--ramp-c-per-min: must be a finite number above 0"),
        (("--program", "fast", "--hold-s", "-1"), "--hold-s: must be a finite number above 0, got -1"),
        (("--program", "fast", "--move-s", "nan"), "--move-s: must be a finite number, 0 or more, got nan"),
    ]:
        code, text, err = run_main(monkeypatch, capsys, "simulate", "--out", str(tmp_path / "x.mcap"), *args)
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "x.mcap").exists()
