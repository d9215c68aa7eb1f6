"""Mismatches outside the effect catalogue (``pipeline.simulate.disturbances``, ``simulate --disturbance``): what
they add to the signal, that they stay out of the catalogue ids, and the CLI syntax."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.effects.base import SignalContext
from pipeline.effects.catalogue import EFFECTS
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.disturbances import DISTURBANCES, make_disturbance, parse_disturbance_spec
from pipeline.simulate.unit import seed000_unit
from tests.conftest import run_main


def ctx(t_s) -> SignalContext:
    t = np.asarray(t_s, dtype=float)
    a = np.tile([0.0, 0.0, 1.0], (t.size, 1))
    return SignalContext(
        t_s=t,
        temp_c=np.full(t.size, 20.0),
        a_g=a,
        position_idx=np.zeros(t.size, int),
        move_start_s=np.array([]),
        arrive_s=np.array([]),
        constants=seed000_unit(),
    )


def test_disturbances_are_not_catalogue_effects():
    assert set(DISTURBANCES) == {"constants_shift", "bias_step", "bias_random_walk", "periodic"}
    assert not set(DISTURBANCES) & set(EFFECTS)
    with pytest.raises(ValueError, match="unknown disturbance 'thermal_lag'"):
        make_disturbance("thermal_lag")
    with pytest.raises(ValueError, match="unknown effect 'bias_step'"):
        from pipeline.effects.catalogue import make_effect

        make_effect("bias_step")


def test_what_each_disturbance_adds():
    c = ctx(np.arange(0.0, 7200.0, 10.0))
    step = make_disturbance("bias_step", {"t_h": 1.0, "step_v": [1e-5, -2e-5, 0.0]}).delta_u_v(c)
    np.testing.assert_array_equal(step[c.t_s < 3600], 0.0)
    np.testing.assert_allclose(step[c.t_s >= 3600], [[1e-5, -2e-5, 0.0]] * int((c.t_s >= 3600).sum()))
    per = make_disturbance("periodic", {"amp_v": [5e-6, 0.0, 0.0], "period_s": 600.0}).delta_u_v(c)
    np.testing.assert_allclose(per[:, 0], 5e-6 * np.sin(2 * np.pi * c.t_s / 600.0), atol=1e-15)
    walk = make_disturbance("bias_random_walk", {"sigma_v_per_sqrt_h": 1e-5, "seed": 3})
    w1, w2 = walk.delta_u_v(c), walk.delta_u_v(c)
    np.testing.assert_array_equal(w1, w2)  # a function of the seed
    assert w1[0].tolist() == [0.0, 0.0, 0.0] and np.abs(w1).max() > 1e-6
    kzz = seed000_unit().constants_at(np.array([20.0]))[0][0, 2, 2]
    shift = make_disturbance("constants_shift", {"du0_v": [1e-5, 0.0, 0.0], "dgain_rel": [0.0, 0.0, 1e-3]})
    np.testing.assert_allclose(shift.delta_u_v(c)[0], [1e-5, 0.0, kzz * 1e-3])
    # gradually: rates per hour since the start of the recording, on top of the shift at the start
    drift = make_disturbance(
        "constants_shift",
        {"du0_v": [1e-5, 0.0, 0.0], "du0_rate_v_per_h": [0.0, 2e-6, 0.0], "dgain_rate_rel_per_h": [0.0, 0.0, 1e-4]},
    ).delta_u_v(c)
    t_h = c.t_s / 3600.0
    np.testing.assert_allclose(
        drift, np.stack([np.full(t_h.size, 1e-5), 2e-6 * t_h, kzz * 1e-4 * t_h], axis=1), rtol=1e-12, atol=1e-18
    )


def test_the_simulator_records_them_apart_from_the_catalogue_effects(tmp_path, monkeypatch, capsys):
    res = simulate(
        SimConfig(
            rate_hz=0.5,
            program="short",
            noise_v=0.0,
            temp_noise_c=0.0,
            disturbances=[("bias_step", {"t_h": 1.0, "step_v": [2e-5, 0.0, 0.0]})],
        )
    )
    clean = simulate(SimConfig(rate_hz=0.5, program="short", noise_v=0.0, temp_noise_c=0.0))
    d = res.run.voltmeter["ux"].to_numpy() - clean.run.voltmeter["ux"].to_numpy()
    t = res.context.t_s
    assert np.allclose(d[t >= 3600], 2e-5) and np.allclose(d[t < 3600], 0.0)
    assert res.truth["effects"] == [] and res.truth["disturbances"][0]["id"] == "bias_step"
    assert parse_disturbance_spec("periodic:period_s=900,amp_v_y=0")[1]["amp_v"] == [20e-6, 0.0, 0.0]
    assert parse_disturbance_spec("constants_shift:du0_v=0,du0_rate_v_per_h_x=1e-6")[1]["du0_rate_v_per_h"] == [
        1e-6,
        0.0,
        0.0,
    ]
    code, out, err = run_main(
        monkeypatch,
        capsys,
        "simulate",
        "--out",
        str(tmp_path / "r.mcap"),
        "--program",
        "short",
        "--rate-hz",
        "0.5",
        "--disturbance",
        "bias_step:t_h=1,step_v=1e-5",
        "--json",
    )
    assert code in (0, None), err
    truth = json.loads((tmp_path / "r.truth.json").read_text())
    assert truth["disturbances"] == [{"id": "bias_step", "params": {"t_h": 1.0, "step_v": [1e-5, 1e-5, 1e-5]}}]
    code, out, err = run_main(
        monkeypatch, capsys, "simulate", "--out", str(tmp_path / "s.mcap"), "--disturbance", "bias_jump:t_h=1"
    )
    assert code == 2 and "unknown disturbance 'bias_jump'" in err and len(err.strip().splitlines()) == 1
