"""Has the unit's constants moved since its passport? The first question ``diagnose`` asks of a given passport
(contract.md ``constants_shift``), before it looks for left-out physics on top.

The passport's model predicts the recording; the residual is explained, in turn, by a change of the zero offsets
U0 alone (3 per unit), of K and U0 at T0 (12), or of the whole thermal model (K, U0 and their temperature
coefficients, 12 per power of dT). Each is a linear least-squares fit of the block means
(:class:`pipeline.diagnose.fit.Design` with its base columns restricted) scored by BIC against the passport as it
is; the best is reported when it is significant against both the fit's uncertainty and the passport's own
(its ``uncertainty`` field, else :data:`DEFAULT_PASSPORT_SIGMA`). A shift inside the passport's uncertainty is
refit without a finding (the passport's constants are not exact either), and said so in a note.

The constants may also move gradually within the recording (ageing, a creeping mount): each level is tried as it
is (a change at one time, before the recording) and with a drift linear in time on top of it, of U0 alone or of K
and U0 (per hour since the start of the recording; block-level columns held in ``Design.extra`` under
:data:`RATE_TERMS`). The change is then reported with its values at the start and at the end of the recording and
its rates, each with its uncertainty. A drift of U0 alone is what the catalogue calls ``time_drift`` (bias ageing):
the two are told apart by what the recording is compared with. Against a given passport the question is whether
its constants hold, so their drift is part of ``constants_shift`` (fitted before any catalogue effect, which then
cannot take it again); without a passport (fitted from the run) there is no earlier calibration to have moved
from, and a drift of the offsets within the run is ``time_drift``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.diagnose.fit import Design, FitResult
from pipeline.positions import AXES

_UV = 1e6
#: the passport's standard uncertainty when it states none: U0 (V) and K (V/g)
DEFAULT_PASSPORT_SIGMA = {"U0": 0.3e-6, "K": 0.6e-6}
#: a shift is reported when some constant moved by more than this many combined standard uncertainties
SIGNIFICANT_SIGMA = 5.0


#: the drift terms' ids in ``Design.extra``: the offsets' rate (V/h per channel), the gains' and cross-axis
#: sensitivities' rate (V/g/h, channel i, column j)
RATE_U0 = "constants_shift:rate_U0"
RATE_K = "constants_shift:rate_K"
RATE_TERMS = (RATE_U0, RATE_K)


@dataclass(frozen=True)
class Level:
    """Which constants may move: a name for people, the base-column mask (order+1, 4) per channel, and which drift
    within the recording ("", "U0" or "K and U0")."""

    name: str
    powers: int          # how many powers of dT (0: none, only a drift; 1: the constants at T0; order+1: the whole
    #                      thermal model)
    u0_only: bool
    drift: str = ""

    @property
    def terms(self) -> tuple[tuple[str, None], ...]:
        """The drift terms this level holds in the model (a fit state)."""
        return {"": (), "U0": ((RATE_U0, None),), "K and U0": ((RATE_U0, None), (RATE_K, None))}[self.drift]


def levels(order: int) -> list[Level]:
    """Drifting within the recording from the passport's values: U0; K and U0. At one time: U0; K and U0; their
    thermal model too; each also with U0, or K and U0 (not more than moved at the start), drifting on top."""
    steps = [Level("U0", 1, True), Level("K and U0", 1, False)]
    if order >= 1:
        steps.append(Level("K, U0 and their thermal model", order + 1, False))
    out = [Level("U0", 0, True, "U0"), Level("K and U0", 0, False, "K and U0")]    # the passport's at the start
    for lv in steps:
        out.append(lv)
        for drift in ("U0",) if lv.u0_only else ("U0", "K and U0"):
            out.append(Level(lv.name, lv.powers, lv.u0_only, drift))
    return out


def add_rate_columns(design: Design) -> None:
    """Register the drift columns (:data:`RATE_TERMS`) in ``design.extra``: t_h on channel i for U0_i, t_h a_j on
    channel i for K_ij (t_h: block time in hours since the start of the recording)."""
    t_h = design.blocks.t_s / 3600.0
    b = t_h.size
    u0 = np.zeros((b, 3, 3))
    k = np.zeros((b, 3, 9))
    for i in range(3):
        u0[:, i, i] = t_h
        k[:, i, 3 * i:3 * i + 3] = t_h[:, None] * design.blocks.a_g
    design.extra[RATE_U0] = ([f"rate_U0_{a}" for a in AXES], u0)
    design.extra[RATE_K] = ([f"rate_K_{a}{b_}" for a in AXES for b_ in AXES], k)


def level_mask(level: Level, order: int) -> np.ndarray:
    mask = np.zeros((order + 1, 4), dtype=bool)
    if level.u0_only:
        mask[:level.powers, 3] = True
    else:
        mask[:level.powers, :] = True
    return mask.reshape(-1)


@dataclass
class ShiftResult:
    """The chosen level (None: the passport holds), its mask, fit and dBIC, the amounts and their uncertainty,
    and whether it is significant beyond the passport's own uncertainty."""

    level: Level | None
    mask: np.ndarray
    fit: FitResult
    delta_bic: float
    significant: bool
    parameters: dict
    largest_z: float

    @property
    def terms(self) -> tuple[tuple[str, None], ...]:
        """The drift terms to hold in the model (empty: no drift, or no shift)."""
        return self.level.terms if self.level is not None else ()


def passport_sigma(passport: dict) -> tuple[np.ndarray, np.ndarray]:
    """The passport's standard uncertainty of K (3, 3) V/g and U0 (3,) V at T0 (its ``uncertainty`` field where
    given, else the defaults)."""
    unc = ((passport.get("uncertainty") or {}).get("coefficients") or {})
    k = np.full((3, 3), DEFAULT_PASSPORT_SIGMA["K"])
    u = np.full(3, DEFAULT_PASSPORT_SIGMA["U0"])
    try:
        if unc.get("K") is not None:
            k = np.where(np.isfinite(a := np.asarray(unc["K"], dtype=float)), a, k)
        if unc.get("U0") is not None:
            u = np.where(np.isfinite(a := np.asarray(unc["U0"], dtype=float)), a, u)
    except (TypeError, ValueError):
        pass
    return k, u


def find_shift(design: Design, passport: dict, threshold: float, state: tuple = ()) -> ShiftResult:
    """Fit every level of constants shift against the passport as it is (with the terms of ``state``, e.g.
    catalogue effects already found, held in the model; drift terms in it are replaced); the best by BIC (see the
    module doc). Leaves ``design``'s base mask as it found it and its drift columns registered."""
    order = design.order
    saved = design.base_mask.copy()
    ln_n = float(np.log(design.n_values))
    state = tuple(s for s in state if s[0] not in RATE_TERMS)
    add_rate_columns(design)
    try:
        design.set_base_mask(np.zeros(4 * (order + 1), dtype=bool))
        none = design.fit(state)
        best = None
        for lv in levels(order):
            mask = level_mask(lv, order)
            design.set_base_mask(mask)
            fr = design.fit(lv.terms + state)
            dbic = fr.chi2 - none.chi2 + (fr.rank - none.rank) * ln_n
            if best is None or dbic < best[2]:
                best = (lv, mask, dbic, fr)
    finally:
        design.set_base_mask(saved)
    lv, mask, dbic, fr = best
    if dbic >= -threshold:
        return ShiftResult(None, np.zeros_like(mask), none, 0.0, False, {}, 0.0)
    params, z = _amounts(fr, lv, passport, float(design.blocks.t_s.max()) / 3600.0)
    return ShiftResult(lv, mask, fr, float(dbic), z >= SIGNIFICANT_SIGMA, params, z)


def _amounts(fr: FitResult, lv: Level, passport: dict, duration_h: float) -> tuple[dict, float]:
    """The shift of K (V/g) and U0 (V) at T0 (at the start of the recording when they drift) with 1-sigma
    uncertainties (the fit's, Birge-scaled when the residual scatters more than the block sigmas say), and the
    largest shift in combined sigmas (fit and passport; a drift against the fit's alone: a passport has no
    rate)."""
    nb = fr.base_coef.shape[1] * 4
    birge = max(1.0, float(np.sqrt(fr.chi2 / max(fr.rw.size - fr.rank, 1))))
    sig_all = fr.coef_sigma() * birge
    sig = sig_all[:3 * nb].reshape(3, -1, 4)
    d = fr.base_coef
    du0, du0_s = d[:, 0, 3], sig[:, 0, 3]
    dk, dk_s = d[:, 0, :3], sig[:, 0, :3]
    if lv.powers == 0:            # the passport's values at the start, held exactly
        du0_s, dk, dk_s = np.zeros(3), np.zeros((3, 3)), np.zeros((3, 3))
    pk, pu = passport_sigma(passport)
    z_u = np.abs(du0) / np.sqrt(du0_s ** 2 + pu ** 2)
    params = {"constants": lv.name, "change": "gradual" if lv.drift else "at one time",
              "moved_before_the_recording": lv.powers > 0,
              "dU0_v": du0.tolist(), "dU0_sigma_v": du0_s.tolist()}
    z = float(np.max(z_u))
    if lv.drift:
        drift, z_d = _drift(fr, lv, passport, duration_h, nb, birge)
        params.update(drift)
        z = max(z, z_d)
    if not lv.u0_only and lv.powers > 0:
        z_k = np.abs(dk) / np.sqrt(np.where(np.isfinite(dk_s), dk_s, 0.0) ** 2 + pk ** 2)
        z = max(z, float(np.max(z_k)))
        params["dK_v_per_g"] = dk.tolist()
        params["dK_sigma_v_per_g"] = np.where(np.isfinite(dk_s), dk_s, np.nan).tolist()
    for n in range(1, lv.powers):     # the passport's thermal coefficients: its T0 uncertainty over 30 C per power
        s_pass_u, s_pass_k = pu / 30.0 ** n, pk / 30.0 ** n
        su, sk = sig[:, n, 3], np.where(np.isfinite(sig[:, n, :3]), sig[:, n, :3], 0.0)
        z = max(z, float(np.max(np.abs(d[:, n, 3]) / np.sqrt(su ** 2 + s_pass_u ** 2))),
                float(np.max(np.abs(d[:, n, :3]) / np.sqrt(sk ** 2 + s_pass_k ** 2))))
    if lv.powers > 1:
        params["thermal_model_change"] = {
            f"power_{n}": {"dK_v_per_g_per_c": d[:, n, :3].tolist(), "dU0_v_per_c": d[:, n, 3].tolist(),
                           "sigma_dU0_v_per_c": sig[:, n, 3].tolist()}
            for n in range(1, lv.powers)}
    return params, z


def _drift(fr: FitResult, lv: Level, passport: dict, duration_h: float, nb: int, birge: float
           ) -> tuple[dict, float]:
    """The drift within the recording: rates per hour and the values at the end of the recording (start value +
    rate x duration, their covariance included), each with its 1-sigma uncertainty, and the largest rate in
    sigmas."""
    out = {"duration_h": duration_h, "drifting": lv.drift}
    z = 0.0
    for name, term, unit in (("dU0", RATE_U0, "v"), ("dK", RATE_K, "v_per_g")):
        if term not in fr.slices:
            continue
        sl = fr.slices[term]
        rate = fr.coef[sl]
        idx = np.arange(sl.start, sl.stop)
        # the start values behind each rate: U0_i at T0 (column 3 of channel i's base), K_ij (column j)
        start_idx = np.array([i * nb + (3 if name == "dU0" else j) for i in range(3)
                              for j in ((0,) if name == "dU0" else range(3))])
        cov = fr.coef_covariance(np.concatenate([start_idx, idx])) * birge ** 2
        k = idx.size
        rate_s = np.sqrt(np.clip(np.diagonal(cov)[k:], 0.0, None))
        start = fr.coef[start_idx]
        end = start + rate * duration_h
        end_var = (np.diagonal(cov)[:k] + duration_h ** 2 * np.diagonal(cov)[k:]
                   + 2 * duration_h * np.diagonal(cov[:k, k:]))
        shape = (3,) if name == "dU0" else (3, 3)
        out[f"{name}_rate_{unit}_per_h"] = rate.reshape(shape).tolist()
        out[f"{name}_rate_sigma_{unit}_per_h"] = rate_s.reshape(shape).tolist()
        out[f"{name}_end_{unit}"] = end.reshape(shape).tolist()
        out[f"{name}_end_sigma_{unit}"] = np.sqrt(np.clip(end_var, 0.0, None)).reshape(shape).tolist()
        z = max(z, float(np.max(np.abs(rate) / np.where(rate_s > 0, rate_s, np.inf))))
        if name == "dK":
            kii = np.diagonal(np.asarray(passport["coefficients"]["K"], dtype=float))
            r = np.diagonal(rate.reshape(3, 3))
            out["gain_drift_ppm_over_run"] = (r * duration_h / kii * 1e6).tolist()
            out["gain_drift_sigma_ppm_over_run"] = (np.diagonal(rate_s.reshape(3, 3)) * duration_h
                                                    / np.abs(kii) * 1e6).tolist()
    return out, z


def explain(params: dict, rms_before_uv: float, rms_after_uv: float, z: float) -> str:
    """One or two sentences: which constants moved, by how much, how sure."""
    du0 = np.asarray(params["dU0_v"]) * _UV
    su0 = np.asarray(params["dU0_sigma_v"]) * _UV
    drift = params.get("drifting", "")
    if not params.get("moved_before_the_recording", True):
        text = (f"The unit's constants ({params['constants']}) start the recording at the passport's values and "
                "drift within it")
    else:
        at = " at the start of the recording" if drift else ""
        text = (f"The unit's constants moved since its passport ({params['constants']}"
                + (f"; {drift} drifting within the recording" if drift else "") + f"): zero offsets{at} by "
                + ", ".join(f"{a} {x:+.2f} +/- {s:.2g}" for a, x, s in zip(AXES, du0, su0)) + " uV")
    if "dK_v_per_g" in params:
        dk = np.asarray(params["dK_v_per_g"])
        text += (", gains by " + ", ".join(f"{a} {x * _UV:+.1f}" for a, x in zip(AXES, np.diagonal(dk)))
                 + " uV/g")
    if "thermal_model_change" in params:
        a1 = np.asarray(params["thermal_model_change"]["power_1"]["dU0_v_per_c"]) * _UV
        text += (", and their temperature coefficients (offsets' first-order: "
                 + ", ".join(f"{a} {x:+.3f}" for a, x in zip(AXES, a1)) + " uV/C)")
    if drift:
        end = np.asarray(params["dU0_end_v"]) * _UV
        s_end = np.asarray(params["dU0_end_sigma_v"]) * _UV
        rate = np.asarray(params["dU0_rate_v_per_h"]) * _UV
        text += (f"; over the {params['duration_h']:.1f} h recording they drift at "
                 + ", ".join(f"{a} {x:+.3f}" for a, x in zip(AXES, rate)) + " uV/h to "
                 + ", ".join(f"{a} {x:+.2f} +/- {s:.2g}" for a, x, s in zip(AXES, end, s_end)) + " uV at its end")
        if "gain_drift_ppm_over_run" in params:
            text += (", the gains by " + ", ".join(
                f"{a} {x:+.1f} +/- {s:.2g}" for a, x, s in zip(AXES, params["gain_drift_ppm_over_run"],
                                                                 params["gain_drift_sigma_ppm_over_run"]))
                     + " ppm over it")
        text += (" (a drift of the offsets is what the catalogue calls time_drift; against a passport it is part "
                 "of the constants' change)")
    return (text + f" ({z:.0f} sigma, the passport's own uncertainty included): refitting them takes the residual "
            f"from {rms_before_uv:.2f} to {rms_after_uv:.2f} uV RMS.")


__all__ = ["Level", "ShiftResult", "levels", "level_mask", "find_shift", "passport_sigma", "explain",
           "add_rate_columns", "RATE_U0", "RATE_K", "RATE_TERMS",
           "DEFAULT_PASSPORT_SIGMA", "SIGNIFICANT_SIGMA"]
