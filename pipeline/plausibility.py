"""Plausibility of fitted constants: are they what a unit of this type can have, or a units or sign mistake?

A calibration fits whatever the numbers say: voltages logged in mV give gains of about -550 V/g, temperatures logged
in kelvin give plateaus at 233..343 "C", a reversed axis gives a gain of the wrong sign, and the VP verification
(which uses the same wrong numbers) still passes. These checks compare the fitted constants with the run's
``nominal_gain_v_per_g`` (docs/log-format.md; signed) and with the unit type's ranges (:class:`UnitTypeRanges`), and say
what looks wrong, one line per finding. A calibration with any finding has status ``fail``
(:func:`judged_status`), never ``pass``.

Units: K in V/g, U0 in V, temperatures in C; cross-axis as the ratio |K_ij| / |K_ii| (1), offsets as |U0_i| / |K_ii|
(g).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["IMPLAUSIBLE", "UnitTypeRanges", "assess", "check_constants", "check_fit", "judged_status", "mirrored_axis"]

AXES = "xyz"
#: The prefix of a finding in a calibration's warnings (a warning that makes the status ``fail``).
IMPLAUSIBLE = "implausible: "
KELVIN_OFFSET_C = 273.15


@dataclass(frozen=True)
class UnitTypeRanges:
    """What a navigational accelerometer unit of seed 000's type can have (defaults about 3x the spread seen).

    ``gain_factor``: each |K_ii| within nominal / factor .. nominal * factor (1) when the run gives a nominal gain;
    ``gain_v_per_g``: the |K_ii| range (V/g) otherwise; ``max_cross_axis``: |K_ij| / |K_ii| (1, seed 000: 0.03);
    ``max_offset_g``: |U0_i| / |K_ii| (g, seed 000: 0.02); ``temp_c``: calibration temperatures (C)."""

    gain_factor: float = 2.0
    gain_v_per_g: tuple[float, float] = (0.05, 5.0)
    max_cross_axis: float = 0.1
    max_offset_g: float = 0.1
    temp_c: tuple[float, float] = (-60.0, 150.0)


def check_constants(
    temps_c, K, U0, nominal_gain_v_per_g: float | None = None, ranges: UnitTypeRanges = UnitTypeRanges()
) -> list[str]:
    """What looks wrong with per-plateau constants: ``temps_c`` (n,) C, ``K`` (n, 3, 3) V/g, ``U0`` (n, 3) V.
    Returns one line per finding (empty: plausible)."""
    temps = np.asarray(temps_c, dtype=float).reshape(-1)
    K = np.asarray(K, dtype=float).reshape(-1, 3, 3)
    U0 = np.asarray(U0, dtype=float).reshape(-1, 3)
    out: list[str] = []
    if temps.size:
        lo, hi = float(np.nanmin(temps)), float(np.nanmax(temps))
        if lo < ranges.temp_c[0] or hi > ranges.temp_c[1]:
            msg = (
                f"calibration temperatures {lo:.1f}..{hi:.1f} C lie outside the unit type's "
                f"{ranges.temp_c[0]:+.0f}..{ranges.temp_c[1]:+.0f} C"
            )
            k_lo, k_hi = lo - KELVIN_OFFSET_C, hi - KELVIN_OFFSET_C
            if ranges.temp_c[0] <= k_lo and k_hi <= ranges.temp_c[1]:
                msg += f": AU temperature recorded in kelvin? (as C: {k_lo:.1f}..{k_hi:.1f})"
            out.append(msg)
    if not K.size:
        return out
    gains = np.abs(np.diagonal(K, axis1=1, axis2=2))  # (n, 3)
    gain = np.nanmedian(gains, axis=0)  # (3,)
    names = ", ".join(f"|K_{a}{a}|" for a in AXES)
    values = ", ".join(f"{g:.4g}" for g in gain)
    if nominal_gain_v_per_g is not None and nominal_gain_v_per_g != 0:
        nominal = abs(float(nominal_gain_v_per_g))
        ratio = gain / nominal
        if np.any(ratio > ranges.gain_factor) or np.any(ratio < 1 / ranges.gain_factor):
            r = float(np.nanmedian(ratio))
            out.append(
                f"gains {names} = {values} V/g are not within a factor {ranges.gain_factor:g} of the nominal "
                f"{nominal:g} V/g (about {_times(r)}){_unit_hint(r, 'voltages')}"
            )
        sign = np.sign(float(nominal_gain_v_per_g))
        diag = np.nanmedian(np.diagonal(K, axis1=1, axis2=2), axis=0)
        for i, a in enumerate(AXES):
            if np.sign(diag[i]) == -sign:
                out.append(
                    f"gain K_{a}{a} = {diag[i]:+.4g} V/g has the opposite sign of the nominal "
                    f"{float(nominal_gain_v_per_g):+g} V/g: axis {a} reversed (wiring, mounting or position "
                    "labels)?"
                )
    else:
        g_lo, g_hi = ranges.gain_v_per_g
        if np.any(gain < g_lo) or np.any(gain > g_hi):
            mid = float(np.sqrt(g_lo * g_hi))
            r = float(np.nanmedian(gain)) / mid
            out.append(
                f"gains {names} = {values} V/g lie outside the unit type's {g_lo:g}..{g_hi:g} V/g"
                f"{_unit_hint(r, 'voltages')}"
            )
    safe = np.where(gains > 0, gains, np.nan)
    cross = np.abs(K) / safe[:, :, None]  # row i divided by |K_ii|
    for i, a in enumerate(AXES):
        for j, b in enumerate(AXES):
            if i != j and np.nanmax(cross[:, i, j]) > ranges.max_cross_axis:
                out.append(
                    f"cross-axis sensitivity |K_{a}{b}| / |K_{a}{a}| = {np.nanmax(cross[:, i, j]):.3g} exceeds "
                    f"the unit type's {ranges.max_cross_axis:g}: misaligned mounting or mislabelled "
                    "positions?"
                )
    offset_g = np.abs(U0) / safe  # (n, 3)
    for i, a in enumerate(AXES):
        worst = float(np.nanmax(offset_g[:, i])) if np.any(np.isfinite(offset_g[:, i])) else 0.0
        if worst > ranges.max_offset_g:
            out.append(
                f"zero-g offset U0_{a} is {worst:.3g} g (|U0_{a}| / |K_{a}{a}|), beyond the unit type's "
                f"{ranges.max_offset_g:g} g"
            )
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(U0)):
        out.append("fitted constants are not all finite")
    return out


def _times(r: float) -> str:
    return f"{r:.3g}x" if r >= 1 else f"1/{1 / r:.3g}x"


def _unit_hint(r: float, what: str) -> str:
    """A guess at the units mistake behind a scale ratio ``r`` (fitted / expected)."""
    if 300 <= r <= 3000:
        return f": {what} recorded in mV?"
    if 1 / 3000 <= r <= 1 / 300:
        return f": {what} recorded in kV (or mV read as V)?"
    return ""


def check_fit(fit, nominal_gain_v_per_g: float | None = None, ranges: UnitTypeRanges = UnitTypeRanges()) -> list[str]:
    """:func:`check_constants` of a calibration recipe's ``UnitFit``: its per-plateau constants, or (a method
    without plateaus, e.g. the differential one) its thermal model at the ends of its valid range and at T0."""
    plateaus = list(getattr(fit, "per_plateau", []) or [])
    if plateaus:
        return check_constants(
            [p.temp_c for p in plateaus],
            [p.K for p in plateaus],
            [p.U0 for p in plateaus],
            nominal_gain_v_per_g,
            ranges,
        )
    model = getattr(fit, "model", None)
    if model is None or not hasattr(model, "constants_at"):
        return []
    temps = [float(fit.normal_temp_c), *(getattr(fit, "valid_temp_c", None) or ())]
    K, U0 = model.constants_at(np.asarray(temps, dtype=float))
    return check_constants(temps, K, U0, nominal_gain_v_per_g, ranges)


def mirrored_axis(labelled: list[tuple[str, str]]) -> str | None:
    """A reversed axis seen in the naming of static positions: ``labelled`` holds (fixture log's position, position
    the signal says) of the segments where the two disagree. When every such disagreement is the same single axis
    with its sign flipped (TP2 <-> TP4, VP2 <-> VP5, ...), at least twice, the finding (one line); else None."""
    from pipeline.positions import ALL_POSITIONS

    hits: dict[int, set[tuple[str, str]]] = {}
    for logged, signal in labelled:
        if logged not in ALL_POSITIONS or signal not in ALL_POSITIONS:
            return None
        a, b = np.asarray(ALL_POSITIONS[logged], float), np.asarray(ALL_POSITIONS[signal], float)
        flipped = np.isclose(a, -b) & ~np.isclose(a, 0.0)
        if flipped.sum() != 1 or not np.all(flipped | np.isclose(a, b)):
            return None
        hits.setdefault(int(np.argmax(flipped)), set()).add((logged, signal))
    if len(hits) != 1:
        return None
    ((axis, pairs),) = hits.items()
    if sum(1 for _ in labelled) < 2:
        return None
    ax = AXES[axis]
    shown = ", ".join(f"{x}->{y}" for x, y in sorted(pairs)[:4])
    return (
        f"every position the fixture log and the signal disagree on ({len(labelled)} segments: {shown}) differs "
        f"by the sign of {ax}: axis {ax} reversed (wiring or mounting), or a fixture log mirrored in {ax}?"
    )


def assess(
    fit,
    status: str,
    nominal_gain_v_per_g: float | None = None,
    run_warnings: Sequence[str] = (),
    ranges: UnitTypeRanges = UnitTypeRanges(),
) -> tuple[str, list[str]]:
    """The calibration's status after the plausibility checks, and every finding (``implausible: ...`` lines: the
    fit's, and those already among ``run_warnings`` from observing the runs): called by every recipe right after
    the VP verification."""
    problems = [w for w in run_warnings if w.startswith(IMPLAUSIBLE)]
    problems += [f"{IMPLAUSIBLE}{p}" for p in check_fit(fit, nominal_gain_v_per_g, ranges)]
    return judged_status(status, problems), problems


def judged_status(status: str, problems: list[str]) -> str:
    """``fail`` when the constants are implausible, whatever the VP verification said; else ``status``."""
    return "fail" if problems else status
