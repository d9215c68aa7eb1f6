"""One home per catalogue effect: each effect's module holds its simulation, fit terms, explanation and properties,
and they agree with each other (the fit columns rebuild the simulated signal through the effect's own parameters).
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import pipeline
from pipeline.effects.base import Effect, Shown, SignalContext
from pipeline.effects.catalogue import EFFECTS, effect_class, make_effect
from pipeline.simulate.unit import seed000_unit

PKG = Path(pipeline.__file__).parent


@pytest.fixture(scope="module")
def ctx() -> SignalContext:
    """Two static positions with a move, a ramp from +20 to +50 C and back: every effect changes this signal."""
    t = np.arange(0.0, 4000.0, 1.0)
    temp = 20.0 + 30.0 * np.clip(np.minimum(t - 500, 3500 - t) / 1000.0, 0.0, 1.0)
    a = np.where((t < 2000)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    ramp = np.where(t < 500, 0.0, np.where(t < 2000, 1.0, -1.0))
    return SignalContext(
        t_s=t,
        temp_c=temp,
        a_g=a,
        position_idx=np.where(t < 2000, 0, 5),
        move_start_s=np.array([1990.0]),
        arrive_s=np.array([2000.0]),
        constants=seed000_unit(),
        normal_temp_c=20.0,
        ramp_sign=ramp,
    )


def test_every_effect_lives_in_its_own_module_named_for_its_id():
    assert len(EFFECTS) == 8
    for eid, cls in EFFECTS.items():
        assert cls.__module__ == f"pipeline.effects.{eid}"
        assert (PKG / "effects" / f"{eid}.py").is_file()
        assert cls.where and cls.acts_on in ("output", "temperature", "specific_force")
        if cls.nonlinear is not None:
            assert cls.nonlinear in cls().params() and len(cls.grid) >= 10
            assert all(b > a for a, b in zip(cls.grid, cls.grid[1:]))


def test_no_module_outside_the_package_names_an_effect_id_in_code():
    """Knowledge of one effect is in its module: no special case by effect id elsewhere in the library."""
    offenders = []
    for path in PKG.rglob("*.py"):
        if path.parent.name == "effects":
            continue
        tree = ast.parse(path.read_text())
        docstrings = {
            id(n.body[0].value)
            for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
            and n.body
            and isinstance(n.body[0], ast.Expr)
        }
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and node.value in EFFECTS and id(node) not in docstrings:
                offenders.append(f"{path.relative_to(PKG)}:{node.lineno} {node.value}")
    assert offenders == []


@pytest.mark.parametrize("eid", list(EFFECTS))
def test_fit_columns_rebuild_the_simulated_signal(ctx, eid):
    """cols @ coef equals delta_u_v of the effect rebuilt from fit_parameters(coef): simulation and fit terms are
    one definition (to first order for the face rotations, exactly for the rest)."""
    cls = effect_class(eid)
    value = None if cls.nonlinear is None else float(cls.grid[len(cls.grid) // 2])
    labels, cols = cls.fit_columns(ctx, value)
    if cls.acts_on == "temperature":  # evaluated through the lagged temperature instead of columns
        assert cols == [] and cls.fit_parameters(np.zeros(0), value, labels) == {"tau_s": value}
        return
    assert len(labels) == len(cols) > 0 and all(c.shape == (ctx.t_s.size, 3) for c in cols)
    rng = np.random.default_rng(4)
    coef = rng.normal(0.0, 1e-5, len(cols))
    if eid == "tilt_settling":
        coef = np.abs(coef)
    params = cls.fit_parameters(coef, value, labels)
    rebuilt = make_effect(eid, params)
    expected = sum(c * k for c, k in zip(cols, coef))
    np.testing.assert_allclose(rebuilt.delta_u_v(ctx), expected, rtol=1e-3, atol=1e-12)
    assert np.abs(expected).max() > 0


@pytest.mark.parametrize("eid", list(EFFECTS))
def test_explanations_and_bounds(eid):
    cls = effect_class(eid)
    effect = make_effect(eid)
    params = effect.stored_params()
    text = cls.explain(params, Shown(peak=12.3e-6, axes="x/z", temps=" at -40, +70 C", duration_h=16.5, unit="V"))
    assert text.endswith(".") and len(text) > 60 and f"{eid}:" not in text
    # The catalogue defaults are plausible; the same effect a thousand times larger is not (except the lag, whose
    # time constant is bounded by the search range instead).
    assert cls.implausible(params) is None
    if eid in ("thermal_lag",):
        return
    big = {
        k: (np.asarray(v) * 1e4).tolist() if k not in ("tau_s", "seed", "sigma_deg") else v
        for k, v in params.items()
        if k != "delta_rad"
    }
    if eid == "fixture_face_error":
        big = {"delta_rad": {"TP1": [0.1, 0.0, 0.0]}}
    if eid == "tilt_settling":
        big["f"] = 0.5
    assert cls.implausible(big) is not None


def test_effects_are_effect_subclasses_with_properties():
    for cls in EFFECTS.values():
        assert issubclass(cls, Effect)
    assert {e for e, c in EFFECTS.items() if not c.local} == {"thermal_lag", "tilt_settling"}
    assert {e for e, c in EFFECTS.items() if c.shown_by_refit} == {"temperature_curvature", "time_drift"}
    assert [e for e, c in EFFECTS.items() if c.in_base_from_order] == ["temperature_curvature"]


def test_small_rates_are_not_printed_as_zero():
    """time_drift of a few tens of nV/h (the reviewer saw "+0.0 uV/h"): said in nV/h, to three digits."""
    text = effect_class("time_drift").explain(
        {"r_v_per_h": [3.2e-8, -2.1e-8, 4.0e-9]}, Shown(peak=1.0e-6, axes="x", temps="", duration_h=16.5, unit="V")
    )
    assert "x +32.0, y -21.0, z +4.0 nV/h" in text and "uV/h" not in text
    assert "x +528, y -346, z +66 nV over the 16.5 h run" in text
