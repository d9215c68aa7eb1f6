"""Plausibility of a run's metadata and of fitted constants: are they what a chamber run and a unit of this type
can have, or a units or sign mistake?

A calibration fits whatever the numbers say: voltages logged in mV give gains of about -550 V/g, temperatures logged
in kelvin give plateaus at 233..343 "C", a reversed axis gives a gain of the wrong sign, and the VP verification
(which uses the same wrong numbers) still passes. These checks compare the fitted constants with the run's
``nominal_gain_v_per_g`` (docs/log-format.md; signed) and with the unit type's ranges (:class:`UnitTypeRanges`), and say
what looks wrong, one line per finding. A calibration with any finding has status ``fail``
(:func:`judged_status`), never ``pass``.

The run's metadata numbers are checked as the run is read (:func:`check_run_metadata`, called by
:func:`pipeline.io.checks.assemble_run`, so every reader, inspect and every method see the same findings in the run's
warnings): local gravity within :data:`G_LOCAL_MPS2` (9.7..9.9 m/s^2: a stand on Earth) unless the run says why in
``g_local_reason``; T0 within a chamber's reach (:data:`CHAMBER_RANGE_C`); the streams' sample rates
within :data:`RATES_HZ`; a nonzero nominal gain. A finding starts with :data:`IMPLAUSIBLE` and makes a calibration of
the run ``fail`` (:func:`assess`), never ``pass``: a gravity of 980.665 (cm/s^2) or -9.8 would scale or flip every
export. T0 against the temperatures the calibration observed (all its runs: :data:`T0_MARGIN_C`) is judged with the
constants (:func:`assess`).

Units: K in V/g, U0 in V, temperatures in C; cross-axis as the ratio |K_ij| / |K_ii| (1), offsets as |U0_i| / |K_ii|
(g).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "IMPLAUSIBLE",
    "UnitTypeRanges",
    "assess",
    "check_constants",
    "check_fit",
    "check_run_metadata",
    "check_t0_span",
    "judged_status",
    "mirrored_axis",
]

AXES = "xyz"
#: The prefix of a finding in a calibration's warnings (a warning that makes the status ``fail``).
IMPLAUSIBLE = "implausible: "
KELVIN_OFFSET_C = 273.15
#: Local gravity of a stand on Earth, m/s^2 (9.78 at the equator .. 9.83 at the poles, less on mountains).
G_LOCAL_MPS2 = (9.7, 9.9)
#: The metadata key a run uses to say why its ``g_local_mps2`` lies outside :data:`G_LOCAL_MPS2` (a centrifuge, ...).
G_LOCAL_REASON_KEY = "g_local_reason"
#: T0 may lie this far outside the AU temperatures a calibration's runs hold (C): beyond, the constants at T0 are
#: extrapolated (a units mistake, K or F, or a typo).
T0_MARGIN_C = 10.0
#: The temperatures a thermal chamber reaches (C): a run's T0 outside is a units mistake whatever the run holds (one
#: run of a calibration may hold only part of the range: T0 against the temperatures is judged over all of them).
CHAMBER_RANGE_C = (-80.0, 200.0)
#: Sample rates a chamber logger can have, Hz, by stream (a median interval outside: timestamps in other units).
RATES_HZ = {"voltmeter": (1e-3, 1e6), "au_temperature": (1e-4, 1e5), "chamber": (1e-4, 1e5)}


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


def check_run_metadata(meta, frames: dict) -> list[str]:
    """Findings (``implausible: ...`` lines, empty: plausible) about every number of a run's metadata ``meta``
    (:class:`pipeline.run.RunMeta`) given its stream tables ``frames`` (name -> polars table, as read): gravity,
    T0 against the AU temperatures recorded, the streams' sample rates, the nominal gain."""
    out: list[str] = []
    g = float(meta.g_local_mps2)
    lo, hi = G_LOCAL_MPS2
    if not lo <= g <= hi and not str(meta.extra.get(G_LOCAL_REASON_KEY, "")).strip():
        hint = ""
        if g < 0:
            hint = ": negative (a sign mistake would flip every exported offset)"
        elif lo <= g / 100 <= hi:
            hint = ": in cm/s^2 (Gal)?"
        elif abs(g - 1.0) < 0.05:
            hint = ": in g rather than m/s^2?"
        elif g == 0:
            hint = ": zero"
        out.append(
            f"g_local_mps2 = {g:g} m/s^2 is not a local gravity on Earth ({lo:g}..{hi:g} m/s^2){hint}; set "
            f"metadata '{G_LOCAL_REASON_KEY}' to say why if it is right"
        )
    t0 = float(meta.normal_temp_c)
    if not CHAMBER_RANGE_C[0] <= t0 <= CHAMBER_RANGE_C[1]:
        out.append(
            f"normal_temp_c (T0) = {t0:g} C lies outside the temperatures a chamber reaches "
            f"({CHAMBER_RANGE_C[0]:g}..{CHAMBER_RANGE_C[1]:g} C): T0 in kelvin?"
        )
    for stream, (rlo, rhi) in RATES_HZ.items():
        df = frames.get(stream)
        if df is None or df.height < 2:
            continue
        tn = df["t_ns"].to_numpy()
        k = np.arange(0, tn.size - 1, max(1, (tn.size - 1) // 100_000))
        med = float(np.median(tn[k + 1] - tn[k]))  # from at most ~100 000 intervals
        if med <= 0:
            continue
        rate = 1e9 / med
        if not rlo <= rate <= rhi:
            out.append(
                f"{stream} is sampled at {rate:.3g} Hz (median interval {med / 1e9:.3g} s), outside the "
                f"{rlo:g}..{rhi:g} Hz a chamber logger records: t_ns not in nanoseconds?"
            )
    gain = meta.nominal_gain_v_per_g
    if gain is not None and not 1e-4 <= abs(float(gain)) <= 1e4:
        out.append(f"nominal_gain_v_per_g = {float(gain):g} V/g is no accelerometer's gain (1e-4..1e4 V/g in size)")
    return [f"{IMPLAUSIBLE}{line}" for line in out]


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


def check_t0_span(normal_temp_c: float, temps_c: Sequence[float]) -> list[str]:
    """A finding when T0 lies more than :data:`T0_MARGIN_C` outside the AU temperatures ``temps_c`` (C) the
    calibration observed (all its runs together): its constants at T0 would be extrapolated."""
    t = np.asarray(temps_c, dtype=float)
    t = t[np.isfinite(t)]
    if not t.size:
        return []
    tmin, tmax, t0 = float(t.min()), float(t.max()), float(normal_temp_c)
    if tmin - T0_MARGIN_C <= t0 <= tmax + T0_MARGIN_C:
        return []
    return [
        f"normal_temp_c (T0) = {t0:g} C lies outside the AU temperatures the runs hold ({tmin:.1f}..{tmax:.1f} C, "
        f"with {T0_MARGIN_C:g} C to spare): the constants at T0 would be extrapolated (T0 in Fahrenheit, a typo?)"
    ]


def assess(
    fit,
    status: str,
    nominal_gain_v_per_g: float | None = None,
    run_warnings: Sequence[str] = (),
    ranges: UnitTypeRanges = UnitTypeRanges(),
    temps_c: Sequence[float] = (),
) -> tuple[str, list[str]]:
    """The calibration's status after the plausibility checks, and every finding (``implausible: ...`` lines: the
    fit's, those already among ``run_warnings`` from observing the runs, and T0 against ``temps_c``, the AU
    temperatures (C) of every observation: :func:`check_t0_span`): called by every recipe right after the VP
    verification."""
    problems = [w for w in run_warnings if w.startswith(IMPLAUSIBLE)]
    problems += [f"{IMPLAUSIBLE}{p}" for p in check_fit(fit, nominal_gain_v_per_g, ranges)]
    normal_temp_c = getattr(fit, "normal_temp_c", None)
    if normal_temp_c is not None:
        problems += [f"{IMPLAUSIBLE}{p}" for p in check_t0_span(normal_temp_c, temps_c)]
    return judged_status(status, problems), problems


def judged_status(status: str, problems: list[str]) -> str:
    """``fail`` when the constants are implausible, whatever the VP verification said; else ``status``."""
    return "fail" if problems else status
