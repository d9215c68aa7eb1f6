"""Mismatch diagnosis: where a recording departs from the model its passport predicts, which left-out physics of
the effect catalogue (physics.md) explains it, the extended model, and the fit before and after.

Steps (:func:`diagnose_run`):

1. The passport is given or fitted from the run itself (default thermal model: polynomial of order = distinct
   calibration temperatures - 1, at most 3). The recording is reduced to its named static stretches (soaks, ramps
   and positions; moves left out) as 1 s means and ~30 s blocks (:mod:`pipeline.diagnose.signal`); the passport
   drives the model with the recorded temperature and positions: residual = recorded - predicted.
2. Noise from the data: the voltmeter's white noise from first differences of static samples, the thermosensor's
   from its second differences (through dU/dT it is part of a block's error), and an Allan-type factor from the
   scatter of consecutive blocks' residuals (:func:`pipeline.diagnose.fit.block_noise_factor`).
3. Locate: blocks whose residual exceeds ``locate_sigma`` block sigmas, merged into time windows, with their axes,
   temperatures and positions.
4. Name: the base model is refit jointly with each catalogue effect's terms (built from the simulator's own
   ``delta_u_v``), scored by BIC with plausibility checks, and accepted greedily (:mod:`pipeline.diagnose.fit`);
   effects the run's program cannot tell apart are reported together as confounded.
5. Improve: residual RMS before (passport) and after (base + accepted effects), overall and per finding; VP gravity
   module errors before and after; the extended model stored in the passport (:mod:`pipeline.diagnose.model`).

The report is contract.md's ``diagnose --json`` object (``verdict`` is ``consistent`` exactly when ``findings`` is
empty) with extra keys. RMS values are of block means (a block is ~30 s), where left-out physics stands out of the
noise; per-sample RMS is dominated by the white noise.
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
from dataclasses import dataclass, field

import numpy as np

from pipeline.calibrate import tilt
from pipeline.calibrate.observations import ObservedRun, observations_from_segmentation
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.diagnose.fit import (
    Design,
    Selection,
    SelectionSettings,
    block_noise_factor,
    select_terms,
)
from pipeline.diagnose.model import (
    ExtendedModel,
    add_polynomial_correction,
    polynomial_reference,
    raise_order,
)
from pipeline.diagnose.shift import RATE_U0, find_shift
from pipeline.diagnose.shift import explain as explain_shift
from pipeline.diagnose.signal import (
    Blocks,
    StaticRecord,
    make_blocks,
    segment_settings_for,
    static_record,
    temperature_noise_c,
)
from pipeline.diagnose.unexplained import describe as describe_unexplained
from pipeline.diagnose.unexplained import find_unexplained
from pipeline.diagnose.unexplained import shares as unexplained_shares
from pipeline.effects.base import Shown
from pipeline.effects.catalogue import EFFECTS, effect_class, make_effect
from pipeline.errors import CalibrationError
from pipeline.model import gravity_module_error_g, output_v, reading_in, small, specific_force_g
from pipeline.passport.document import compensate_extended, load_model
from pipeline.passport.text import output_unit_of
from pipeline.positions import AXES, POSITION_NAMES, is_verification_position
from pipeline.run import NS_PER_S as _NS
from pipeline.run import Run
from pipeline.segment import Segmentation, segment_run
from pipeline.thermal import default_order

#: sigma factor of blocks left out of the fits (they keep their place in the figure)
_EXCLUDE = 1e3
#: beside an unexplained mismatch, a catalogue effect is kept only where, with it, the residual where it shows is
#: within this factor of the noise there (RMS) ...
WITHIN_NOISE = 1.5
#: ... or where, with it, the residual there is at most this share of the residual without it (RMS)
LARGE_SHARE = 0.5


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
    """The report (contract.md's JSON object plus extras), the passport with its extended model, and the block
    series behind the figure: times (h), residuals before and after (B, 3) V, block sigma, the windows where the
    findings show and where the residual before exceeded the noise (h)."""

    report: dict
    passport: dict
    extended: ExtendedModel
    t_h: np.ndarray
    before_v: np.ndarray
    after_v: np.ndarray
    sigma_v: np.ndarray
    windows_h: list[tuple[float, float]]
    located_h: list[tuple[float, float]]


def fit_passport(run: Run, segmentation: Segmentation, settings: CalibrationSettings = CalibrationSettings()) -> dict:
    """A passport fitted from the run itself by the tilt recipe (what ``calibrate`` would write, without registry
    fields), from the run's ``segmentation``."""
    observed = ObservedRun(
        meta=run.meta, source="", observations=observations_from_segmentation(run.meta.run_id, segmentation)
    )
    return tilt.calibrate_observed([observed], settings).passport


#: order of the temperature polynomial fitted to a recording the tilt recipe cannot calibrate
OWN_MODEL_ORDER = 3


def own_model_passport(meta, order: int = OWN_MODEL_ORDER) -> dict:
    """A passport document with nominal constants (K = nominal gain x I, U0 = 0) and a zero polynomial thermal
    model of ``order``: the reference a diagnosis refits to the recording itself when nothing calibrates it."""
    zeros = [0.0] * order
    pairs = [a + b for a in AXES for b in AXES if a != b]
    return {
        "schema": "thermocal.passport/1",
        "unit": meta.unit_serial,
        "normal_temp_c": float(meta.normal_temp_c),
        "g_local_mps2": float(meta.g_local_mps2),
        "coefficients": {"K": (float(meta.nominal_gain_v_per_g) * np.eye(3)).tolist(), "U0": [0.0, 0.0, 0.0]},
        "thermal_model": {
            "kind": "polynomial",
            "order": order,
            "alpha": {a: zeros for a in AXES},
            "beta": {a + a: zeros for a in AXES},
            "gamma": {p: zeros for p in pairs},
        },
        "per_plateau": [],
    }


def diagnose_run(
    run: Run,
    passport: dict | None = None,
    settings: DiagnoseSettings = DiagnoseSettings(),
    passport_source: str | None = None,
) -> Diagnosis:
    """Diagnose ``run`` against ``passport`` (fitted from the run when None). See the module doc."""
    with _one_blas_thread():  # in a context of its own: the explanations' unit (reading_in) stays inside
        return contextvars.copy_context().run(_diagnose, run, passport, settings, passport_source)


def _one_blas_thread():
    """Hundreds of small eigen-decompositions: a threaded BLAS only gets in their way (badly so on a busy
    machine). Uses threadpoolctl when it is installed (optional)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        return contextlib.nullcontext()
    return threadpool_limits(1)


def _diagnose(run: Run, passport: dict | None, settings: DiagnoseSettings, passport_source: str | None) -> Diagnosis:
    seg_settings = segment_settings_for(run)
    seg = segment_run(run, seg_settings)
    given = passport is not None
    if passport is None:
        try:
            passport = fit_passport(run, seg, CalibrationSettings(segment=seg_settings))
            passport_source = "fitted from the run (default thermal model)"
        except CalibrationError as e:  # no plateau the tilt recipe calibrates (a sweep, few orientations)
            passport = own_model_passport(run.meta, OWN_MODEL_ORDER)
            passport_source = (
                f"none: the tilt recipe cannot calibrate this run ({e.message}); the base model "
                f"K(T) a + U0(T), a polynomial of order {OWN_MODEL_ORDER} in temperature, is fitted "
                "to the recording itself, as far as its orientations determine it"
            )
    reading_in(output_unit_of(passport))  # the explanations' amounts in its unit (uV, mm/s^2)
    model, reference, notes = _base_model(passport)
    own_order = polynomial_reference(model).order
    rec = static_record(run, seg, micro_s=settings.micro_s, settings=seg_settings)
    if rec.size < 10 or not np.all(np.isfinite(rec.sigma_sample_v)):
        raise CalibrationError(
            "too few named static samples to compare with the model and estimate the noise", stream="voltmeter"
        )
    blocks = make_blocks(rec, settings.block_s)
    sigma = _block_sigma(run, rec, blocks, reference)
    excluded = blocks.mean(rec.ramp_uncertain.astype(float)) > 0  # direction of the last ramp unknown there
    sigma[excluded] *= _EXCLUDE
    design = Design(rec, blocks, reference, sigma)
    shift = None
    if given:  # the passport as it is: its constants move only where the recording says they moved
        design.set_base_mask(np.zeros_like(design.base_mask))
    design.set_sigma(design.sigma * block_noise_factor(design, design.fit(())))
    held: tuple = ()  # a drift of the constants within the recording, held in the model once found
    if given:
        shift = find_shift(design, passport, settings.selection.threshold)
        design.set_base_mask(shift.mask)
        held = shift.terms
    in_base = [
        e for e, c in EFFECTS.items() if c.in_base_from_order is not None and reference.order >= c.in_base_from_order
    ]
    candidates = [e for e in EFFECTS if e not in in_base]
    sel = _select(design, candidates, settings, initial=held)
    if given and sel.accepted:  # does the shift still hold with the effects found? (they may explain it)
        again = find_shift(design, passport, settings.selection.threshold, tuple(s for s in sel.state if s not in held))
        if again.level != shift.level or again.significant != shift.significant:
            shift = again
            design.set_base_mask(shift.mask)
            held = shift.terms
            sel = _select(design, candidates, settings, initial=held)
    if given and sel.accepted:  # an effect that only takes up the passport's own error is not named
        absorbed = _passport_error_absorbed(design, sel, settings)
        if absorbed:
            candidates = [e for e in candidates if e not in absorbed]
            sel = _select(design, candidates, settings, initial=held)
            notes.append(
                f"{', '.join(absorbed)} would only take up the passport's own error (with its thermal "
                "model free to move, the recording does not need it): not named"
            )
    unexplained = find_unexplained(design, sel.final, settings.locate_sigma)
    if unexplained is not None:  # held in the model, the catalogue search is redone on top of it
        held = held + ((unexplained[0], None),)
        sel = _select(design, candidates, settings, initial=held)
        forced = _forced_by_unexplained(design, sel, unexplained[0], settings)
        if forced:
            candidates = [e for e in candidates if e not in forced]
            sel = _select(design, candidates, settings, initial=held)
            notes.append(
                f"{', '.join(forced)} would only absorb part of the unexplained mismatch (a generic "
                "function of time explains it as well): not named"
            )
        for _ in range(3):
            nibbling = _not_explained_to_noise(design, sel, settings)
            if not nibbling:
                break
            candidates = [e for e in candidates if e not in nibbling]
            sel = _select(design, candidates, settings, initial=held)
            notes.append(
                ", ".join(f"{e} (leaves {r:.1f} x the noise where it shows)" for e, r in nibbling.items())
                + ": not named, it does not explain the mismatch beside the unexplained one to within the "
                "noise, nor most of it"
            )

    final_trials = _final_trials(sel)
    predicted = blocks.mean(output_v(*model.constants_at(rec.temp_c), rec.a_g))
    before = design.y - predicted
    after = design.y - sel.final.fitted
    extended = ExtendedModel(
        add_polynomial_correction(reference, sel.final.base_coef),
        [make_effect(t.effect, t.params) for t in final_trials] + _drift_effects(sel),
        source={"run_id": run.meta.run_id, "run": run.source, "method": "thermocal diagnose"},
    )
    w = (blocks.n * ~excluded)[:, None] * np.ones(3)
    noise_sigma = design.sigma / np.where(excluded, _EXCLUDE, 1.0)[:, None]
    findings = [_finding(design, sel, t, before, after, seg, settings) for t in final_trials]
    if shift is not None and shift.significant:
        if shift.level is not None and shift.level.powers - 1 > own_order:
            shift.parameters["thermal_model_note"] = (
                f"The passport's thermal model is a polynomial of order {own_order}: the recording needs powers "
                f"up to {shift.level.powers - 1}, which its calibration temperatures warrant."
            )
        findings.insert(0, _shift_finding(design, shift, predicted, before, after, seg, settings))
    elif shift is not None and shift.level is not None:
        notes.append(
            f"the constants agree with the passport within its uncertainty (largest change "
            f"{shift.largest_z:.1f} sigma); {shift.level.name} refit to this run without a finding"
        )
    if unexplained is not None:
        findings.append(_unexplained_finding(design, sel, unexplained, after, seg, settings))
    located = _where(design, np.abs(before) > settings.locate_sigma * design.sigma, seg, settings)
    vp = _vp_errors(seg, rec, model, extended)
    out_passport = copy.deepcopy(passport)
    out_passport["extended_model"] = extended.to_dict()
    notes += rec.warnings
    for e in in_base:
        notes.append(
            f"the base thermal model is of order {reference.order}: {e} is already part of it and is not tested"
        )
    rms_before, rms_refit = _rms(before, w), _rms(design.y - sel.base.fitted, w)
    if not findings and rms_before > 3 * rms_refit and rms_before > 2 * _rms(noise_sigma, w):
        notes.append(
            f"the passport's own model departs from the recording by {small(rms_before, '.2f')} RMS where "
            f"its base refit to this run (a polynomial of order {reference.order}) leaves "
            f"{small(rms_refit, '.2f')}: its constants or thermal model, not a left-out effect"
        )
    report = {
        "verdict": "mismatch" if findings else "consistent",
        "findings": findings,
        "unit": run.meta.unit_serial,
        "run_id": run.meta.run_id,
        "passport_source": passport_source or "given",
        "base_model": {"kind": "polynomial", "order": reference.order},
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
        "rms_after_v": _rms(after, w),
        "rms_noise_v": _rms(noise_sigma, w),
        "located": located,
        "vp": vp,
        "vp_max_abs_dg_before_g": max((abs(v["dg_before_g"]) for v in vp), default=None),
        "vp_max_abs_dg_after_g": max((abs(v["dg_after_g"]) for v in vp), default=None),
        "extended_model": out_passport["extended_model"],
        "candidates": sel.rounds,
        "empirical_corrections": unexplained[3] if unexplained is not None else [],
        "blocks": blocks.size,
        "notes": notes,
    }
    return Diagnosis(
        report=report,
        passport=out_passport,
        extended=extended,
        t_h=blocks.t_s / 3600.0,
        before_v=before,
        after_v=after,
        sigma_v=noise_sigma,
        windows_h=_hours(rec, [w for f in findings for w in f["where"]["windows"]]),
        located_h=_hours(rec, located["windows"]),
    )


def _select(design: Design, candidates: list[str], settings: DiagnoseSettings, initial: tuple = ()) -> Selection:
    """The greedy catalogue search, redone with wider block sigmas when the accepted effects leave a correlated
    residual, and without any effect whose final parameters are physically implausible."""
    left = list(candidates)
    for _ in range(4):
        sel = select_terms(design, left, settings.selection, initial)
        factor = block_noise_factor(design, sel.final)
        if sel.accepted and np.any(factor > 1.05):  # correlated residual the accepted effects leave: widen, redo
            design.set_sigma(design.sigma * factor)
            sel = select_terms(design, left, settings.selection, initial)
        bad = [t.effect for t in _final_trials(sel) if effect_class(t.effect).implausible(t.params)]
        if not bad:
            return sel
        left = [e for e in left if e not in bad]
    return sel


def _passport_error_absorbed(design: Design, sel: Selection, settings: DiagnoseSettings) -> list[str]:
    """Catalogue effects accepted on top of a given, held passport that the recording no longer needs once the
    passport's constants and thermal model are free to move (a passport's constants are not exact: a smooth
    function of temperature such as ``temperature_curvature`` can take up their error at the calibration
    temperatures). An effect the free base cannot tell apart from (rank 0) is kept: there the held passport is
    what separates it."""
    saved = design.base_mask.copy()
    ln_n = float(np.log(design.n_values))
    out = []
    try:
        design.set_base_mask(np.ones_like(saved))
        with_all = design.fit(sel.state)
        for t in sel.accepted:
            without = design.fit(tuple(s for s in sel.state if s[0] != t.effect))
            cls = effect_class(t.effect)
            if with_all.rank == without.rank and cls.acts_on != "temperature":
                continue
            added = with_all.rank - without.rank + (cls.nonlinear is not None)
            if with_all.chi2 - without.chi2 + added * ln_n > -settings.selection.threshold:
                out.append(t.effect)
    finally:
        design.set_base_mask(saved)
    return out


def _forced_by_unexplained(design: Design, sel: Selection, fid: str, settings: DiagnoseSettings) -> list[str]:
    """Catalogue effects accepted beside an unexplained mismatch that a generic fine function of time (besides the
    chosen empirical correction) explains as well: they are not explained to within the noise by their own
    physics, only absorbing part of the mismatch."""
    from pipeline.diagnose.unexplained import families

    if not sel.accepted:
        return []
    fine = "empirical:time_fine"
    if fine not in design.extra:
        labels, cols, _ = families(design, sel.final)[fine]
        design.extra[fine] = (labels, cols)
    ln_n = float(np.log(design.n_values))
    held = tuple(sel.state) + (((fine, None),) if fid != fine else ())
    with_all = design.fit(held)
    forced = []
    for t in sel.accepted:
        without = design.fit(tuple(s for s in held if s[0] != t.effect))
        if with_all.chi2 - without.chi2 + (with_all.rank - without.rank) * ln_n > -settings.selection.threshold:
            forced.append(t.effect)
    if fid != fine:
        del design.extra[fine]
    return forced


def _shift_finding(
    design: Design,
    shift,
    predicted: np.ndarray,
    before: np.ndarray,
    after: np.ndarray,
    seg: Segmentation,
    settings: DiagnoseSettings,
) -> dict:
    """``constants_shift``: which constants moved since the passport, by how much, where it shows."""
    signature = shift.fit.fitted - predicted
    z = np.abs(signature) / design.sigma
    flagged = z >= np.minimum(settings.where_sigma, 0.5 * z.max(axis=0))[None, :]
    where = _where(design, flagged, seg, settings)
    w = design.blocks.n[:, None] * flagged
    rb, ra = _rms(before, w), _rms(after, w)
    return {
        "effect": "constants_shift",
        "explanation": explain_shift(shift.parameters, rb, ra, shift.largest_z),
        "where": where,
        "parameters": shift.parameters,
        "rms_before_v": rb,
        "rms_after_v": ra,
        "delta_bic": round(shift.delta_bic, 1),
        "max_effect_v": float(np.abs(signature).max()),
    }


def _unexplained_finding(
    design: Design, sel: Selection, unexplained, after: np.ndarray, seg: Segmentation, settings: DiagnoseSettings
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
        "rms_before_v": _rms(residual, w),
        "rms_after_v": _rms(after, w),
        "delta_bic": dbic,
        "max_effect_v": peak,
    }


def _drift_effects(sel: Selection) -> list:
    """The offsets' drift of a ``constants_shift`` in the extended model: the catalogue's forward model of that
    signal (``time_drift``, U0 += r t: the effect with an ``offset_rate_param``). A drift of K has no term there:
    it is reported, not modelled."""
    cls = next((c for c in EFFECTS.values() if c.offset_rate_param), None)
    if RATE_U0 not in sel.final.slices or cls is None:
        return []
    return [cls.make({cls.offset_rate_param: sel.final.term_coef(RATE_U0).tolist()})]


def _hours(rec: StaticRecord, windows_ns: list[list[int]]) -> list[tuple[float, float]]:
    return [((a - rec.start_ns) / _NS / 3600.0, (b - rec.start_ns) / _NS / 3600.0) for a, b in windows_ns]


# ---------------------------------------------------------------------------------------------------------------


def _base_model(passport: dict):
    """The passport's model, the polynomial base the fits refine, and notes on how one became the other.

    The base is of the order the passport's calibration temperatures warrant (distinct temperatures - 1, at most
    3): a cubic part is ``temperature_curvature`` only beyond that.
    """
    model = load_model(passport)
    reference = polynomial_reference(model)
    cal_temps = np.array([p["temp_c"] for p in passport.get("per_plateau", []) if "temp_c" in p], dtype=float)
    order = max(reference.order, default_order(cal_temps) if cal_temps.size else 0)
    notes = []
    if model is not reference:
        notes.append(
            "the passport's piecewise-linear thermal model was referred to a polynomial of order "
            f"{reference.order} through its breakpoints for the refit"
        )
    if order > reference.order:
        notes.append(
            f"the passport's polynomial of order {reference.order} was refit as order {order}, what its "
            f"{order + 1} calibration temperatures warrant"
        )
        reference = raise_order(reference, order)
    return model, reference, notes


def _block_sigma(run: Run, rec: StaticRecord, blocks: Blocks, reference) -> np.ndarray:
    """Expected sigma (B, 3) V of each block mean: white voltmeter noise and, through dU/dT, thermosensor noise."""
    sigma_t, rate_t = temperature_noise_c(run)
    kp, up = reference.constants_at(blocks.temp_c + 0.5)
    km, um = reference.constants_at(blocks.temp_c - 0.5)
    du_dt = output_v(kp - km, up - um, blocks.a_g)
    n_t = np.maximum(1.0, (blocks.t_end_s - blocks.t_start_s + 1.0) * rate_t)
    return np.sqrt(rec.sigma_sample_v[None, :] ** 2 / blocks.n[:, None] + du_dt**2 * sigma_t**2 / n_t[:, None])


def _final_trials(sel: Selection):
    """Accepted trials with the final (refined) time constants and coefficients."""
    out = []
    for t in sel.accepted:
        value = dict(sel.state)[t.effect]
        coef = sel.final.term_coef(t.effect) if t.effect in sel.final.slices else np.zeros(0)
        params = effect_class(t.effect).fit_parameters(coef, value, sel.final.labels.get(t.effect, []))
        out.append(type(t)(t.effect, value, t.chi2, t.added_rank, t.delta_bic, params, t.reason, t.change_w))
    return out


def _rms(r: np.ndarray, w: np.ndarray) -> float:
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
    any_axis = flagged.any(axis=1)
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
) -> dict:
    """One accepted effect as a contract finding: where its terms change the model, how much, in words."""
    effect = trial.effect
    signature = _shows(design, sel, effect)
    flagged = _shows_where(design, signature, settings)
    where = _where(design, flagged, seg, settings)
    w = design.blocks.n[:, None] * flagged
    confounded = sel.confounded.get(effect, [])
    finding = {
        "effect": effect,
        "explanation": _explain(
            effect, trial.params, signature, flagged, where, confounded, float(design.rec.t_s[-1]) / 3600.0
        ),
        "where": where,
        "parameters": trial.params,
        "rms_before_v": _rms(before, w),
        "rms_after_v": _rms(after, w),
        "delta_bic": round(trial.delta_bic, 1),
        "max_effect_v": float(np.abs(signature[flagged]).max()) if flagged.any() else 0.0,
    }
    if confounded:
        finding["confounded_with"] = list(confounded)
    return finding


def _shows_where(design: Design, signature: np.ndarray, settings: DiagnoseSettings) -> np.ndarray:
    """(B, 3) bool: where an effect's ``signature`` (B, 3) V stands out of the noise and is at least a quarter of
    its largest size (a large effect spreads a little into the base refit everywhere; that is not where it shows);
    small effects: where largest."""
    z = np.abs(signature) / design.sigma
    share = (z**2).sum(axis=0)
    axes_on = share >= 0.05 * share.max()
    level = np.minimum(settings.where_sigma, 0.5 * z.max(axis=0))
    big = np.abs(signature) >= 0.25 * np.abs(signature).max(axis=0)
    return (z >= level[None, :]) & big & axes_on[None, :] & (z > 0)


def _not_explained_to_noise(design: Design, sel: Selection, settings: DiagnoseSettings) -> dict[str, float]:
    """Catalogue effects accepted beside an unexplained mismatch that neither explain the mismatch where they show
    to within the noise (:data:`WITHIN_NOISE`) nor take out most of it there (the residual RMS there at most
    :data:`LARGE_SHARE` of what the model refit without them leaves; the rest is then something else, located
    there too): effect -> the residual RMS where it shows over the noise RMS there. Such an effect only nibbles at
    a signature it does not explain (issue 14.3)."""
    after = design.y - sel.final.fitted
    out = {}
    for t in sel.accepted:
        flagged = _shows_where(design, _shows(design, sel, t.effect), settings)
        w = design.blocks.n[:, None] * flagged
        if not flagged.any():
            continue
        without = design.fit(tuple(s for s in sel.state if s[0] != t.effect))
        ra, rb = _rms(after, w), _rms(design.y - without.fitted, w)
        ratio = ra / max(_rms(design.sigma, w), 1e-30)
        if ratio > WITHIN_NOISE and ra > LARGE_SHARE * rb:
            out[t.effect] = ratio
    return out


def _shows(design: Design, sel: Selection, effect: str) -> np.ndarray:
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
) -> str:
    """The effect's own sentences (what, where, how big, with units), and what it cannot be told apart from."""
    peak = float(np.abs(signature[flagged]).max()) if flagged.any() else 0.0
    shown = Shown(peak=peak, axes="/".join(where["axes"]) or "no axis", temps=_temps_text(where), duration_h=duration_h)
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
    k, u0 = model.constants_at(rec.temp_c)
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


__all__ = ["DiagnoseSettings", "Diagnosis", "diagnose_run", "fit_passport", "compensate_extended"]
