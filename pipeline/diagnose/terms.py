"""The effect catalogue as fit terms for ``diagnose``: linear columns, a nonlinear time constant, plausibility.

Every candidate's columns are the simulator's own physics: :meth:`pipeline.effects.Effect.delta_u_v` evaluated on
the recording's :class:`~pipeline.effects.SignalContext` with unit parameters (one column per linear parameter; a
small rotation, scaled back, for the fixture face errors). ``thermal_lag`` has no column: it moves the temperature
at which the base model is evaluated to the lagged element temperature (the simulator's first-order lag, applied
to the whole thermosensor series: :meth:`pipeline.diagnose.signal.StaticRecord.element_temperature_c`).

A :class:`Term` knows its effect id, the grid of its nonlinear parameter (a time constant in s) if any, how to
build its columns, how to turn fitted coefficients into the catalogue's parameters (so that
:func:`pipeline.effects.make_effect` rebuilds the fitted effect), and which fitted values are physically plausible.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from pipeline.effects import SignalContext, make_effect
from pipeline.positions import ALL_POSITIONS, POSITION_NAMES

#: rotation used to linearise the fixture face error, rad (far below any real face error)
_FACE_EPS_RAD = 1e-6


@dataclass(frozen=True)
class Term:
    """One catalogue effect as fit terms.

    ``grid`` holds the candidate values of the nonlinear parameter ``nonlinear`` (None: purely linear);
    ``columns(ctx, value)`` returns (labels, list of (n, 3) arrays); ``parameters(coef, value, labels)`` the
    catalogue parameters; ``implausible(params)`` a reason or None; ``bounds`` the plausible range of the nonlinear
    parameter (values at the edge of the grid are not accepted).
    """

    id: str
    nonlinear: str | None
    grid: tuple[float, ...]
    columns: Callable[[SignalContext, float | None], tuple[list[str], list[np.ndarray]]]
    parameters: Callable[[np.ndarray, float | None, list[str]], dict[str, Any]]
    implausible: Callable[[dict[str, Any]], str | None]


def _log_grid(lo: float, hi: float, n: int) -> tuple[float, ...]:
    return tuple(float(x) for x in np.geomspace(lo, hi, n))


def _axis_columns(effect_id: str, name: str, ctx: SignalContext, **fixed) -> list[np.ndarray]:
    """delta_u_v of ``effect_id`` with its 3-vector parameter ``name`` set to each unit vector in turn."""
    return [make_effect(effect_id, {name: list(e), **fixed}).delta_u_v(ctx) for e in np.eye(3)]


def _vector_params(name: str, **extra) -> Callable:
    def params(coef, value, labels):
        out = {name: [float(c) for c in coef[:3]]}
        out.update(extra)
        if value is not None:
            out["tau_s"] = float(value)
        return out
    return params


def _too_big(params: dict, name: str, limit: float, unit: str) -> str | None:
    v = np.max(np.abs(params[name]))
    return f"{name} {v:.3g} {unit} is beyond {limit:.3g} {unit}" if v > limit else None


# ---------------------------------------------------------------------------------------------------- the terms


def _lag_columns(ctx, value):
    return [], []


def _lag_params(coef, value, labels):
    return {"tau_s": float(value)}


def _hyst_columns(ctx, value):
    return ["h_x", "h_y", "h_z"], _axis_columns("thermal_hysteresis", "h_v", ctx)


def _drift_columns(ctx, value):
    return ["r_x", "r_y", "r_z"], _axis_columns("time_drift", "r_v_per_h", ctx)


def _warmup_columns(ctx, value):
    return ["a_x", "a_y", "a_z"], _axis_columns("warmup_transient", "a_v", ctx, tau_s=value)


def _warmup_params(coef, value, labels):
    return {"a_v": [float(c) for c in coef[:3]], "tau_s": float(value)}


def _curv_columns(ctx, value):
    cols = (_axis_columns("temperature_curvature", "c_v_per_c3", ctx, c_rel_per_c3=0.0)
            + _axis_columns("temperature_curvature", "c_rel_per_c3", ctx, c_v_per_c3=0.0))
    return ["c_x", "c_y", "c_z", "crel_x", "crel_y", "crel_z"], cols


def _curv_params(coef, value, labels):
    return {"c_v_per_c3": [float(c) for c in coef[:3]], "c_rel_per_c3": [float(c) for c in coef[3:6]]}


def _curv_implausible(p):
    # a cubic term beyond a few mV (or a few per mille of scale) at 50 C from T0 is not a small left-out term
    return (_too_big(p, "c_v_per_c3", 5e-3 / 50 ** 3, "V/C^3")
            or _too_big(p, "c_rel_per_c3", 5e-3 / 50 ** 3, "1/C^3"))


def _k2_columns(ctx, value):
    return ["k2_x", "k2_y", "k2_z"], _axis_columns("scale_nonlinearity", "k2_v_per_g2", ctx)


def perpendicular_basis(a: np.ndarray) -> np.ndarray:
    """Two unit vectors (2, 3) perpendicular to ``a`` (rotations about ``a`` leave a position's vector alone)."""
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)
    _, _, vt = np.linalg.svd(a[None, :])
    return vt[1:]


def _face_columns(ctx, value):
    present = sorted(set(int(i) for i in np.unique(ctx.position_idx) if i >= 0))
    labels, cols = [], []
    for i in present:
        name = POSITION_NAMES[i]
        for k, b in enumerate(perpendicular_basis(np.asarray(ALL_POSITIONS[name]))):
            eff = make_effect("fixture_face_error", {"delta_rad": {name: list(_FACE_EPS_RAD * b)}})
            labels.append(f"{name}:{k}")
            cols.append(eff.delta_u_v(ctx) / _FACE_EPS_RAD)
    return labels, cols


def _face_params(coef, value, labels):
    delta: dict[str, np.ndarray] = {}
    for c, lab in zip(coef, labels):
        name, k = lab.split(":")
        b = perpendicular_basis(np.asarray(ALL_POSITIONS[name]))[int(k)]
        delta[name] = delta.get(name, np.zeros(3)) + float(c) * b
    return {"delta_rad": {p: [float(x) for x in v] for p, v in sorted(delta.items())}}


def _face_implausible(p):
    worst = max((np.linalg.norm(v) for v in p["delta_rad"].values()), default=0.0)
    return f"face error {np.degrees(worst):.3g} deg is beyond 1 deg" if worst > np.radians(1.0) else None


def _tilt_columns(ctx, value):
    return ["f"], [make_effect("tilt_settling", {"f": 1.0, "tau_s": value}).delta_u_v(ctx)]


def _tilt_params(coef, value, labels):
    return {"f": float(coef[0]), "tau_s": float(value)}


def _tilt_implausible(p):
    if p["f"] <= 0:
        return f"f = {p['f']:.3g} < 0: the reading overshoots instead of creeping"
    return "f beyond 1 %" if p["f"] > 0.01 else None


def _none(p):
    return None


TERMS: dict[str, Term] = {t.id: t for t in (
    Term("thermal_lag", "tau_s", _log_grid(0.5, 3600.0, 20), _lag_columns, _lag_params, _none),
    Term("thermal_hysteresis", None, (), _hyst_columns, _vector_params("h_v"),
         lambda p: _too_big(p, "h_v", 5e-3, "V")),
    Term("time_drift", None, (), _drift_columns, _vector_params("r_v_per_h"),
         lambda p: _too_big(p, "r_v_per_h", 1e-3, "V/h")),
    Term("warmup_transient", "tau_s", _log_grid(10.0, 3 * 3600.0, 18), _warmup_columns, _warmup_params,
         lambda p: _too_big(p, "a_v", 0.02, "V")),
    Term("temperature_curvature", None, (), _curv_columns, _curv_params, _curv_implausible),
    Term("scale_nonlinearity", None, (), _k2_columns, _vector_params("k2_v_per_g2"),
         lambda p: _too_big(p, "k2_v_per_g2", 5e-3, "V/g^2")),
    Term("fixture_face_error", None, (), _face_columns, _face_params, _face_implausible),
    Term("tilt_settling", "tau_s", _log_grid(1.0, 900.0, 18), _tilt_columns, _tilt_params, _tilt_implausible),
)}

__all__ = ["Term", "TERMS", "perpendicular_basis"]
