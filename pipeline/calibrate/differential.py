"""Seed 003's differential method (Zhuo and Du) as a calibration method (:class:`Differential`, a
:class:`pipeline.calibrate.method.Method`): which recordings support it, the per-run step (orientation windows and
block averages, from a base passport's constants or the nominal gain) and the fit that makes the passport's
constants, thermal model, rate terms and their uncertainties.

The estimation itself is :mod:`pipeline.calibrate.differential_fit` (the equations, their least-squares fit,
compensation); without a base passport the constants at T0 come from :mod:`pipeline.calibrate.orientation_base`.
The passport maps alpha (bias, V/C^m), beta (scale, 1/C^m) and gamma (cross-axis, 1/C^m) onto the polynomial thermal
model, and the rate terms and lag onto its extra field ``rate_terms``
(:func:`pipeline.calibrate.differential_fit.compensate_differential` applies them; ``pipeline.compensate`` works on
the same passport without them).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from pipeline.calibrate.differential_fit import (
    CLUSTER_S,
    DifferentialFit,
    DifferentialSettings,
    block_data,
    fit_differential,
    nominal_gain_v_per_g,
    with_constants,
)
from pipeline.calibrate.method import Fitted, Method, Support
from pipeline.calibrate.observations import Observation, ObservedRun, observe_run, unit_of
from pipeline.calibrate.orientation_base import (
    FOLD_S,
    SCORE_MEAN_S,
    SWEEP_SETTINGS,
    OrientationBase,
    select_model,
    sweep_base,
)
from pipeline.calibrate.recording import Recording, axis_roles
from pipeline.calibrate.result import UnitFit, base_reference
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import CalibrationError
from pipeline.passport.document import Passport
from pipeline.positions import AXES, is_verification_position
from pipeline.uncertainty import ThermalSigma, as_json_list

#: The passport's ``method`` for this recipe.
METHOD = "differential"


def base_constants(base_passport: Passport, unit: str) -> tuple[np.ndarray, np.ndarray, float]:
    """K0 (3, 3) V/g, U0 (3,) V and T0 (C) of the base passport the differential method starts from (any method;
    its thermal model is not used); CalibrationError when it is of another unit or its constants are not finite."""
    if base_passport.unit not in (None, unit):
        raise CalibrationError(f"the base passport is for unit {base_passport.unit}, the runs for {unit}")
    K0, U0 = base_passport.K, base_passport.U0
    if not np.all(np.isfinite(K0)) or not np.all(np.isfinite(U0)):
        raise CalibrationError("the base passport's K must be 3x3 and U0 a 3-vector of finite numbers")
    return K0, U0, base_passport.normal_temp_c


def held_orientations(recording: Recording) -> list[dict[str, Any]]:
    """The static poses of ``recording`` (:attr:`Recording.poses`) the differential method takes: each held
    :data:`SWEEP_MIN_HOLD_S` or more through :data:`SWEEP_MIN_SPAN_C` or more."""
    return [
        p
        for p in recording.poses
        if p["longest_hold_s"] >= SWEEP_MIN_HOLD_S
        and None not in p["temp_range_c"]
        and p["temp_range_c"][1] - p["temp_range_c"][0] >= SWEEP_MIN_SPAN_C
    ]


class Differential(Method):
    """Seed 003's differential calibration: fixed orientations through a temperature cycle or sweep; starts from a
    normal-temperature passport when there is one, else from the constants the orientations determine."""

    name = "differential"
    passport_method = METHOD
    uses_base_passport = True

    def supports(self, recording: Recording) -> Support:
        """Orientations held :data:`SWEEP_MIN_HOLD_S` or more through :data:`SWEEP_MIN_SPAN_C` or more (two or
        more); per axis, whether its bias and scale factor separate (vertical in one orientation, horizontal in
        another)."""
        held = held_orientations(recording)
        roles = axis_roles(held)
        both = [ax for ax, (v, h) in roles.items() if v and h]
        ok = len(held) >= 2
        det: list[str] = []
        if ok:
            det.append("per axis: bias temperature terms (polynomial in T, rate terms)")
            det += [
                f"axis {ax}: bias and scale factor separated (vertical in one orientation, horizontal in another)"
                for ax in both
            ]
            det += [
                f"axis {ax}: scale factor and its temperature terms undetermined without --base-passport (never "
                "vertical)"
                if not roles[ax][0]
                else f"axis {ax}: bias at T0 undetermined without --base-passport (never horizontal)"
                for ax in "xyz"
                if ax not in both
            ]
            det.append(
                "cross-axis constants: undetermined without --base-passport (only their temperature terms, "
                "where the orientations excite them)"
            )
        hold_h = f"{SWEEP_MIN_HOLD_S / 3600:.0f} h"
        span = f"{SWEEP_MIN_SPAN_C:.0f} C"
        return Support(
            supported=ok,
            why=(
                f"{len(held)} orientations held {hold_h} or more through {span} or more"
                if ok
                else f"needs two or more orientations each held {hold_h} or more through {span} or more; "
                f"found {len(held)}"
            ),
            determines=tuple(det),
            preference=PREFERENCE_SWEEP if recording.program.kind == "sweep" else PREFERENCE,
        )

    def observe(
        self,
        run,
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        segmentation=None,
        differential: DifferentialSettings | None = None,
    ) -> ObservedRun:
        """The run's orientation windows and block averages (``data``, :func:`block_data`, with the base
        passport's normal-temperature constants, or without one the nominal gain and zero offsets) and its VP
        observations, if any (a run without plateaus simply has none; ``segmentation``: the run's, if already made
        with ``settings.segment``)."""
        if base_passport is None:
            K0, U0 = np.diag(nominal_gain_v_per_g([run])), np.zeros(3)
        else:
            K0, U0, _ = base_constants(base_passport, run.meta.unit_serial)
        data = block_data(run, K0, U0, differential or _settings_for(base_passport))
        try:
            observations = observe_run(run, settings.segment, segmentation)[0]
        except CalibrationError:
            observations = []
        return ObservedRun(
            meta=run.meta, source=run.source, observations=observations, warnings=list(run.warnings), data=data
        )

    def recorded_temps_c(self, observed: list[ObservedRun], observations: list[Observation]) -> list[float]:
        """The temperature range (C) the orientation windows cover, with the observations' temperatures: a sweep
        holds its orientations through the cycle, so its few static observations do not say what it spans."""
        temps = [o.temp_c for o in observations]
        for r in observed:
            for w in r.data.windows if r.data is not None else []:
                temps += [w.temp_min_c, w.temp_max_c]
        return temps

    def fit(
        self,
        observed: list[ObservedRun],
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        differential: DifferentialSettings | None = None,
    ) -> Fitted:
        """The differential fit of one unit's observed runs, from a normal-temperature passport.

        The passport's ``thermal_model`` is the polynomial of order ``differential.poly_order`` (alpha, beta, gamma),
        ``rate_terms`` holds the rate terms and lag (see :class:`RateTerms`), ``differential`` the fit's details and
        ``base_passport`` the starting passport's unit, version and method. VP segments in the runs, if any, verify it
        as usual (without rate terms).

        Without ``base_passport`` (temperature sweeps, docs/physics.md "Real recordings") the constants at T0 come from
        the orientations themselves (:func:`sweep_base`, default model :data:`SWEEP_SETTINGS`): the passport's
        ``orientation_base`` says how, and ``undetermined`` lists what the orientations cannot determine (kept at
        nominal values, never guessed).
        """
        serial = unit_of(observed)
        differential = differential or _settings_for(base_passport)
        data = [r.data for r in observed]
        orientation_base = None
        if base_passport is None:
            t0 = float(observed[0].meta.normal_temp_c)
            orientation_base = sweep_base(data, dataclasses.replace(differential, select_model=False), t0)
            K0, U0 = orientation_base.K, orientation_base.U0
            data = [with_constants(d, K0, U0) for d in data]
        else:
            K0, U0, t0 = base_constants(base_passport, serial)
        scores: list[dict] = []
        if differential.select_model:
            differential, scores = select_model(data, K0, U0, t0, differential)
        fit = fit_differential(data, K0, U0, t0, differential)
        covered = None
        if fit.windows:  # the temperatures the orientation windows went through
            covered = (
                round(min(w["temp_min_c"] for w in fit.windows), 1),
                round(max(w["temp_max_c"] for w in fit.windows), 1),
            )
        notes = list(fit.notes)
        if orientation_base is not None:
            notes.append(
                "no base passport: constants at T0 from the orientations; undetermined (kept at nominal "
                "values): " + ", ".join(orientation_base.undetermined)
            )
        unit_fit = UnitFit(
            unit=serial,
            normal_temp_c=t0,
            per_plateau=[],
            model=fit.model.static,
            skipped=notes,
            valid_temp_c=covered,
            uncertainty=fit_uncertainty(fit, base_passport=base_passport, orientation_base=orientation_base),
        )
        summary = fit.summary()
        if scores:
            summary["model_selection"] = {"folds_s": FOLD_S, "score_mean_s": SCORE_MEAN_S, "candidates": scores}
        fields: dict[str, Any] = {
            "differential": summary,
            "rate_terms": fit.model.rate.to_dict() if fit.model.rate is not None else None,
            "base_passport": (
                {
                    "unit": base_passport.unit,
                    "version": base_passport.version,
                    "method": base_passport.method,
                    "created_utc": base_passport.created_utc,
                }
                if base_passport is not None
                else None
            ),
        }
        if orientation_base is not None:
            fields["orientation_base"] = orientation_base.to_dict()
            fields["undetermined"] = list(orientation_base.undetermined)
        identity = base_reference(base_passport) if base_passport is not None else {"base_passport_sha256": None}
        return Fitted(unit_fit, passport_fields=fields, settings_extra=identity)

    def plateau_observations(self, observations):
        """The plateaus that verified the passport (the fit uses none; a sweep's drifting stretches are no
        plateaus)."""
        return [o for o in observations if is_verification_position(o.position)]


def _settings_for(base_passport: Passport | None) -> DifferentialSettings:
    return DifferentialSettings() if base_passport is not None else SWEEP_SETTINGS


#: a recording supports the differential method with two or more orientations each held this long (s) through at
#: least this temperature change (C)
SWEEP_MIN_HOLD_S = 3600.0
SWEEP_MIN_SPAN_C = 2.0
#: how much ``--method auto`` prefers the differential method (:attr:`pipeline.calibrate.method.Support.preference`):
#: first on a temperature sweep, between the tilt and the scalar method otherwise
PREFERENCE_SWEEP = 30.0
PREFERENCE = 10.0

#: the differential method, for the registry (:mod:`pipeline.calibrate.methods`)
CALIBRATION_METHOD = Differential()
observe = CALIBRATION_METHOD.observe
calibrate_observed = CALIBRATION_METHOD.calibrate_observed


def fit_uncertainty(
    fit: DifferentialFit, *, base_passport: Passport | None = None, orientation_base: OrientationBase | None = None
) -> ThermalSigma:
    """The passport's ``uncertainty`` of a differential calibration (standard uncertainties, 1 sigma, in the units
    of the fields they qualify):

    - ``coefficients`` (K, U0 at T0): the base passport's own uncertainties (the method takes its constants), or,
      without a base, the spread of the constants between the orientations that give them (std / sqrt(n); an
      offset given by four or more windows scatters about the part their cross-axis sensitivities explain);
    - ``thermal_model`` and ``rate_terms``: every fitted coefficient's standard uncertainty
      (:func:`pipeline.uncertainty.regression_cov`) over the differenced pairs (residuals clustered in :data:`CLUSTER_S`
      stretches, or the block noise measured in the data, whichever is larger), conditional on the lag when the lag was
      fitted.

    A number without a measured uncertainty is null, and ``undetermined`` says why (a term the orientations do not
    excite, a cross-axis constant the orientations cannot separate, a base passport without uncertainties, a
    constant that one orientation alone gives)."""
    undetermined: dict[str, str] = {}
    if orientation_base is not None:
        ob = orientation_base
        K_sig = np.full((3, 3), np.nan)
        K_sig[np.diag_indices(3)] = ob.std_K
        U0_sig = np.asarray(ob.std_U0, dtype=float).copy()
        for name in ob.undetermined:  # "K_xy", "U0_x": kept at nominal values
            kind, ax = name.split("_")
            if kind == "K":
                K_sig[AXES.index(ax[0]), AXES.index(ax[1])] = np.nan
            else:
                U0_sig[AXES.index(ax)] = np.nan
            undetermined[f"{kind}.{ax}"] = (
                "not determined by the orientations (no base passport): kept at its nominal value"
            )
        for i in range(3):
            for name, sig in ((f"K.{AXES[i] * 2}", K_sig[i, i]), (f"U0.{AXES[i]}", U0_sig[i])):
                if not np.isfinite(sig) and name not in undetermined:
                    undetermined[name] = (
                        "one orientation alone gives it: no second orientation checks it, and "
                        "its error is not covered by the noise and the model's uncertainty alone"
                    )
        source = (
            "no base passport: the spread between the orientations that give each constant (std / sqrt(n); an "
            "offset from four or more windows: about the part the cross-axis sensitivities explain), "
            "the thermal model's error in bringing each window to T0 and the noise of the window means, "
            "in quadrature"
        )
    else:
        base_unc = ((base_passport.uncertainty if base_passport else None) or {}).get("coefficients") or {}
        K_sig = _as_sigma(base_unc.get("K"), (3, 3))
        U0_sig = _as_sigma(base_unc.get("U0"), (3,))
        version = base_passport.version if base_passport else None
        ref = (f"base passport v{version}" if version is not None else "base passport") + (
            f" ({base_passport.method if base_passport else '-'})"
        )
        for i in range(3):
            for j in range(3):
                if not np.isfinite(K_sig[i, j]):
                    undetermined[f"K.{AXES[i]}{AXES[j]}"] = f"taken from the {ref}, which records no uncertainty for it"
            if not np.isfinite(U0_sig[i]):
                undetermined[f"U0.{AXES[i]}"] = f"taken from the {ref}, which records no uncertainty for it"
        source = f"the {ref}'s own uncertainties (the method takes its constants at T0)"
    sig = fit.sigma
    K0 = fit.model.K0
    for c in range(3):
        terms = fit.terms[c]
        if "scale" not in terms:
            undetermined[f"beta.{AXES[c] * 2}"] = (
                f"no orientation had gravity along {AXES[c]}: its scale-factor "
                "temperature terms are not determined (left at 0)"
            )
            if fit.settings.rate_order:
                undetermined[f"rate_terms.beta_rate.{AXES[c] * 2}"] = undetermined[f"beta.{AXES[c] * 2}"]
        for j in range(3):
            if j == c:
                continue
            key = AXES[c] + AXES[j]
            fitted = f"cross_{AXES[j]}" in terms
            if K0[c, j] == 0:
                undetermined[f"gamma.{key}"] = (
                    "relative to K_"
                    + key
                    + " = 0 (not known): "
                    + (
                        "fitted as the absolute rate_terms.cross_axis_abs." + key
                        if fitted
                        else "not fitted (left at 0)"
                    )
                )
            elif not fitted:
                undetermined[f"gamma.{key}"] = (
                    "cross-axis temperature terms not fitted (cross_axis off)"
                    if not fit.settings.cross_axis
                    else f"the orientations do not excite axis {AXES[j]} for channel "
                    f"{AXES[c]}: not determined (left at 0)"
                )
            if sig.rate is not None and sig.rate.cross_abs is not None and not fitted:
                undetermined[f"rate_terms.cross_axis_abs.{key}"] = "not fitted (left at 0)"
    rate = None
    if sig.rate is not None:
        rate = {
            k: v
            for k, v in as_json_list(sig.rate.to_dict()).items()
            if k in ("order", "dt_order", "alpha_rate", "beta_rate", "cross_axis_abs")
        }
        rate["lag_tau_s"] = None
        undetermined["rate_terms.lag_tau_s"] = (
            "the lag is found by a search, its uncertainty not estimated; the coefficients' uncertainties are "
            "conditional on it"
            if fit.settings.lag_fit
            else "no lag fitted (lag_fit off): 0 by setting"
        )
    basis = {
        "level": "standard uncertainty (1 sigma)",
        "coefficients": source,
        "thermal_model": "least squares over the differenced block means: the larger of the sandwich "
        "estimate from the residuals (clustered in stretches of cluster_s of each "
        "orientation window, and in stretches of twice the thermosensor's smoothing span, over which its noise "
        "is correlated) and the voltmeter noise measured in the blocks",
        "cluster_s": CLUSTER_S,
        "block_s": fit.settings.block_s,
        "residual_rms_g": fit.residual_rms_g.tolist(),
        "n_pairs": int(fit.n_pairs),
    }
    if orientation_base is not None:
        basis["identification"] = (
            "statistical uncertainties of the model the orientations identify: with few orientations, the "
            "temperature change of a cross-axis term they do not excite is folded into the fitted bias and scale "
            "terms, and the cross-axis constants left at 0 shift the offsets (and so the windows' specific force); "
            "neither can be seen in the data, so neither is in these numbers"
        )
    return ThermalSigma(
        K0=K_sig,
        U00=U0_sig,
        thermal_model=as_json_list(sig.static.to_dict()),
        birge_ratio=float("nan"),
        dof=0,
        extra={"rate_terms": rate, "undetermined": undetermined},
        basis=basis,
    )


def _as_sigma(values, shape) -> np.ndarray:
    """A passport's sigma list (None: not determined) as a float array (NaN); all NaN when absent."""
    if values is None:
        return np.full(shape, np.nan)
    try:
        a = np.array(values, dtype=float)  # None -> nan
    except (TypeError, ValueError):
        return np.full(shape, np.nan)
    return a if a.shape == shape else np.full(shape, np.nan)


calibrate = CALIBRATION_METHOD.calibrate
