"""The report of a diagnosis (:mod:`pipeline.diagnose.diagnosis` runs its steps): docs/contract.md's ``diagnose --json``
object with its extra keys, the passport with the extended model, and the block series behind the figure.

- :class:`DiagnoseSettings`: block length, where a finding shows (thresholds in block sigmas), the selection's
  settings; :class:`Diagnosis`: the result; :class:`Outcome`: what the steps found, handed to :func:`report`.
- :func:`report`: the findings (one per accepted catalogue effect, the constants' shift, the unexplained
  mismatch), where each shows (windows, axes, temperatures, positions), the explanations in the recording's output
  unit (:func:`pipeline.model.small`: uV for volts, mm/s^2 for m/s^2, passed explicitly), the RMS before and after,
  the VP gravity-module errors before and after, and the notes.
- :func:`shows`, :func:`shows_where`, :func:`rms`: what an effect puts into the model, where it stands out of the
  noise, the weighted RMS (the selection uses them too).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.diagnose.fit import Design, Selection, SelectionSettings
from pipeline.diagnose.shift import SIGNIFICANT_SIGMA, VISIBLE_FRACTION, ShiftResult
from pipeline.diagnose.shift import explain as explain_shift
from pipeline.diagnose.signal import Blocks, StaticRecord, temperature_noise_c
from pipeline.diagnose.unexplained import describe as describe_unexplained
from pipeline.diagnose.unexplained import shares as unexplained_shares
from pipeline.effects.base import Shown
from pipeline.effects.catalogue import effect_class
from pipeline.effects.model import ExtendedModel
from pipeline.model import gravity_module_error_g, output_v, small, specific_force_g
from pipeline.passport.document import Passport
from pipeline.positions import AXES, POSITION_NAMES, is_verification_position
from pipeline.run import NS_PER_S as _NS
from pipeline.run import Run
from pipeline.segment import Segmentation
from pipeline.thermal import PolynomialModel


@dataclass(frozen=True)
class DiagnoseSettings:
    """Block length, location and reporting thresholds (in block sigmas), and the selection settings."""

    block_s: float = 30.0
    micro_s: float = 1.0
    locate_sigma: float = 5.0
    where_sigma: float = 3.0
    merge_gap_s: float = 60.0
    selection: SelectionSettings = field(default_factory=SelectionSettings)


@dataclass
class Diagnosis:
    """The report (docs/contract.md's JSON object plus extras), the passport with its extended model, and the block
    series behind the figure: times (h), residuals before and after (B, 3) V, block sigma, the windows where the
    findings show and where the residual before exceeded the noise (h)."""

    report: dict
    passport: Passport
    extended: ExtendedModel
    t_h: np.ndarray
    before_v: np.ndarray
    after_v: np.ndarray
    sigma_v: np.ndarray
    windows_h: list[tuple[float, float]]
    located_h: list[tuple[float, float]]


@dataclass
class Outcome:
    """What the steps of a diagnosis found, for :func:`report`: the run, its segmentation and static record, the
    design and the final selection (``trials``: the accepted effects with their final parameters), the passport's
    model (``model``, before) and the polynomial base the fits refine (``reference``; ``own_order``: the passport's
    own order), the constants' shift and the unexplained mismatch (None: none), the blocks left out
    (``excluded``) and the noise sigma (B, 3) of every block, the effects already in the base (``in_base``), the
    notes so far, the extended model, the passport and where it came from, and the output unit (V, m/s^2) the
    explanations are written in."""

    run: Run
    seg: Segmentation
    rec: StaticRecord
    design: Design
    sel: Selection
    trials: list
    model: Any
    reference: PolynomialModel
    own_order: int
    shift: ShiftResult | None
    unexplained: tuple | None
    excluded: np.ndarray
    noise_sigma: np.ndarray
    in_base: list[str]
    notes: list[str]
    extended: ExtendedModel
    passport: Passport
    passport_source: str | None
    unit: str


def report(out: Outcome, settings: DiagnoseSettings) -> Diagnosis:
    """The diagnosis' report, passport and figure series from what its steps found (see the module doc)."""
    run, seg, rec, design, sel, shift, unexplained = (
        out.run,
        out.seg,
        out.rec,
        out.design,
        out.sel,
        out.shift,
        out.unexplained,
    )
    blocks, excluded, notes, unit = design.blocks, out.excluded, list(out.notes), out.unit
    K_t, U0_t = out.model.constants_at(rec.element_temperature_c(None))
    predicted = blocks.mean(output_v(K_t, U0_t, rec.a_g))
    before = design.y - predicted
    after = design.y - sel.final.fitted
    w = (blocks.n * ~excluded)[:, None] * np.ones(3)
    noise_sigma = out.noise_sigma
    findings = [_finding(design, sel, t, before, after, seg, settings, unit) for t in out.trials]
    if shift is not None and shift.significant:
        if shift.level is not None and shift.level.powers - 1 > out.own_order:
            shift.parameters["thermal_model_note"] = (
                f"The passport's thermal model is a polynomial of order {out.own_order}: the recording needs powers "
                f"up to {shift.level.powers - 1}, which its calibration temperatures warrant."
            )
        findings.insert(0, _shift_finding(design, shift, predicted, before, after, seg, settings, unit))
    elif shift is not None and shift.level is not None:
        if shift.largest_z >= SIGNIFICANT_SIGMA:  # many sigmas by the fit, but too small for the recording to show
            change, noise = shift.parameters.get("departure_rms_v", 0.0), shift.parameters.get("noise_rms_v", 0.0)
            notes.append(
                f"the constants' change from the passport ({shift.largest_z:.1f} sigma by the fit) moves the "
                f"prediction by {small(change, unit=unit)} RMS, less than {VISIBLE_FRACTION:g} of the block noise "
                f"({small(noise, unit=unit)}): not named; {shift.level.name} refit to this run"
            )
        else:
            notes.append(
                f"the constants agree with the passport within its uncertainty (largest change "
                f"{shift.largest_z:.1f} sigma); {shift.level.name} refit to this run without a finding"
            )
    if unexplained is not None:
        findings.append(_unexplained_finding(design, sel, unexplained, after, seg, settings, unit))
    located = _where(design, np.abs(before) > settings.locate_sigma * design.sigma, seg, settings)
    vp = _vp_errors(seg, rec, out.model, out.extended)
    document = copy.deepcopy(out.passport.document)
    document["extended_model"] = out.extended.to_dict()
    notes += rec.warnings
    for e in out.in_base:
        notes.append(
            f"the base thermal model is of order {out.reference.order}: {e} is already part of it and is not tested"
        )
    rms_before, rms_refit = rms(before, w), rms(design.y - sel.base.fitted, w)
    if not findings and rms_before > 3 * rms_refit and rms_before > 2 * rms(noise_sigma, w):
        notes.append(
            f"the passport's own model departs from the recording by {small(rms_before, '.2f', unit=unit)} RMS where "
            f"its base refit to this run (a polynomial of order {out.reference.order}) leaves "
            f"{small(rms_refit, '.2f', unit=unit)}: its constants or thermal model, not a left-out effect"
        )
    report = {
        "verdict": "mismatch" if findings else "consistent",
        "findings": findings,
        "unit": run.meta.unit_serial,
        "run_id": run.meta.run_id,
        "passport_source": out.passport_source or "given",
        "base_model": {"kind": "polynomial", "order": out.reference.order},
        "noise_v": {
            "per_sample": rec.sigma_sample_v.tolist(),
            "thermosensor_c": temperature_noise_c(run)[0],
            "block_s": settings.block_s,
            "block_sigma_median": np.median(noise_sigma, axis=0).tolist(),
            "blocks_left_out": int(excluded.sum()),
            "ramp_direction_from": rec.ramp_source,
        },
        "rms_before_v": rms_before,
        "rms_base_refit_v": rms_refit,
        "rms_after_v": rms(after, w),
        "rms_noise_v": rms(noise_sigma, w),
        "located": located,
        "vp": vp,
        "vp_max_abs_dg_before_g": max((abs(v["dg_before_g"]) for v in vp), default=None),
        "vp_max_abs_dg_after_g": max((abs(v["dg_after_g"]) for v in vp), default=None),
        "extended_model": document["extended_model"],
        "candidates": sel.rounds,
        "empirical_corrections": unexplained[3] if unexplained is not None else [],
        "blocks": blocks.size,
        "notes": notes,
    }
    return Diagnosis(
        report=report,
        passport=Passport.from_dict(document),
        extended=out.extended,
        t_h=blocks.t_s / 3600.0,
        before_v=before,
        after_v=after,
        sigma_v=noise_sigma,
        windows_h=_hours(rec, [w for f in findings for w in f["where"]["windows"]]),
        located_h=_hours(rec, located["windows"]),
    )


def _shift_finding(
    design: Design,
    shift,
    predicted: np.ndarray,
    before: np.ndarray,
    after: np.ndarray,
    seg: Segmentation,
    settings: DiagnoseSettings,
    unit: str,
) -> dict:
    """``constants_shift``: which constants moved since the passport, by how much, where it shows."""
    signature = shift.fit.fitted - predicted
    z = np.abs(signature) / design.sigma
    flagged = z >= np.minimum(settings.where_sigma, 0.5 * z.max(axis=0))[None, :]
    where = _where(design, flagged, seg, settings)
    w = design.blocks.n[:, None] * flagged
    rb, ra = rms(before, w), rms(after, w)
    return {
        "effect": "constants_shift",
        "explanation": explain_shift(shift.parameters, rb, ra, shift.largest_z, unit=unit),
        "where": where,
        "parameters": shift.parameters,
        "rms_before_v": rb,
        "rms_after_v": ra,
        "delta_bic": round(shift.delta_bic, 1),
        "max_effect_v": float(np.abs(signature).max()),
    }


def _unexplained_finding(
    design: Design,
    sel: Selection,
    unexplained,
    after: np.ndarray,
    seg: Segmentation,
    settings: DiagnoseSettings,
    unit: str,
) -> dict:
    """``unexplained``: the located mismatch the catalogue leaves, its signature, and the empirical correction."""
    fid, desc, dbic, _ = unexplained
    desc = dict(desc, coef=sel.final.term_coef(fid).tolist())
    without = design.fit(tuple(s for s in sel.state if s[0] != fid))
    signature = sel.final.fitted - without.fitted
    residual = design.y - without.fitted
    z = np.abs(signature) / design.sigma
    share_z = (z**2).sum(axis=0)
    axes_on = share_z >= 0.05 * share_z.max()
    level = np.minimum(settings.where_sigma, 0.5 * z.max(axis=0))
    flagged = (z >= level[None, :]) & axes_on[None, :] & (z > 0)
    where = _where(design, flagged, seg, settings)
    w = design.blocks.n[:, None] * flagged
    peak = float(np.abs(signature[flagged]).max()) if flagged.any() else 0.0
    share, features = unexplained_shares(design, residual, axes_on)
    text, numbers = describe_unexplained(
        fid,
        desc,
        residual,
        design,
        share,
        where,
        peak,
        features["dominant_period_s"] if features["periodic_share"] >= 0.5 else None,
        unit=unit,
    )
    params = {
        "empirical_correction": fid.split(":", 1)[1],
        **{k: v for k, v in desc.items() if k != "coef"},
        **numbers,
        "shares": share,
        "shares_alone": features["alone"],
        "dominant_period_s": features["dominant_period_s"],
        "periodic_share": features["periodic_share"],
        "peak_v": peak,
        "axes": where["axes"],
    }
    return {
        "effect": "unexplained",
        "explanation": text,
        "where": where,
        "parameters": params,
        "rms_before_v": rms(residual, w),
        "rms_after_v": rms(after, w),
        "delta_bic": dbic,
        "max_effect_v": peak,
    }


def _hours(rec: StaticRecord, windows_ns: list[list[int]]) -> list[tuple[float, float]]:
    return [((a - rec.start_ns) / _NS / 3600.0, (b - rec.start_ns) / _NS / 3600.0) for a, b in windows_ns]


def rms(r: np.ndarray, w: np.ndarray) -> float:
    return float(np.sqrt(np.sum(w * r**2) / np.sum(w))) if np.sum(w) > 0 else 0.0


def _windows(blocks: Blocks, flagged: np.ndarray, start_ns: int, merge_gap_s: float, half_s: float) -> list[list[int]]:
    """Flagged blocks merged into [t_start_ns, t_end_ns] windows (gaps up to ``merge_gap_s`` bridged)."""
    idx = np.flatnonzero(flagged)
    out: list[list[float]] = []
    for i in idx:
        a, b = blocks.t_start_s[i] - half_s, blocks.t_end_s[i] + half_s
        if out and a - out[-1][1] <= merge_gap_s:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [[int(start_ns + round(a * _NS)), int(start_ns + round(b * _NS))] for a, b in out]


def _where(design: Design, flagged: np.ndarray, seg: Segmentation, settings: DiagnoseSettings) -> dict:
    """Windows, axes, temperatures and positions of the flagged (B, 3) block values."""
    blocks, rec = design.blocks, design.rec
    any_axis = np.any(flagged, axis=1)
    t_ns = rec.start_ns + blocks.t_s * _NS
    temps, on_ramps = set(), 0
    for i in np.flatnonzero(any_axis):
        on = [p.temp_c for p in seg.plateaus if p.t_start_ns <= t_ns[i] <= p.t_end_ns]
        if on:
            temps.add(round(float(on[0]), 1))
        else:
            on_ramps += 1
    positions = {POSITION_NAMES[int(p)] for p in blocks.position_idx[any_axis]}
    return {
        "windows": _windows(blocks, any_axis, rec.start_ns, settings.merge_gap_s, settings.micro_s / 2),
        "axes": [AXES[i] for i in range(3) if flagged[:, i].any()],
        "temps_c": sorted(temps),
        "positions": [p for p in POSITION_NAMES if p in positions],
        "blocks": int(any_axis.sum()),
        "blocks_on_ramps": on_ramps,
    }


def _finding(
    design: Design,
    sel: Selection,
    trial,
    before: np.ndarray,
    after: np.ndarray,
    seg: Segmentation,
    settings: DiagnoseSettings,
    unit: str,
) -> dict:
    """One accepted effect as a contract finding: where its terms change the model, how much, in words."""
    effect = trial.effect
    signature = shows(design, sel, effect)
    flagged = shows_where(design, signature, settings)
    where = _where(design, flagged, seg, settings)
    w = design.blocks.n[:, None] * flagged
    confounded = sel.confounded.get(effect, [])
    finding = {
        "effect": effect,
        "explanation": _explain(
            effect, trial.params, signature, flagged, where, confounded, float(design.rec.t_s[-1]) / 3600.0, unit
        ),
        "where": where,
        "parameters": trial.params,
        "rms_before_v": rms(before, w),
        "rms_after_v": rms(after, w),
        "delta_bic": round(trial.delta_bic, 1),
        "max_effect_v": float(np.abs(signature[flagged]).max()) if flagged.any() else 0.0,
    }
    if confounded:
        finding["confounded_with"] = list(confounded)
    return finding


def shows_where(design: Design, signature: np.ndarray, settings: DiagnoseSettings) -> np.ndarray:
    """(B, 3) bool: where an effect's ``signature`` (B, 3) V stands out of the noise and is at least a quarter of
    its largest size (a large effect spreads a little into the base refit everywhere; that is not where it shows);
    small effects: where largest."""
    z = np.abs(signature) / design.sigma
    share = (z**2).sum(axis=0)
    axes_on = share >= 0.05 * share.max()
    level = np.minimum(settings.where_sigma, 0.5 * z.max(axis=0))
    big = np.abs(signature) >= 0.25 * np.abs(signature).max(axis=0)
    return (z >= level[None, :]) & big & axes_on[None, :] & (z > 0)


def shows(design: Design, sel: Selection, effect: str) -> np.ndarray:
    """(B, 3) V: what the effect puts into the model where it shows. Its own fitted term (a decay after power-on
    or a move, a lag on ramps, an offset after a ramp, a per-position error), or for effects ``shown_by_refit``
    the change of the fitted values against the model refitted without it."""
    f = sel.final
    cls = effect_class(effect)
    if cls.shown_by_refit:
        return f.fitted - design.fit(tuple(s for s in sel.state if s[0] != effect)).fitted
    if cls.acts_on == "temperature":
        tau = dict(sel.state)[effect]
        return design.base_prediction(f, tau) - design.base_prediction(f, None)
    _, cols = design.term_columns(effect, dict(sel.state)[effect])
    return cols @ f.term_coef(effect)


def _temps_text(where: dict) -> str:
    temps = where["temps_c"]
    text = (" at " + ", ".join(f"{t:+.0f}" for t in temps) + " C") if temps else ""
    if where.get("blocks_on_ramps"):
        text += " and on the ramps" if temps else " on the ramps"
    return text


def _explain(
    effect: str,
    p: dict,
    signature: np.ndarray,
    flagged: np.ndarray,
    where: dict,
    confounded: list[str],
    duration_h: float,
    unit: str,
) -> str:
    """The effect's own sentences (what, where, how big, with units), and what it cannot be told apart from."""
    peak = float(np.abs(signature[flagged]).max()) if flagged.any() else 0.0
    shown = Shown(
        peak=peak, axes="/".join(where["axes"]) or "no axis", temps=_temps_text(where), duration_h=duration_h, unit=unit
    )
    text = effect_class(effect).explain(p, shown)
    if confounded:
        text += (
            f" Under this run's program it cannot be told apart from {', '.join(confounded)}: they explain "
            "the mismatch equally well."
        )
    return text


def _vp_errors(seg: Segmentation, rec: StaticRecord, model, extended: ExtendedModel) -> list[dict]:
    """Gravity-module error dg = |a| - 1 (g) of each VP segment on a plateau: the passport (method 1) before, the
    extended model after, from the same 1 s means."""
    vp = [s for s in seg.segments if s.position and is_verification_position(s.position) and s.plateau is not None]
    if not vp or rec.size == 0:
        return []
    t_ns = rec.start_ns + rec.t_s * _NS
    k, u0 = model.constants_at(rec.element_temperature_c(None))
    a_before = specific_force_g(k, u0, rec.u_v)
    a_after = extended.specific_force_g(
        rec.u_v, rec.context(extended.base), rec.element_temperature_c(extended.lag_tau_s)
    )
    out = []
    for s in vp:
        m = (t_ns >= s.t_start_ns) & (t_ns <= s.t_end_ns)
        if not m.any():
            continue
        wts = rec.count[m][:, None]
        mean_b = (a_before[m] * wts).sum(0) / wts.sum()
        mean_a = (a_after[m] * wts).sum(0) / wts.sum()
        out.append(
            {
                "temp_c": round(float(s.temp_c), 2),
                "position": s.position,
                "t_start_ns": int(s.t_start_ns),
                "t_end_ns": int(s.t_end_ns),
                "dg_before_g": float(gravity_module_error_g(mean_b)),
                "dg_after_g": float(gravity_module_error_g(mean_a)),
            }
        )
    return out


__all__ = ["DiagnoseSettings", "Diagnosis", "Outcome", "report", "rms", "shows", "shows_where"]
