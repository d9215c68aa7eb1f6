"""Only visits of the verification positions are verification results: the position the unit held through a ramp
and a soak (the first segment of a plateau, where the previous plateau ended) is not one (issue 16, item 7)."""

from __future__ import annotations

import numpy as np

from pipeline.calibrate.observations import Observation, soak_holds
from pipeline.calibrate.tilt import calibrate
from pipeline.simulate.chamber import SimConfig, simulate


def _obs(plateau, position, t, run="r"):
    return Observation(
        run_id=run,
        plateau=plateau,
        position=position,
        u_v=(0.0, 0.0, -0.55),
        std_v=(1e-6,) * 3,
        count=100,
        temp_c=20.0,
        t_start_ns=t,
        t_end_ns=t + 1,
    )


def test_the_held_position_is_a_soak_hold():
    seq = [
        _obs(0, "VP5", 0),
        _obs(0, "VP6", 1),
        _obs(None, "VP6", 2),
        _obs(1, "VP6", 3),
        _obs(1, "VP1", 4),
        _obs(1, "VP6", 5),
        _obs(2, "VP6", 6),
        _obs(0, "VP6", 0, run="other"),
    ]
    held = soak_holds(seq)
    assert held == {id(seq[3]), id(seq[6])}  # carried onto plateau 1 (through a ramp segment) and onto plateau 2


def test_simulated_standard_run_verifies_only_the_vp_sequences():
    """The short program ends plateaus in VP6 and carries it onto the next: no soak hold among the rows; every
    visit is a whole VP1..VP6 sequence."""
    run = simulate(SimConfig(program="short", rate_hz=2.0, seed=4)).run
    res = calibrate([run])
    rows = res.rows
    assert rows and len(rows) % 6 == 0
    names = [r.position for r in sorted(rows, key=lambda r: r.t_start_ns)]
    assert names == [f"VP{k}" for k in range(1, 7)] * (len(rows) // 6)
    temps = np.array([r.temp_c for r in rows])
    assert np.all(np.abs(temps - np.round(temps / 5) * 5) < 0.5)  # on the plateaus' nominal temperatures
