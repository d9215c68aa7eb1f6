"""Mismatch diagnosis: where a recording departs from the model its passport predicts, which left-out physics of
the effect catalogue (docs/physics.md) explains it, the extended model, and the fit before and after.

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
   module errors before and after; the extended model stored in the passport (:mod:`pipeline.effects.model`).

This module runs the steps; :mod:`pipeline.diagnose.report` writes what they found
(:func:`~pipeline.diagnose.report.report`): docs/contract.md's ``diagnose --json`` object (``verdict`` is ``consistent``
exactly when ``findings`` is empty) with extra keys, its sentences in the recording's output unit (given
explicitly). RMS values are of block means (a block is ~30 s), where left-out physics stands out of the noise;
per-sample RMS is dominated by the white noise.
"""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np

from pipeline.calibrate import tilt
from pipeline.calibrate.observations import ObservedRun, observations_from_segmentation
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.diagnose.fit import (
    Design,
    Selection,
    block_noise_factor,
    select_terms,
)
from pipeline.diagnose.report import DiagnoseSettings, Diagnosis, Outcome, report, rms, shows, shows_where
from pipeline.diagnose.shift import RATE_U0, find_shift
from pipeline.diagnose.signal import (
    Blocks,
    StaticRecord,
    make_blocks,
    segment_settings_for,
    static_record,
    temperature_noise_c,
)
from pipeline.diagnose.unexplained import find_unexplained
from pipeline.dynamics import Thermosensor
from pipeline.effects.catalogue import EFFECTS, effect_class, make_effect
from pipeline.effects.model import ExtendedModel
from pipeline.errors import CalibrationError
from pipeline.model import output_v
from pipeline.passport.document import Passport, compensate_extended, load_passport
from pipeline.positions import AXES
from pipeline.run import Run
from pipeline.segment import Segmentation, segment_run
from pipeline.thermal import (
    DifferentialModel,
    add_polynomial_correction,
    default_order,
    polynomial_reference,
    raise_order,
)

#: sigma factor of blocks left out of the fits (they keep their place in the figure)
_EXCLUDE = 1e3
#: beside an unexplained mismatch, a catalogue effect is kept only where, with it, the residual where it shows is
#: within this factor of the noise there (RMS) ...
WITHIN_NOISE = 1.5
#: ... or where, with it, the residual there is at most this share of the residual without it (RMS)
LARGE_SHARE = 0.5


def fit_passport(
    run: Run, segmentation: Segmentation, settings: CalibrationSettings = CalibrationSettings()
) -> Passport:
    """A passport fitted from the run itself by the tilt recipe (what ``calibrate`` would write, without registry
    fields), from the run's ``segmentation``."""
    observed = ObservedRun(
        meta=run.meta, source="", observations=observations_from_segmentation(run.meta.run_id, segmentation)
    )
    return load_passport(tilt.calibrate_observed([observed], settings).passport)


#: order of the temperature polynomial fitted to a recording the tilt recipe cannot calibrate
OWN_MODEL_ORDER = 3


def own_model_passport(meta, order: int = OWN_MODEL_ORDER) -> Passport:
    """A passport with nominal constants (K = nominal gain x I, U0 = 0) and a zero polynomial thermal
    model of ``order``: the reference a diagnosis refits to the recording itself when nothing calibrates it."""
    zeros = [0.0] * order
    pairs = [a + b for a in AXES for b in AXES if a != b]
    return Passport.from_dict(
        {
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
    )


def diagnose_run(
    run: Run,
    passport: Passport | dict | None = None,
    settings: DiagnoseSettings = DiagnoseSettings(),
    passport_source: str | None = None,
    segmentation: Segmentation | None = None,
) -> Diagnosis:
    """Diagnose ``run`` against ``passport`` (fitted from the run when None; a document is loaded once here,
    :func:`pipeline.passport.document.load_passport`). ``segmentation``: the run's, when already made (a unit of a
    run holding several: the consensus of the units' still times, as ``calibrate`` segments it,
    :func:`pipeline.calibrate.inputs.segment_recordings`); else :func:`pipeline.segment.segment_run`'s. See the
    module doc."""
    with _one_blas_thread():
        loaded = None if passport is None else load_passport(passport)
        return _diagnose(run, loaded, settings, passport_source, segmentation)


def _one_blas_thread():
    """Hundreds of small eigen-decompositions: a threaded BLAS only gets in their way (badly so on a busy
    machine). Uses threadpoolctl when it is installed (optional)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        return contextlib.nullcontext()
    return threadpool_limits(1)


def _diagnose(
    run: Run,
    passport: Passport | None,
    settings: DiagnoseSettings,
    passport_source: str | None,
    segmentation: Segmentation | None = None,
) -> Diagnosis:
    seg_settings = segment_settings_for(run)
    seg = segmentation if segmentation is not None else segment_run(run, seg_settings)
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
    unit = passport.output_unit  # the explanations' amounts in its unit (uV, mm/s^2)
    model, reference, notes = _base_model(passport)
    own_order = polynomial_reference(model).order
    rec = static_record(run, seg, micro_s=settings.micro_s, settings=seg_settings)
    if rec.size < 10 or not np.all(np.isfinite(rec.sigma_sample_v)):
        raise CalibrationError(
            "too few named static samples to compare with the model and estimate the noise", stream="voltmeter"
        )
    rec, lag_s = _with_passport_dynamics(run, rec, passport, notes)
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
    if shift is not None and sel.accepted:  # does the shift still hold with the effects found? (they may explain it)
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
    extended = ExtendedModel(
        add_polynomial_correction(reference, sel.final.base_coef),
        [make_effect(t.effect, t.params) for t in final_trials]
        + _passport_lag(final_trials, lag_s)
        + _drift_effects(sel),
        source={"run_id": run.meta.run_id, "run": run.source, "method": "thermocal diagnose"},
    )
    return report(
        Outcome(
            run=run,
            seg=seg,
            rec=rec,
            design=design,
            sel=sel,
            trials=final_trials,
            model=model,
            reference=reference,
            own_order=own_order,
            shift=shift,
            unexplained=unexplained,
            excluded=excluded,
            noise_sigma=design.sigma / np.where(excluded, _EXCLUDE, 1.0)[:, None],
            in_base=in_base,
            notes=notes,
            extended=extended,
            passport=passport,
            passport_source=passport_source,
            unit=unit,
        ),
        settings,
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


def _drift_effects(sel: Selection) -> list:
    """The offsets' drift of a ``constants_shift`` in the extended model: the catalogue's forward model of that
    signal (``time_drift``, U0 += r t: the effect with an ``offset_rate_param``). A drift of K has no term there:
    it is reported, not modelled."""
    cls = next((c for c in EFFECTS.values() if c.offset_rate_param), None)
    if RATE_U0 not in sel.final.slices or cls is None or cls.offset_rate_param is None:
        return []
    return [cls.make({cls.offset_rate_param: sel.final.term_coef(RATE_U0).tolist()})]


# ---------------------------------------------------------------------------------------------------------------


def _base_model(passport: Passport):
    """The passport's model, the polynomial base the fits refine, and notes on how one became the other.

    The base is of the order the passport's calibration temperatures warrant (distinct temperatures - 1, at most
    3): a cubic part is ``temperature_curvature`` only beyond that.
    """
    model = passport.thermal_model
    reference = polynomial_reference(model)
    cal_temps = np.array(passport.plateau_temps_c, dtype=float)
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


def _with_passport_dynamics(run: Run, rec: StaticRecord, p: Passport, notes: list[str]) -> tuple[StaticRecord, float]:
    """The record compared with the passport's whole model where the passport holds ``rate_terms`` (the ramp and
    differential methods), as ``apply`` evaluates it: the model at the element temperature, through the passport's
    element lag (``model_temp_c``), and the outputs without what its rate terms add (the rate the smoothed
    thermosensor's). Returns the record and the lag (s; 0: none). A lag term the search then tries is the whole lag
    of the element behind the thermosensor, named only where the recording needs a lag other than the passport's."""
    rate = p.rate_terms
    if rate is None or rec.size == 0:
        return rec, 0.0
    lag_s = max(float(rate.lag_tau_s), 0.0)
    changes: dict = {}
    if lag_s > 0:
        changes["model_temp_c"] = rec.element_temperature_c(lag_s)
        notes.append(
            f"the passport's model is compared at the element temperature, {lag_s:.0f} s behind the thermosensor "
            "(its rate_terms.lag_tau_s); a thermal_lag finding gives the whole lag the recording shows"
        )
    if rate.order > 0 or rate.cross_abs is not None:
        temp = changes.get("model_temp_c", rec.temp_c)
        rate_c = None
        if rate.order > 0:
            rate_c = Thermosensor.from_run(run, rate.temp_smooth_s, t_ref_ns=rec.start_ns).at(rec.t_s)[1]
        k, u0 = DifferentialModel(p.thermal_model, rate).constants_at(temp, rate_c)
        k_s, u0_s = p.thermal_model.constants_at(temp)
        changes["u_v"] = rec.u_v - output_v(k - k_s, u0 - u0_s, rec.a_g)
        notes.append(
            "what the passport's rate terms add (rate_terms) was taken off the recorded outputs before the "
            "comparison; the extended model does not hold them"
        )
    return dataclasses.replace(rec, **changes), lag_s


def _passport_lag(trials, lag_s: float) -> list:
    """The passport's own element lag as a catalogue term of the extended model (which replaces the passport's
    model in ``apply``), unless the search found a lag (the whole lag then)."""
    cls = next((c for c in EFFECTS.values() if c.acts_on == "temperature"), None)
    if lag_s <= 0 or cls is None or cls.nonlinear is None or any(t.effect == cls.id for t in trials):
        return []
    return [cls.make({cls.nonlinear: lag_s})]


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


def _not_explained_to_noise(design: Design, sel: Selection, settings: DiagnoseSettings) -> dict[str, float]:
    """Catalogue effects accepted beside an unexplained mismatch that neither explain the mismatch where they show
    to within the noise (:data:`WITHIN_NOISE`) nor take out most of it there (the residual RMS there at most
    :data:`LARGE_SHARE` of what the model refit without them leaves; the rest is then something else, located
    there too): effect -> the residual RMS where it shows over the noise RMS there. Such an effect only nibbles at
    a signature it does not explain (issue 14.3)."""
    after = design.y - sel.final.fitted
    out = {}
    for t in sel.accepted:
        flagged = shows_where(design, shows(design, sel, t.effect), settings)
        w = design.blocks.n[:, None] * flagged
        if not flagged.any():
            continue
        without = design.fit(tuple(s for s in sel.state if s[0] != t.effect))
        ra, rb = rms(after, w), rms(design.y - without.fitted, w)
        ratio = ra / max(rms(design.sigma, w), 1e-30)
        if ratio > WITHIN_NOISE and ra > LARGE_SHARE * rb:
            out[t.effect] = ratio
    return out


__all__ = ["DiagnoseSettings", "Diagnosis", "diagnose_run", "fit_passport", "compensate_extended"]
