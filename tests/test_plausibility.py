"""Plausibility of fitted constants: mV, kelvin and sign mistakes are named, never a pass."""

from __future__ import annotations

import pytest

from pipeline.plausibility import UnitTypeRanges, check_constants, judged_status, mirrored_axis


@pytest.fixture(scope="module")
def table(seed000_constants):
    return seed000_constants  # T (C), K (V/g), U0 (V) of seed 000's Tables 1-2


def test_seed000_unit_is_plausible(table):
    T, K, U0 = table
    assert check_constants(T, K, U0, nominal_gain_v_per_g=-0.55) == []
    assert check_constants(T, K, U0) == []
    assert judged_status("pass", []) == "pass"


def test_voltages_in_millivolts(table):
    T, K, U0 = table
    for nominal in (-0.55, None):
        [msg] = check_constants(T, K * 1000, U0 * 1000, nominal_gain_v_per_g=nominal)
        assert "voltages recorded in mV?" in msg and "550.7, 548.5, 548.6 V/g" in msg, msg
    assert judged_status("pass", [msg]) == "fail"


def test_temperatures_in_kelvin(table):
    T, K, U0 = table
    [msg] = check_constants(T + 273.15, K, U0, nominal_gain_v_per_g=-0.55)
    assert "233.1..343.1 C" in msg and "kelvin" in msg and "-40.0..70.0" in msg, msg


def test_reversed_axis(table):
    T, K, U0 = table
    K = K.copy()
    K[:, 1, :] *= -1  # the y output wired the other way round
    [msg] = check_constants(T, K, U0, nominal_gain_v_per_g=-0.55)
    assert "K_yy = +0.5485 V/g has the opposite sign" in msg and "axis y reversed" in msg, msg
    assert check_constants(T, K, U0) == []  # without a nominal gain the sign cannot be judged


def test_cross_axis_offsets_and_gain_range(table):
    T, K, U0 = table
    K2, U2 = K.copy(), U0.copy()
    K2[:, 0, 2] = 0.2  # 0.36 of the gain
    U2[:, 2] = 0.3  # 0.55 g
    msgs = check_constants(T, K2, U2, nominal_gain_v_per_g=-0.55)
    assert any("|K_xz| / |K_xx| = 0.363" in m for m in msgs), msgs
    assert any("U0_z is 0.547 g" in m for m in msgs), msgs
    [gain] = check_constants(T, K * 3, U0 * 3, nominal_gain_v_per_g=-0.55)
    assert "factor 2" in gain and "about 2.99x" in gain and "mV" not in gain
    assert check_constants(T, K * 3, U0 * 3, -0.55, UnitTypeRanges(gain_factor=4)) == []


def test_mirrored_axis_from_label_conflicts():
    msg = mirrored_axis([("TP2", "TP4"), ("TP4", "TP2"), ("VP2", "VP5")])
    assert "differs by the sign of y" in msg and "axis y reversed" in msg and "3 segments" in msg, msg
    assert mirrored_axis([("TP2", "TP4")]) is None  # once is not a pattern
    assert mirrored_axis([("TP2", "TP4"), ("TP1", "TP3")]) is None  # not one axis
    assert mirrored_axis([("TP2", "TP4"), ("TP1", "TP5")]) is None  # not a mirror
    assert mirrored_axis([]) is None
