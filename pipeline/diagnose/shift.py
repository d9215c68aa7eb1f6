"""Has the unit's constants moved since its passport? The first question ``diagnose`` asks of a given passport
(contract.md ``constants_shift``), before it looks for left-out physics on top.

The passport's model predicts the recording; the residual is explained, in turn, by a change of the zero offsets
U0 alone (3 per unit), of K and U0 at T0 (12), or of the whole thermal model (K, U0 and their temperature
coefficients, 12 per power of dT). Each is a linear least-squares fit of the block means
(:class:`pipeline.diagnose.fit.Design` with its base columns restricted) scored by BIC against the passport as it
is; the best is reported when it is significant against both the fit's uncertainty and the passport's own
(its ``uncertainty`` field, else :data:`DEFAULT_PASSPORT_SIGMA`). A shift inside the passport's uncertainty is
refit without a finding (the passport's constants are not exact either), and said so in a note.
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


@dataclass(frozen=True)
class Level:
    """Which constants may move: a name for people and the base-column mask (order+1, 4) per channel."""

    name: str
    powers: int          # how many powers of dT (1: the constants at T0 only; order+1: the whole thermal model)
    u0_only: bool


def levels(order: int) -> list[Level]:
    out = [Level("U0", 1, True), Level("K and U0", 1, False)]
    if order >= 1:
        out.append(Level("K, U0 and their thermal model", order + 1, False))
    return out


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
    catalogue effects already found, held in the model); the best by BIC (see the module doc). Leaves
    ``design``'s base mask as it found it."""
    order = design.order
    saved = design.base_mask.copy()
    ln_n = float(np.log(design.n_values))
    try:
        design.set_base_mask(np.zeros(4 * (order + 1), dtype=bool))
        none = design.fit(state)
        best = None
        for lv in levels(order):
            mask = level_mask(lv, order)
            design.set_base_mask(mask)
            fr = design.fit(state)
            dbic = fr.chi2 - none.chi2 + (fr.rank - none.rank) * ln_n
            if best is None or dbic < best[2]:
                best = (lv, mask, dbic, fr)
    finally:
        design.set_base_mask(saved)
    lv, mask, dbic, fr = best
    if dbic >= -threshold:
        return ShiftResult(None, np.zeros_like(mask), none, 0.0, False, {}, 0.0)
    params, z = _amounts(fr, lv, passport)
    return ShiftResult(lv, mask, fr, float(dbic), z >= SIGNIFICANT_SIGMA, params, z)


def _amounts(fr: FitResult, lv: Level, passport: dict) -> tuple[dict, float]:
    """The shift of K (V/g) and U0 (V) at T0 with 1-sigma uncertainties (the fit's, Birge-scaled when the residual
    scatters more than the block sigmas say), and the largest shift in combined sigmas (fit and passport)."""
    nb = fr.base_coef.shape[1] * 4
    sig = fr.coef_sigma()[:3 * nb].reshape(3, -1, 4)
    dof = max(fr.rw.size - fr.rank, 1)
    sig = sig * max(1.0, float(np.sqrt(fr.chi2 / dof)))
    d = fr.base_coef
    du0, du0_s = d[:, 0, 3], sig[:, 0, 3]
    dk, dk_s = d[:, 0, :3], sig[:, 0, :3]
    pk, pu = passport_sigma(passport)
    z_u = np.abs(du0) / np.sqrt(du0_s ** 2 + pu ** 2)
    params = {"constants": lv.name,
              "dU0_v": du0.tolist(), "dU0_sigma_v": du0_s.tolist()}
    z = float(np.max(z_u))
    if not lv.u0_only:
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


def explain(params: dict, rms_before_uv: float, rms_after_uv: float, z: float) -> str:
    """One or two sentences: which constants moved, by how much, how sure."""
    du0 = np.asarray(params["dU0_v"]) * _UV
    su0 = np.asarray(params["dU0_sigma_v"]) * _UV
    text = (f"The unit's constants moved since its passport ({params['constants']}): zero offsets by "
            + ", ".join(f"{a} {x:+.2f} +/- {s:.2g}" for a, x, s in zip(AXES, du0, su0)) + " uV")
    if "dK_v_per_g" in params:
        dk = np.asarray(params["dK_v_per_g"])
        text += (", gains by " + ", ".join(f"{a} {x * _UV:+.1f}" for a, x in zip(AXES, np.diagonal(dk)))
                 + " uV/g")
    if "thermal_model_change" in params:
        a1 = np.asarray(params["thermal_model_change"]["power_1"]["dU0_v_per_c"]) * _UV
        text += (", and their temperature coefficients (offsets' first-order: "
                 + ", ".join(f"{a} {x:+.3f}" for a, x in zip(AXES, a1)) + " uV/C)")
    return (text + f" ({z:.0f} sigma, the passport's own uncertainty included): refitting them takes the residual "
            f"from {rms_before_uv:.2f} to {rms_after_uv:.2f} uV RMS.")


__all__ = ["Level", "ShiftResult", "levels", "level_mask", "find_shift", "passport_sigma", "explain",
           "DEFAULT_PASSPORT_SIGMA", "SIGNIFICANT_SIGMA"]
