"""Seed 000's tilt calibration (``tilt_six_position``): per-plateau constants from the six test positions, the
thermal model, VP verification.

The method (:class:`Tilt`, a :class:`pipeline.calibrate.method.Method`), each step a pure function:

1. ``observe`` (per run): the run's averaged static segments (:func:`pipeline.calibrate.observations.observe_run`);
2. ``fit`` (:func:`fit_unit`): per-plateau constants (six-position closed form or least squares), then the thermal
   model, with the segment averages referred to their plateau's mean temperature (the unit is still settling
   during a plateau's positions, so each position is at a slightly different temperature);
3. the tail every method shares (:meth:`pipeline.calibrate.method.Method.finish`): dg at every VP observation,
   uncompensated and by both compensation methods, the plausibility judgement and the passport document, as a
   :class:`pipeline.calibrate.result.CalibrationResult`, with what the VP data leave unverified
   (:func:`pipeline.calibrate.observations.verification_gap`). ``calibrate_observed`` is 2 then 3,
   ``calibrate(runs)`` 1, 2, 3.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipeline.calibrate.method import Fitted, Method, Support
from pipeline.calibrate.observations import (
    Observation,
    ObservedRun,
    calibration_plateaus,
    determines_constants,
    observations_from_segmentation,
    observe_run,
    plateau_groups,
    plateau_summary,
    unit_of,
    verify_unit,
)
from pipeline.calibrate.recording import Recording
from pipeline.calibrate.result import PlateauConstants, UnitFit
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.constants import fit_constants
from pipeline.errors import CalibrationError
from pipeline.passport.document import Passport
from pipeline.positions import TEST_POSITIONS, gravity_vector_g
from pipeline.run import NS_PER_S as _NS
from pipeline.segment import SHORT_HOLDS_WARNING, Segmentation, SegmentSettings, segment_run
from pipeline.thermal import ThermalModel, cluster_temperatures, default_order, fit_thermal_model
from pipeline.uncertainty import (
    ThermalSigma,
    design_matrix,
    estimator_matrix,
    excess_scatter_v,
    plateau_sigma,
    segment_noise_var_v2,
    thermal_sigma,
)
from pipeline.utc import utc_span
from pipeline.words import count_words

#: The passport's ``method`` for this recipe.
METHOD = "tilt_six_position"

__all__ = [
    "METHOD",
    "CALIBRATION_METHOD",
    "Tilt",
    "CalibrationSettings",
    "Observation",
    "ObservedRun",
    "UnitFit",
    "PlateauConstants",
    "observe",
    "calibrate_observed",
    "calibrate",
    "fit_unit",
    "observe_run",
    "observations_from_segmentation",
    "unit_of",
    "verify_unit",
    "plateau_summary",
    "calibration_plateaus",
    "determines_constants",
]


class Tilt(Method):
    """Seed 000's tilt calibration: the 12 constants per plateau from the known test positions, then the thermal
    model (this module's functions)."""

    name = "tilt"
    passport_method = METHOD

    def supports(self, recording: Recording) -> Support:
        """The soaks whose test positions determine the 12 constants, as the fit takes them (the six, or fewer by
        least squares; held while the unit still settled too); the thermal model's order is what their distinct
        temperatures allow (calibrate --thermal-model refuses a higher one). A recording whose fixture logged its
        positions is the tilt method's even where it falls short: the fit then says exactly what is missing."""
        cal = recording.constant_plateaus
        n = len(cal)
        six = sum(set(c[3]) >= {f"TP{k}" for k in range(1, 7)} for c in cal)
        temps = np.array([c[2] for c in cal])
        labels = cluster_temperatures(temps) if n else np.zeros(0, dtype=int)
        distinct = int(labels.max()) + 1 if n else 0
        order = default_order(temps) if n else 0
        at = ", ".join(f"{t:+.0f}" for t in sorted(float(np.mean(temps[labels == k])) for k in range(distinct)))
        logged = recording.fixture_logged
        return Support(
            supported=n > 0,
            why=(
                f"{count_words(n, 'plateau')} whose test positions determine the 12 constants ({six} with all "
                f"six), at {count_words(distinct, 'temperature')} ({at} C)"
                if n
                else "no temperature plateau holds test positions that determine the 12 constants (TP1..TP6, "
                "or five of them)"
            ),
            determines=(
                (
                    "K (9) and U0 (3) at each plateau temperature",
                    f"thermal model of order up to {order} (one less than the distinct temperatures, at most 3)"
                    if distinct > 1
                    else "no thermal model (one temperature)",
                )
                if n
                else ()
            ),
            preference=PREFERENCE_LOGGED if logged else PREFERENCE,
            insists="the fixture log says tilt; it will say what is missing" if logged else None,
        )

    def observe(
        self,
        run,
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        segmentation=None,
    ) -> ObservedRun:
        """The run's observations and warnings; CalibrationError for a run with no named static position on any
        plateau (``base_passport`` is not used by this method; ``segmentation``: the run's, if already made with
        ``settings.segment``)."""
        seg = segmentation if segmentation is not None else segment_run(run, settings.segment)
        obs, warnings = observe_run(run, settings.segment, seg)
        warnings += left_out_stages(seg, obs, settings.segment, run)
        return ObservedRun(meta=run.meta, source=run.source, observations=obs, warnings=warnings)

    def fit(
        self,
        observed: list[ObservedRun],
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
    ) -> Fitted:
        """:func:`fit_unit` over the observations of one unit's observed runs."""
        observations = [o for r in observed for o in r.observations]
        try:
            return Fitted(fit_unit(unit_of(observed), observations, settings, observed[0].meta.normal_temp_c))
        except CalibrationError as e:
            # positions missing because the holds were too short for the rate: say so in the refusal's line
            short = next((w for r in observed for w in r.warnings if w.startswith(SHORT_HOLDS_WARNING)), None)
            if short is None:
                raise
            why = short.removeprefix("voltmeter: ").removesuffix(": not used")
            raise CalibrationError(f"{e.message}; {why}", path=e.path, stream=e.stream, where=e.where) from None


#: how a warning of a stage the tilt method leaves out begins (:func:`left_out_stages`); ``calibrate``'s status line
#: quotes the clause before its first ": " (:func:`stage_clause`)
STAGE_LEFT_OUT = "the tilt method leaves out the "


def left_out_stages(seg: Segmentation, obs: list[Observation], settings: SegmentSettings, run=None) -> list[str]:
    """One warning per stage of the program the tilt method leaves out although the unit held test positions
    there, beyond the run's calibration plateaus (:func:`calibration_plateaus`, their temperatures ``lo .. hi``)
    by more than ``plateau_band_c``:

    - a plateau whose test positions do not determine the 12 constants (the others lost, e.g. to a data gap);
    - two or more test positions held off every plateau and off every settling at one temperature (within
      ``settle_band_c``, each hold's own spread within ``plateau_band_c``: not a ramp), e.g. a soak too short for
      the plateau test, or one whose stable part a data gap took;
    - two or more test positions the fixture log of ``run`` held in a data gap off every plateau (a stage whose
      every hold was lost), at the last temperature read before the gap.

    Pieces of these less than ``plateau_min_s`` apart and within ``settle_band_c`` of each other are one stage.
    Each warning names the stage's temperature (C), the positions and their time, why they were not used (the data
    gap of any stream within ``plateau_min_s`` of them, the temperature's rate over the holds, C/min) and how far
    (C) the thermal model is extrapolated to reach that stage. [] when the run has no calibration plateau."""
    from pipeline.calibrate.ramp import visits
    from pipeline.positions import is_test_position

    plateaus = calibration_plateaus(obs)
    if not plateaus:
        return []
    lo, hi = min(t for _, _, t, _ in plateaus), max(t for _, _, t, _ in plateaus)
    used = {(r, p) for r, p, _, _ in plateaus}
    pieces: list[tuple[float, list[str], int, int, str]] = []  # temperature C, positions, span ns, what
    for (run_id, p), rows in plateau_groups(obs).items():
        names = list(dict.fromkeys(o.position for o in rows))
        if (run_id, p) not in used and len(names) > 1:  # one position: held through the soak, not a stage
            t0, t1 = min(o.t_start_ns for o in rows), max(o.t_end_ns for o in rows)
            temp_c = float(np.mean([o.temp_c for o in rows]))
            what = (
                f"{', '.join(names)} held at {temp_c:+.1f} C ({utc_span(t0, t1)}), which do not determine the 12 "
                "constants"
            )
            pieces.append((temp_c, names, t0, t1, what))
    off = [
        h
        for h in visits(seg.segments)
        if is_test_position(h.position)
        and h.plateau is None
        and h.settling is None
        and h.temp_std_c <= settings.plateau_band_c
    ]
    groups: list[list] = []
    for h in off:
        if groups and abs(h.temp_c - groups[-1][0].temp_c) <= settings.settle_band_c:
            groups[-1].append(h)
        else:
            groups.append([h])
    for g in groups:
        names = list(dict.fromkeys(h.position for h in g))
        if len(names) < 2:
            continue
        t_min = np.array([(h.t_start_ns + h.t_end_ns) / 2 for h in g]) / _NS / 60.0
        temps = np.array([h.temp_c for h in g])
        rate = abs(float(np.polyfit(t_min, temps, 1)[0])) if np.ptp(t_min) > 0 else 0.0
        temp_c, t0, t1 = float(np.mean(temps)), g[0].t_start_ns, g[-1].t_end_ns
        what = (
            f"{', '.join(names)} held at {temp_c:+.1f} C ({utc_span(t0, t1)}) off every temperature plateau (the "
            f"temperature moved {rate:.2f} C/min there; a plateau needs below {settings.plateau_rate_c_per_min} "
            f"C/min for {settings.plateau_min_s:.0f} s of data)"
        )
        pieces.append((temp_c, names, t0, t1, what))
    gaps = _union([(a, b) for spans in seg.gaps_ns.values() for a, b in spans])
    pieces += _stages_in_gaps(seg, gaps, settings, run)
    stages: list[tuple[float, list[str], int, int, list[str]]] = []
    for temp_c, names, t0, t1, what in sorted(pieces, key=lambda x: x[2]):
        if stages:
            s_c, s_names, s0, s1, s_what = stages[-1]
            if t0 - s1 < settings.plateau_min_s * _NS and abs(temp_c - s_c) <= settings.settle_band_c:
                stages[-1] = (s_c, list(dict.fromkeys([*s_names, *names])), s0, max(s1, t1), [*s_what, what])
                continue
        stages.append((temp_c, names, t0, t1, [what]))
    out = []
    for temp_c, _names, t0, t1, whats in stages:
        beyond = lo - temp_c if temp_c < lo else temp_c - hi
        if beyond <= settings.plateau_band_c:
            continue
        margin = settings.plateau_min_s * _NS
        near = [(a, b) for a, b in gaps if a < t1 + margin and b > t0 - margin]
        lost = f"lost its test positions to the data gap {utc_span(*near[0])}" if near else "was not used"
        out.append(
            f"{STAGE_LEFT_OUT}{temp_c:+.0f} C stage, which {lost}: {'; '.join(whats)}; the calibration plateaus "
            f"cover {lo:+.1f} .. {hi:+.1f} C only, so the thermal model is extrapolated by {beyond:.0f} C to that "
            "stage"
        )
    return out


def _union(spans: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The union of the spans (first, last ns), as disjoint spans in time order."""
    out: list[tuple[int, int]] = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _stages_in_gaps(
    seg: Segmentation, gaps: list[tuple[int, int]], settings: SegmentSettings, run
) -> list[tuple[float, list[str], int, int, str]]:
    """Stages lost whole to a data gap (``gaps``: disjoint (first, last) ns) off every plateau: two or more test
    positions the fixture log of ``run`` held in the gap for ``static_min_s`` or more, at the last AU temperature
    read before it (C). [] without a run or a fixture log."""
    from pipeline.positions import is_test_position
    from pipeline.segment import _fixture_time_in_gaps

    if run is None or run.fixture is None or run.fixture.height == 0 or not gaps:
        return []
    fronts = [(p.t_start_ns if p.settle_start_ns is None else p.settle_start_ns, p.t_end_ns) for p in seg.plateaus]
    t_ns = run.au_temperature["t_ns"].to_numpy()
    temp_c = run.au_temperature["temp_c"].to_numpy()
    ok = np.isfinite(temp_c)
    t_ns, temp_c = t_ns[ok], temp_c[ok]
    out = []
    for a, b in gaps:
        if any(a < f1 and b > f0 for f0, f1 in fronts):
            continue
        held = _fixture_time_in_gaps(run.fixture, a, b, np.array([[a, b]], dtype=np.int64))
        names = [k for k, (_, inside) in held.items() if is_test_position(k) and inside >= settings.static_min_s * _NS]
        before = t_ns <= a
        if len(names) < 2 or not before.any():
            continue
        at_c = float(temp_c[before][np.argmax(t_ns[before])])
        out.append(
            (
                at_c,
                names,
                int(a),
                int(b),
                f"{', '.join(names)} held in the gap (the fixture log), at {at_c:+.1f} C before it",
            )
        )
    return out


def stage_clauses(warnings: list[str]) -> list[str]:
    """The head of each :func:`left_out_stages` warning among ``warnings`` (the text before its first ": "): which
    stage the tilt method left out and why, in a few words, for a status line."""
    return [w.split(": ", 1)[0] for w in warnings if w.startswith(STAGE_LEFT_OUT)]


#: how much ``--method auto`` prefers the tilt method (:attr:`pipeline.calibrate.method.Support.preference`): above
#: the differential method except on a sweep, below the scalar method where that one is preferred; with a fixture
#: log, above both but a sweep the differential method supports
PREFERENCE = 20.0
PREFERENCE_LOGGED = 28.0

#: the tilt method, for the registry (:mod:`pipeline.calibrate.methods`)
CALIBRATION_METHOD = Tilt()
observe = CALIBRATION_METHOD.observe
calibrate_observed = CALIBRATION_METHOD.calibrate_observed
calibrate = CALIBRATION_METHOD.calibrate


def _fit_plateaus(
    groups, shift_v: dict[int, np.ndarray], method: str, skipped: list[str] | None
) -> list[PlateauConstants]:
    fits = []
    for (run_id, p), rows in groups.items():
        names = [o.position for o in rows]
        missing = [tp for tp in TEST_POSITIONS if tp not in names]
        where = (
            f"{run_id} plateau {p} at {np.mean([o.temp_c for o in rows]):.1f} C "
            f"({utc_span(min(o.t_start_ns for o in rows), max(o.t_end_ns for o in rows))}): fewer than six "
            f"test positions (missing {', '.join(missing)})"
        )
        if missing and not determines_constants(names):
            # a position carried through the ramp onto a VP plateau is not an attempt at calibration
            if skipped is not None and len(set(names)) > 1:
                skipped.append(f"{where}; {', '.join(dict.fromkeys(names))} do not determine the 12 constants")
            continue
        if missing and skipped is not None:
            skipped.append(f"{where}; the 12 constants fitted by least squares over {', '.join(dict.fromkeys(names))}")
        u = np.array([np.asarray(o.u_v) - shift_v.get(id(o), 0.0) for o in rows])
        # one weight per segment: a position carried through a ramp and soak is a long segment taken while the
        # unit settled; it should not outweigh the program's own hold of that position. Positions missing: least
        # squares over those there are (docs/physics.md)
        cf = fit_constants(names, u, method="least_squares" if missing else method)
        fits.append(
            PlateauConstants(
                run_id=run_id,
                plateau=p,
                temp_c=float(np.mean([o.temp_c for o in rows])),
                K=cf.K,
                U0=cf.U0,
                positions=tuple(dict.fromkeys(names)),
                method=cf.method,
                residual_rms_v=float(np.sqrt(np.mean(cf.residual_v**2))),
            )
        )
    return fits


def fit_unit(
    unit: str,
    observations: list[Observation],
    settings: CalibrationSettings = CalibrationSettings(),
    normal_temp_c: float = 20.0,
) -> UnitFit:
    """Per-plateau constants and the thermal model from a unit's observations (any number of runs)."""
    groups = plateau_groups(observations)
    skipped: list[str] = []
    fits = _fit_plateaus(groups, {}, settings.constants_method, skipped)
    if not fits:
        on_plateaus = [o for rows in groups.values() for o in rows]
        where = (
            f"t_ns={min(o.t_start_ns for o in on_plateaus)}..{max(o.t_end_ns for o in on_plateaus)}"
            if on_plateaus
            else None
        )
        raise CalibrationError(
            "no temperature plateau with the six test positions TP1..TP6, nor with test "
            "positions that determine the 12 constants" + (f" ({'; '.join(skipped)})" if skipped else ""),
            path=", ".join(sorted({o.source for o in observations if o.source})) or None,
            stream="voltmeter",
            where=where,
        )

    def thermal(kind: str, temps=None, K=None, U0=None) -> ThermalModel:
        temps = np.array([f.temp_c for f in fits]) if temps is None else temps
        try:
            return fit_thermal_model(
                temps,
                np.array([f.K for f in fits]) if K is None else K,
                np.array([f.U0 for f in fits]) if U0 is None else U0,
                kind,
                normal_temp_c,
                settings.cluster_tol_c,
            )
        except ValueError as e:
            distinct = sorted({round(float(t)) for t in temps})
            raise CalibrationError(
                f"thermal model {kind}: {e}; calibration temperatures found: "
                f"{', '.join(f'{t:+d} C' for t in distinct)}",
                stream="au_temperature",
            ) from None

    for _ in range(settings.temperature_referencing_passes):
        # Refer every segment average to its plateau's mean temperature. The local slopes come from the smooth
        # default polynomial (a piecewise model's slopes are chords, wrong at the breakpoints themselves).
        shift = _referral_shifts(thermal("auto"), groups, fits)
        fits = _fit_plateaus(groups, shift, settings.constants_method, None)
    if not settings.temperature_referencing_passes:
        shift = {}
    temp_v = _temperature_noise_v(thermal("auto"), groups, fits) if shift else None
    fits, tau_v = _with_uncertainty(fits, groups, shift, temp_noise_v=temp_v)
    if shift:
        fits, tau_v = _with_uncertainty(fits, groups, shift, _referral_errors(thermal, groups, fits), temp_v)
    nominal, K_nom, U0_nom = _at_calibration_temperatures(fits, thermal("auto"), normal_temp_c, settings.cluster_tol_c)
    model = thermal(settings.thermal_model, nominal, K_nom, U0_nom)
    sigma = thermal_sigma(
        lambda t, K, U0: thermal(settings.thermal_model, t, K, U0),
        nominal,
        K_nom,
        U0_nom,
        np.array([f.K_sigma for f in fits]),
        np.array([f.U0_sigma for f in fits]),
    )
    temps = [f.temp_c for f in fits]
    sigma = _extrapolated_to_t0(sigma, temps, normal_temp_c)
    fits.sort(key=lambda f: (f.temp_c, f.run_id, f.plateau))
    return UnitFit(
        unit=unit,
        normal_temp_c=normal_temp_c,
        per_plateau=fits,
        model=model,
        skipped=skipped,
        uncertainty=sigma,
        valid_temp_c=(round(min(temps), 1), round(max(temps), 1)),
        excess_scatter_v=tau_v,
    )


def _extrapolated_to_t0(sigma: ThermalSigma, plateau_temps_c, t0_c: float) -> ThermalSigma:
    """``sigma`` with the constants at T0 (K0, U00) undetermined when T0 lies more than
    :data:`pipeline.plausibility.T0_MARGIN_C` outside the temperatures of the plateaus the constants come from (C):
    the constants at T0 are then the thermal model extrapolated beyond every plateau (one plateau at -40 C left:
    its constants, taken as T0's), an error the plateaus' noise does not contain and the data do not measure. Their
    uncertainty is null, each named in ``uncertainty.undetermined`` with why. (The plausibility check on T0,
    :func:`pipeline.plausibility.check_t0_span`, looks at every AU temperature of the runs, ramps included: a run
    through -40..70 C of which only the -40 C plateau gave constants passes it.)"""
    from pipeline.plausibility import T0_MARGIN_C

    lo, hi = float(np.min(plateau_temps_c)), float(np.max(plateau_temps_c))
    if lo - T0_MARGIN_C <= t0_c <= hi + T0_MARGIN_C:
        return sigma
    why = (
        f"T0 {t0_c:g} C lies outside the temperatures of the plateaus the constants come from ({lo:.1f}..{hi:.1f} C, "
        f"with {T0_MARGIN_C:g} C to spare): extrapolated by the thermal model, an error the data do not measure"
    )
    names = [f"K.{a}{b}" for a in "xyz" for b in "xyz"] + [f"U0.{a}" for a in "xyz"]
    extra = dict(sigma.extra or {})
    extra["undetermined"] = {**(extra.get("undetermined") or {}), **dict.fromkeys(names, why)}
    return replace(sigma, K0=np.full((3, 3), np.nan), U00=np.full(3, np.nan), extra=extra)


def _referral_shifts(local: ThermalModel, groups, fits: list[PlateauConstants]) -> dict[int, np.ndarray]:
    """Per observation (by id), the change (3,) V of its mean output from its own temperature to its plateau's
    mean temperature, by the ``local`` model: [K(T_seg) - K(T_plateau)] a + U0(T_seg) - U0(T_plateau)."""
    return {i: d[k] for ids, d in _group_shifts(local, _referral_layout(groups, fits)) for k, i in enumerate(ids)}


def _referral_layout(
    groups, fits: list[PlateauConstants]
) -> list[tuple[list[int], np.ndarray, np.ndarray, np.ndarray]]:
    """What :func:`_referral_shifts` needs of each plateau group, whatever the model: the observations' ids, their
    temperatures (C), gravity vectors (g) and their plateau's mean temperature (C) once per observation."""
    plateau_temp = {(f.run_id, f.plateau): f.temp_c for f in fits}
    return [
        (
            [id(o) for o in rows],
            np.array([o.temp_c for o in rows]),
            np.array([gravity_vector_g(o.position) for o in rows]),
            np.full(len(rows), plateau_temp[key]),
        )
        for key, rows in groups.items()
        if key in plateau_temp
    ]


def _group_shifts(local: ThermalModel, layout) -> list[tuple[list[int], np.ndarray]]:
    """Per group of :func:`_referral_layout`, the ids and the referral shifts (n, 3) V by the ``local`` model."""
    out = []
    for ids, t_seg, a, t_plateau in layout:
        Ks, U0s = local.constants_at(t_seg)
        Kp, U0p = local.constants_at(t_plateau)
        out.append((ids, np.einsum("nij,nj->ni", Ks - Kp, a) + (U0s - U0p)))
    return out


def _temperature_noise_v(local: ThermalModel, groups, fits: list[PlateauConstants]) -> dict[int, np.ndarray]:
    """Per observation (by id), the standard error (3,) V of its referral shift (:func:`_referral_shifts`) from the
    thermosensor's noise in its mean temperature (:attr:`Observation.temp_sigma_c`, C): the local model's slope
    d/dT [K(T) a + U0(T)] at the segment's temperature (V/C) times it. Independent between segments (each its own
    readings, but for the one or two that neighbouring holds share). With the thermosensor read at 1 Hz it is
    about 0.1 micro-V on a 60-s hold (0.0014 C at 1e-4 V/C); read once a minute, up to 1 micro-V, beyond the
    hold mean's noise."""
    h_c = 0.5  # (the models are polynomials of order <= 3: a central difference over +-0.5 C is their slope)
    by_id = {id(o): o for rows in groups.values() for o in rows}
    out: dict[int, np.ndarray] = {}
    for ids, t_seg, a, _ in _referral_layout(groups, fits):
        Kp, U0p = local.constants_at(t_seg + h_c)
        Km, U0m = local.constants_at(t_seg - h_c)
        slope = (np.einsum("nij,nj->ni", Kp - Km, a) + (U0p - U0m)) / (2 * h_c)
        sigma_c = np.array([by_id[i].temp_sigma_c for i in ids])
        out.update(zip(ids, np.abs(slope) * sigma_c[:, None]))
    return out


def _referral_errors(thermal, groups, fits: list[PlateauConstants]) -> dict[int, np.ndarray]:
    """Per observation (by id), the 1-sigma changes (n_moves, 3) V of its referral shift (:func:`_referral_shifts`)
    when the local model is refitted with one plateau's K column j (j = x, y, z) or U0 moved by +-1 standard
    uncertainty, one row per move. The moves are independent (a shift of channel i depends on K_ij and U0_i only),
    and within one move the changes of all segments are fully correlated (one slope error): the error of
    referring each segment to its plateau's temperature through the model's slope. The thermosensor's own noise in
    each segment's temperature is another error, independent per segment (:func:`_temperature_noise_v`).
    Measured: with 20-min soaks (positions up to 1.1 C from their
    plateau's mean) the referral error is about 0.005 micro-V against 0.3 micro-V of a segment mean's noise, so it
    moves the stored sigmas by less than 0.1 % (tests/calibrate/test_uncertainty_coverage.py); it is included all
    the same, so a program with longer excursions is covered too."""
    temps = np.array([f.temp_c for f in fits])
    K, U0 = np.array([f.K for f in fits]), np.array([f.U0 for f in fits])
    layout = _referral_layout(groups, fits)  # the same for every move: only the model changes
    kind = f"poly{thermal('auto', temps, K, U0).order}"  # "auto"'s order, which depends on the temperatures alone
    changes: list[list[np.ndarray]] = [[] for _ in layout]  # per group, per move: (n, 3)
    for p, f in enumerate(fits):
        assert f.K_sigma is not None and f.U0_sigma is not None  # set by _with_uncertainty before this is called
        for col in range(4):
            moved = []
            for sign in (1.0, -1.0):
                Kp, Up = K.copy(), U0.copy()
                if col < 3:
                    Kp[p, :, col] += sign * f.K_sigma[:, col]
                else:
                    Up[p] += sign * f.U0_sigma
                moved.append(_group_shifts(thermal(kind, temps, Kp, Up), layout))
            for g, ((_, plus), (_, minus)) in enumerate(zip(*moved)):
                changes[g].append((plus - minus) / 2.0)
    return {i: per_id for (ids, *_), c in zip(layout, changes) for i, per_id in zip(ids, np.stack(c, axis=1))}


def _with_uncertainty(
    fits: list[PlateauConstants],
    groups,
    shift_v: dict[int, np.ndarray],
    referral_v: dict[int, np.ndarray] | None = None,
    temp_noise_v: dict[int, np.ndarray] | None = None,
) -> tuple[list[PlateauConstants], np.ndarray]:
    """The plateau fits with the standard uncertainties of their constants (:mod:`pipeline.uncertainty`): the
    noise measured in each segment plus the excess scatter of the fits' residuals, pooled over the plateaus, and
    the error of referring each segment to its plateau's temperature (``referral_v``: :func:`_referral_errors`,
    propagated through the plateau's estimator with the segments' correlation) and the thermosensor's noise in
    each segment's temperature (``temp_noise_v``: :func:`_temperature_noise_v`, independent per segment, with the
    segment's own noise)."""
    parts = []
    for f in fits:
        rows = groups[(f.run_id, f.plateau)]
        names = [o.position for o in rows]
        u = np.array([np.asarray(o.u_v) - shift_v.get(id(o), 0.0) for o in rows])
        A = design_matrix(names)
        resid = u - A @ np.vstack([f.K.T, f.U0])
        parts.append(
            (
                estimator_matrix(names, f.method),
                A,
                resid,
                segment_noise_var_v2(
                    np.array([o.std_v for o in rows]),
                    np.array([o.count for o in rows]),
                    np.array([o.resolution_v for o in rows]),
                )
                + (np.array([temp_noise_v[id(o)] for o in rows]) ** 2 if temp_noise_v else 0.0),
            )
        )
    tau_v = excess_scatter_v([p[2] for p in parts], [p[3] for p in parts], [p[0] for p in parts], [p[1] for p in parts])
    out = []
    for f, (W, _, _, var) in zip(fits, parts):
        K_sig, U0_sig = plateau_sigma(W, var + tau_v**2)
        rows = groups[(f.run_id, f.plateau)]
        if referral_v and all(id(o) in referral_v for o in rows):
            moves = np.stack([referral_v[id(o)] for o in rows])  # (m, n_moves, 3)
            extra = np.sum(np.einsum("rm,mni->nri", W, moves) ** 2, axis=0)  # (4, 3): [K_.x, K_.y, K_.z, U0]
            K_sig = np.sqrt(K_sig**2 + extra[:3].T)
            U0_sig = np.sqrt(U0_sig**2 + extra[3])
        out.append(replace(f, K_sigma=K_sig, U0_sigma=U0_sig))
    return out, tau_v


def _at_calibration_temperatures(
    fits: list[PlateauConstants], local: ThermalModel, normal_temp_c: float, cluster_tol_c: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-plateau constants referred to their calibration temperature: T0 for plateaus within ``cluster_tol_c``
    of it, else the plateau cluster's mean rounded to 0.1 C. The shift uses the smooth ``local`` model; it is a few
    hundredths of a degree on a soaked plateau. Breakpoints of a piecewise model then sit at the nominal
    temperatures."""
    temps = np.array([f.temp_c for f in fits])
    labels = cluster_temperatures(temps, cluster_tol_c)
    nominal = np.array([round(float(temps[labels == lab].mean()), 1) for lab in labels])
    nominal[np.abs(nominal - normal_temp_c) <= cluster_tol_c] = normal_temp_c
    K_nom, U0_nom = local.constants_at(nominal)
    K_t, U0_t = local.constants_at(temps)
    K = np.array([f.K for f in fits]) + (K_nom - K_t)
    U0 = np.array([f.U0 for f in fits]) + (U0_nom - U0_t)
    return nominal, K, U0
