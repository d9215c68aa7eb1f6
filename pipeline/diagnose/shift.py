"""Has the unit's constants moved since its passport? The first question ``diagnose`` asks of a given passport
(docs/contract.md ``constants_shift``), before it looks for left-out physics on top.

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
from pipeline.model import small, small_name, small_number
from pipeline.passport.document import Passport
from pipeline.positions import AXES

#: the passport's standard uncertainty when it states none: U0 (V) and K (V/g)
DEFAULT_PASSPORT_SIGMA = {"U0": 0.3e-6, "K": 0.6e-6}
#: a shift is reported when some constant moved by more than this many combined standard uncertainties
SIGNIFICANT_SIGMA = 5.0
#: a departure of the passport's prediction larger than this many times the block noise (RMS) is a finding even
#: when the passport's own stated uncertainty allows it: the passport as given does not explain the recording
BEYOND_NOISE = 2.0
#: ... and a change some constant makes by :data:`SIGNIFICANT_SIGMA` is named only when the recording shows it: its
#: RMS over the blocks at least this many times the block noise. A drift of a few tenths of a micro-volt over a few
#: hours, "7 sigma" by the fit's own small uncertainty, improved the residual by a twentieth of the noise: against
#: a passport made from that very run, 7 of 30 clean short runs were a "mismatch" (issue 26).
VISIBLE_FRACTION = 0.5


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
    powers: int  # how many powers of dT (0: none, only a drift; 1: the constants at T0; order+1: the whole
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
    out = [Level("U0", 0, True, "U0"), Level("K and U0", 0, False, "K and U0")]  # the passport's at the start
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
        k[:, i, 3 * i : 3 * i + 3] = t_h[:, None] * design.blocks.a_g
    design.extra[RATE_U0] = ([f"rate_U0_{a}" for a in AXES], u0)
    design.extra[RATE_K] = ([f"rate_K_{a}{b_}" for a in AXES for b_ in AXES], k)


def level_mask(level: Level, order: int) -> np.ndarray:
    mask = np.zeros((order + 1, 4), dtype=bool)
    if level.u0_only:
        mask[: level.powers, 3] = True
    else:
        mask[: level.powers, :] = True
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


def passport_sigma(passport: Passport) -> tuple[np.ndarray, np.ndarray]:
    """The passport's standard uncertainty of K (3, 3) V/g and U0 (3,) V at T0 (its ``uncertainty`` where given,
    else the defaults)."""
    unc = (passport.uncertainty or {}).get("coefficients") or {}
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


def find_shift(design: Design, passport: Passport, threshold: float, state: tuple = ()) -> ShiftResult:
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
    assert best is not None  # levels() gives at least the passport's own levels
    lv, mask, dbic, fr = best
    if dbic >= -threshold:
        return ShiftResult(None, np.zeros_like(mask), none, 0.0, False, {}, 0.0)
    params, z = _amounts(fr, lv, passport, float(design.blocks.t_s.max()) / 3600.0)
    change = fr.fitted - none.fitted
    z_joint = departure_sigma(design, passport, change, max(lv.powers, 1))
    z = max(z, z_joint)
    w = design.blocks.n[:, None] * _kept(design)
    rms_change = float(np.sqrt(np.sum(w * change**2) / np.sum(w)))
    rms_noise = float(np.sqrt(np.sum(w * design.sigma**2) / np.sum(w)))
    params.update(
        departure_sigma=round(z_joint, 1),
        departure_rms_v=rms_change,
        noise_rms_v=rms_noise,
        within_passport_uncertainty=bool(z < SIGNIFICANT_SIGMA),
    )
    # beyond the noise, the passport as given does not explain the recording, whatever uncertainty it states; below
    # a visible fraction of it, no change is named however many sigmas the fit gives it
    significant = (z >= SIGNIFICANT_SIGMA and rms_change >= VISIBLE_FRACTION * rms_noise) or (
        rms_change > BEYOND_NOISE * rms_noise
    )
    return ShiftResult(lv, mask, fr, float(dbic), significant, params, z)


def _kept(design: Design) -> np.ndarray:
    """(B, 1) blocks that count (those left out of the fits carry a huge sigma)."""
    return (design.sigma < 100 * np.median(design.sigma, axis=0)).all(axis=1, keepdims=True)


def departure_sigma(design: Design, passport: Passport, change_v: np.ndarray, powers: int) -> float:
    """How far the refit model departs from the passport's, in the data (the joint test of a change of many
    correlated constants, which one by one may each look small): the RMS over blocks of the change ``change_v``
    (B, 3) V over its uncertainty, the block sigma and the passport's own uncertainty of its prediction there
    (K and U0 at T0, and each of the ``powers`` - 1 thermal coefficients that uncertainty over 30 C per power)."""
    pk, pu = passport_sigma(passport)
    a = design.blocks.a_g
    at_t0 = np.sqrt(pu[None, :] ** 2 + np.einsum("ij,bj->bi", pk**2, a**2))
    x = (design.blocks.temp_c - design.rec.normal_temp_c) / 30.0
    spread = np.sqrt(np.sum(x[:, None] ** (2 * np.arange(powers))[None, :], axis=1))
    sigma = np.sqrt(design.sigma**2 + (at_t0 * spread[:, None]) ** 2)
    w = design.blocks.n[:, None] * _kept(design)
    return float(np.sqrt(np.sum(w * (change_v / sigma) ** 2) / max(np.sum(w), 1)))


def _amounts(fr: FitResult, lv: Level, passport: Passport, duration_h: float) -> tuple[dict, float]:
    """The shift of K (V/g) and U0 (V) at T0 (at the start of the recording when they drift) with 1-sigma
    uncertainties (the fit's, Birge-scaled when the residual scatters more than the block sigmas say), and the
    largest shift in combined sigmas (fit and passport; a drift against the fit's alone: a passport has no
    rate)."""
    nb = fr.base_coef.shape[1] * 4
    birge = max(1.0, float(np.sqrt(fr.chi2 / max(fr.rw.size - fr.rank, 1))))
    sig_all = fr.coef_sigma() * birge
    sig = sig_all[: 3 * nb].reshape(3, -1, 4)
    d = fr.base_coef
    du0, du0_s = d[:, 0, 3], sig[:, 0, 3]
    dk, dk_s = d[:, 0, :3], sig[:, 0, :3]
    if lv.powers == 0:  # the passport's values at the start, held exactly
        du0_s, dk, dk_s = np.zeros(3), np.zeros((3, 3)), np.zeros((3, 3))
    pk, pu = passport_sigma(passport)
    params = {
        "constants": lv.name,
        "change": "gradual" if lv.drift else "at one time",
        "moved_before_the_recording": lv.powers > 0,
        "dU0_v": du0.tolist(),
        "dU0_sigma_v": du0_s.tolist(),
    }
    moved, z = _entries(d, sig, lv, pu, pk)
    params["moved"] = moved  # against the fit's and the passport's uncertainty
    params["beyond_fit_uncertainty"] = _entries(d, sig, lv, 0 * pu, 0 * pk)[0]
    if lv.drift:
        drift, z_d = _drift(fr, lv, passport, duration_h, nb, birge)
        z = max(z, z_d)
        drifting = [f"{name[1:]} drift" for name, zz in drift.pop("_z").items() if zz >= SIGNIFICANT_SIGMA]
        params.update(drift)
        params["moved"] += drifting
        params["beyond_fit_uncertainty"] += drifting
    if not lv.u0_only and lv.powers > 0:
        params["dK_v_per_g"] = dk.tolist()
        params["dK_sigma_v_per_g"] = np.where(np.isfinite(dk_s), dk_s, np.nan).tolist()
    if lv.powers > 1:
        params["thermal_model_change"] = {
            f"power_{n}": {
                "dK_v_per_g_per_c": d[:, n, :3].tolist(),
                "dU0_v_per_c": d[:, n, 3].tolist(),
                "sigma_dU0_v_per_c": sig[:, n, 3].tolist(),
            }
            for n in range(1, lv.powers)
        }
    return params, z


def _entries(d: np.ndarray, sig: np.ndarray, lv: Level, pu: np.ndarray, pk: np.ndarray) -> tuple[list[str], float]:
    """The entries of level ``lv`` that moved by :data:`SIGNIFICANT_SIGMA` or more, most significant first (K_ij,
    U0_i at T0, their temperature coefficients "U0_x power 1", ...) and the largest change in sigmas: the fit's
    uncertainty ``sig`` (3, order+1, 4) combined with the passport's at T0 (``pu`` V, ``pk`` V/g), over 30 C per power
    for its thermal coefficients."""
    if lv.powers == 0:
        return [], 0.0
    out: list[tuple[float, str]] = []
    z = 0.0
    for n in range(lv.powers):
        scale = 30.0**n
        su = sig[:, n, 3]
        zu = np.abs(d[:, n, 3]) / np.sqrt(su**2 + (pu / scale) ** 2)
        tail = f" power {n}" if n else ""
        z = max(z, float(np.max(zu)))
        if not lv.u0_only:
            sk = np.where(np.isfinite(sig[:, n, :3]), sig[:, n, :3], 0.0)
            zk = np.abs(d[:, n, :3]) / np.sqrt(sk**2 + (pk / scale) ** 2)
            z = max(z, float(np.max(zk)))
            out += [
                (zk[i, j], f"K_{a}{b}{tail}")
                for i, a in enumerate(AXES)
                for j, b in enumerate(AXES)
                if zk[i, j] >= SIGNIFICANT_SIGMA
            ]
        out += [(zz, f"U0_{a}{tail}") for a, zz in zip(AXES, zu) if zz >= SIGNIFICANT_SIGMA]
    return [name for _, name in sorted(out, key=lambda p: -p[0])], z


def _drift(
    fr: FitResult, lv: Level, passport: Passport, duration_h: float, nb: int, birge: float
) -> tuple[dict, float]:
    """The drift within the recording: rates per hour and the values at the end of the recording (start value +
    rate x duration, their covariance included), each with its 1-sigma uncertainty, and the largest rate in
    sigmas."""
    out = {"duration_h": duration_h, "drifting": lv.drift}
    z = 0.0
    zs: dict[str, float] = {}
    for name, term, unit in (("dU0", RATE_U0, "v"), ("dK", RATE_K, "v_per_g")):
        if term not in fr.slices:
            continue
        sl = fr.slices[term]
        rate = fr.coef[sl]
        idx = np.arange(sl.start, sl.stop)
        # the start values behind each rate: U0_i at T0 (column 3 of channel i's base), K_ij (column j)
        start_idx = np.array(
            [i * nb + (3 if name == "dU0" else j) for i in range(3) for j in ((0,) if name == "dU0" else range(3))]
        )
        cov = fr.coef_covariance(np.concatenate([start_idx, idx])) * birge**2
        k = idx.size
        rate_s = np.sqrt(np.clip(np.diagonal(cov)[k:], 0.0, None))
        start = fr.coef[start_idx]
        end = start + rate * duration_h
        end_var = (
            np.diagonal(cov)[:k] + duration_h**2 * np.diagonal(cov)[k:] + 2 * duration_h * np.diagonal(cov[:k, k:])
        )
        shape = (3,) if name == "dU0" else (3, 3)
        out[f"{name}_rate_{unit}_per_h"] = rate.reshape(shape).tolist()
        out[f"{name}_rate_sigma_{unit}_per_h"] = rate_s.reshape(shape).tolist()
        out[f"{name}_end_{unit}"] = end.reshape(shape).tolist()
        out[f"{name}_end_sigma_{unit}"] = np.sqrt(np.clip(end_var, 0.0, None)).reshape(shape).tolist()
        z_rate = np.abs(rate) / np.where(rate_s > 0, rate_s, np.inf)
        z = max(z, float(np.max(z_rate)))
        zs[name] = float(np.max(z_rate))
        if name == "dK":
            kii = np.diagonal(passport.K)
            r = np.diagonal(rate.reshape(3, 3))
            out["gain_drift_ppm_over_run"] = (r * duration_h / kii * 1e6).tolist()
            out["gain_drift_sigma_ppm_over_run"] = (
                np.diagonal(rate_s.reshape(3, 3)) * duration_h / np.abs(kii) * 1e6
            ).tolist()
    out["_z"] = zs
    return out, z


def _moved_text(params: dict, names: list[str], unit: str, most: int = 4) -> str:
    """The entries ``names`` with their amounts and uncertainty in the output unit ``unit``'s small unit (uV,
    uV/g, uV/C^n: :func:`pipeline.model.small`); the first ``most`` of them, and how many more."""
    du0, su0 = np.asarray(params["dU0_v"]), np.asarray(params["dU0_sigma_v"])
    dk = np.asarray(params.get("dK_v_per_g", np.zeros((3, 3))))
    sk = np.asarray(params.get("dK_sigma_v_per_g", np.zeros((3, 3))), dtype=float)
    thermal = params.get("thermal_model_change", {})
    parts = []
    for name in names:
        words = name.split()
        if name.startswith("U0_") and len(words) == 1:
            i = AXES.index(name[3])
            parts.append(
                f"U0 {name[3]} by {small_number(du0[i], '+.2f', unit=unit)} +/- {small(su0[i], '.2g', unit=unit)}"
            )
        elif name.startswith("K_") and len(words) == 1:
            i, j = AXES.index(name[2]), AXES.index(name[3])
            sigma = small(sk[i, j], ".2g", "/g", unit=unit)
            parts.append(f"K {name[2:4]} by {small_number(dk[i, j], '+.2f', unit=unit)} +/- {sigma}")
        elif len(words) == 3 and words[1] == "power":
            n = int(words[2])
            ch = thermal.get(f"power_{n}", {})
            if name.startswith("U0_"):
                x = ch.get("dU0_v_per_c", [0.0] * 3)[AXES.index(name[3])]
                parts.append(
                    f"U0 {name[3]}'s temperature coefficient of power {n} by {small(x, '+.4g', f'/C^{n}', unit=unit)}"
                )
            else:
                x = ch.get("dK_v_per_g_per_c", [[0.0] * 3] * 3)[AXES.index(name[2])][AXES.index(name[3])]
                amount = small(x, "+.4g", f"/g/C^{n}", unit=unit)
                parts.append(f"K {name[2:4]}'s temperature coefficient of power {n} by {amount}")
        elif not name.endswith("drift"):
            parts.append(name)
    more = len(parts) - most
    return "; ".join(parts[:most]) + (f"; and {more} more (the finding's parameters list them)" if more > 0 else "")


def explain(params: dict, rms_before: float, rms_after: float, z: float, *, unit: str) -> str:
    """Two or three sentences (``rms_before``, ``rms_after``: in the output unit ``unit``, V or m/s^2): which
    constants moved significantly (only those), by how much, how sure; what else was refit with them and agrees
    with the passport."""
    drift = params.get("drifting", "")
    moved = _moved_text(params, params.get("moved", []), unit)
    fit_moved = _moved_text(params, params.get("beyond_fit_uncertainty", []), unit)
    if not params.get("moved_before_the_recording", True):
        text = (
            f"The unit's constants ({params['constants']}) start the recording at the passport's values and "
            "drift within it"
        )
    else:
        at = " (at the start of the recording)" if drift else ""
        if params.get("within_passport_uncertainty"):
            text = (
                f"The passport's constants do not hold for this recording{at}: refit ({params['constants']}), "
                f"they change its prediction by {small(params['departure_rms_v'], '.2f', unit=unit)} RMS, "
                f"{params['departure_rms_v'] / params['noise_rms_v']:.0f} times the noise, although within "
                "the passport's own stated uncertainty (an imprecise or wrong passport, not necessarily a unit "
                "that moved)" + (f"; beyond the fit's uncertainty: {fit_moved}" if fit_moved else "") + "."
            )
        else:
            text = (
                f"The unit's constants moved since its passport{at}: "
                + (
                    moved
                    or "no single entry is "
                    f"significant on its own, but together ({params['constants']}) they depart from the passport "
                    f"by {params.get('departure_sigma', z):.0f} sigma of its prediction"
                )
                + "."
            )
        if moved and not params.get("within_passport_uncertainty"):
            text += (
                f" Refit with them ({params['constants']}), the other entries agree with the passport within "
                f"{SIGNIFICANT_SIGMA:g} sigma."
            )
    if params.get("thermal_model_note"):
        text += " " + params["thermal_model_note"]
    if drift:
        end, s_end = np.asarray(params["dU0_end_v"]), np.asarray(params["dU0_end_sigma_v"])
        rate = np.asarray(params["dU0_rate_v_per_h"])
        text += (
            f" Over the {params['duration_h']:.1f} h recording ({drift} drifting) the offsets drift at "
            + ", ".join(f"{a} {small_number(x, '+.3f', unit=unit)}" for a, x in zip(AXES, rate))
            + f" {small_name(unit)}/h to "
            + ", ".join(
                f"{a} {small_number(x, '+.2f', unit=unit)} +/- {small_number(s, '.2g', unit=unit)}"
                for a, x, s in zip(AXES, end, s_end)
            )
            + f" {small_name(unit)} at its end"
        )
        if "gain_drift_ppm_over_run" in params:
            text += (
                ", the gains by "
                + ", ".join(
                    f"{a} {x:+.1f} +/- {s:.2g}"
                    for a, x, s in zip(AXES, params["gain_drift_ppm_over_run"], params["gain_drift_sigma_ppm_over_run"])
                )
                + " ppm over it"
            )
        text += (
            " (a drift of the offsets is what the catalogue calls time_drift; against a passport it is part "
            "of the constants' change)."
        )
    return (
        text + f" Largest change {z:.0f} sigma (the passport's own uncertainty included); refitting takes the "
        f"residual from {small_number(rms_before, '.2f', unit=unit)} to {small(rms_after, '.2f', unit=unit)} RMS."
    )


__all__ = [
    "Level",
    "ShiftResult",
    "levels",
    "level_mask",
    "find_shift",
    "passport_sigma",
    "explain",
    "add_rate_columns",
    "RATE_U0",
    "RATE_K",
    "RATE_TERMS",
    "DEFAULT_PASSPORT_SIGMA",
    "SIGNIFICANT_SIGMA",
]
