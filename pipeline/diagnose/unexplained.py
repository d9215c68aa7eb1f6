"""The open world: a located mismatch that no catalogue effect explains is reported as ``unexplained``
(docs/contract.md), with its signature and the fit improvement of a generic empirical correction, labelled as empirical.

After the catalogue search, the residual is offered generic corrections (:func:`families`), each a set of block-level
columns per axis, scored by BIC against the model with the accepted catalogue effects:

- ``step``: a step of the offsets at one time (the best split of the residual), per axis;
- ``time`` / ``time_fine``: a piecewise-linear function of time (knots every :data:`KNOT_S` or a quarter of it),
  per axis: random walks, drifts of any shape;
- ``periodic``: a sinusoid per axis at the period where the residual's periodogram peaks (2 min to 3 h, at most
  a third of the record);
- ``orientation``: an offset per position and axis;
- ``temperature``: powers of dT beyond the base polynomial, per axis.

When one improves the fit beyond :data:`THRESHOLD` and blocks still stand out of the noise, the mismatch is outside
the catalogue: the catalogue search is redone with that correction held in the model (so that no catalogue effect is
kept only for absorbing part of it), and the correction is reported with the signature of what it absorbed: where
(windows, axes, temperatures, positions), how large, and which share of it is a function of time, of temperature,
of the direction of temperature change, and of orientation.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.signal import lombscargle

from pipeline.diagnose.fit import Design, FitResult
from pipeline.model import small, small_name, small_number
from pipeline.positions import AXES, POSITION_NAMES

#: knot spacing of the empirical function of time, s (wider on long records: at most MAX_KNOTS knots)
KNOT_S = 1800.0
MAX_KNOTS = 48
#: dBIC beyond which an empirical correction shows a mismatch outside the catalogue
THRESHOLD = 100.0
#: periods searched for a periodic disturbance, s
PERIODS_S = (120.0, 3 * 3600.0)


def _per_axis(basis: np.ndarray) -> np.ndarray:
    """(B, k) basis -> (B, 3, 3k) columns acting on one axis each."""
    b, k = basis.shape
    cols = np.zeros((b, 3, 3 * k))
    for i in range(3):
        cols[:, i, i * k : (i + 1) * k] = basis
    return cols


def _labels(name: str, k: int) -> list[str]:
    return [f"{name}_{a}{j}" for a in AXES for j in range(k)]


def time_basis(t_s: np.ndarray, knot_s: float = KNOT_S) -> np.ndarray:
    """Hat functions (B, k) of a piecewise-linear function of time with knots every ``knot_s``."""
    t0, t1 = float(t_s.min()), float(t_s.max())
    knots = np.linspace(t0, t1, max(2, int(np.ceil((t1 - t0) / knot_s)) + 1))
    eye = np.eye(knots.size)
    return np.stack([np.interp(t_s, knots, eye[j]) for j in range(knots.size)], axis=1)


def best_period_s(t_s: np.ndarray, r: np.ndarray, w: np.ndarray) -> float | None:
    """The period (s) where the weighted residual's Lomb-Scargle periodogram, summed over the axes, peaks (periods
    from 2 min to 3 h and at most a third of the record); None for a record shorter than three of the shortest."""
    longest = min(PERIODS_S[1], float(np.ptp(t_s)) / 3)
    if longest <= PERIODS_S[0]:
        return None
    ys = [(r[:, i] - np.average(r[:, i], weights=w[:, i])) * np.sqrt(w[:, i] / w[:, i].mean()) for i in range(3)]

    def peak(periods: np.ndarray) -> int:
        freqs = 2 * np.pi / periods
        return int(np.argmax(sum(lombscargle(t_s, y, freqs) for y in ys)))

    periods = np.geomspace(PERIODS_S[0], longest, 400)
    k = peak(periods)
    # refined to a small fraction of a cycle over the record: a period 1 % off drifts half a cycle in 50 cycles
    step = periods[1] / periods[0]
    fine = np.geomspace(periods[k] / step**1.5, periods[k] * step**1.5, 301)
    return float(fine[peak(fine)])


def families(design: Design, current: FitResult) -> dict[str, tuple[list[str], np.ndarray, dict]]:
    """The generic corrections: id -> (labels, (B, 3, p) columns, description)."""
    b = design.blocks
    out: dict[str, tuple[list[str], np.ndarray, dict]] = {}
    coarse = max(KNOT_S, float(np.ptp(b.t_s)) / MAX_KNOTS)
    for fid, knot in (("empirical:time", coarse), ("empirical:time_fine", coarse / 4)):
        tb = time_basis(b.t_s, knot)
        out[fid] = (_labels("t", tb.shape[1]), _per_axis(tb), {"knot_s": knot})
    r = design.y - current.fitted
    w = 1.0 / design.sigma**2
    t_step, size, _ = best_step(b.t_s, r, w)
    out["empirical:step"] = (
        _labels("step", 1),
        _per_axis((b.t_s >= t_step).astype(float)[:, None]),
        {"step_at_h": t_step / 3600.0},
    )
    period = best_period_s(b.t_s, r, w)
    if period is not None:
        out["empirical:periodic"] = _periodic_family(b.t_s, period)
    present = [int(p) for p in np.unique(b.position_idx) if p >= 0]
    pb = np.stack([(b.position_idx == p).astype(float) for p in present], axis=1)
    out["empirical:orientation"] = (
        _labels("pos", len(present)),
        _per_axis(pb),
        {"positions": [POSITION_NAMES[p] for p in present]},
    )
    dt = b.temp_c - design.rec.normal_temp_c
    scale = max(float(np.max(np.abs(dt))), 1.0)
    powers = np.stack([(dt / scale) ** (design.order + 1 + k) for k in range(2)], axis=1)
    out["empirical:temperature"] = (
        _labels("dT", 2),
        _per_axis(powers),
        {"powers": [design.order + 1, design.order + 2]},
    )
    return out


def find_unexplained(
    design: Design, current: FitResult, locate_sigma: float, threshold: float = THRESHOLD
) -> tuple[str, dict, float, list[dict]] | None:
    """The best generic correction when the residual after the catalogue still stands out (see the module doc):
    (id, description, dBIC, scores of all families), or None. Registers the chosen columns in ``design.extra``."""
    z = np.abs(design.y - current.fitted) / design.sigma
    if not np.any(z > locate_sigma):
        return None
    ln_n = float(np.log(design.n_values))
    scores: list[dict[str, Any]] = []
    fams = families(design, current)
    if "empirical:periodic" in fams:
        fams["empirical:periodic"] = _refined_periodic(design, current, fams["empirical:periodic"][2]["period_s"])
    for fid, (labels, cols, _desc) in fams.items():
        design.extra[fid] = (labels, cols)
        chi2, added, _, _, _ = design.score(current, fid, None)
        scores.append(
            {"correction": fid, "delta_bic": round(float(chi2 - current.chi2 + added * ln_n), 1), "rank": int(added)}
        )
        del design.extra[fid]
    best = min(scores, key=lambda s: s["delta_bic"])
    if best["delta_bic"] >= -threshold or best["rank"] == 0:
        return None
    fid = best["correction"]
    labels, cols, desc = fams[fid]
    design.extra[fid] = (labels, cols)
    return fid, desc, best["delta_bic"], scores


def _periodic_family(t_s: np.ndarray, period_s: float) -> tuple[list[str], np.ndarray, dict]:
    ph = 2 * np.pi * t_s / period_s
    return (_labels("sc", 2), _per_axis(np.stack([np.sin(ph), np.cos(ph)], axis=1)), {"period_s": period_s})


def _refined_periodic(design: Design, current: FitResult, period_s: float) -> tuple[list[str], np.ndarray, dict]:
    """The periodic family at the period that minimises chi2 jointly with the current model (the periodogram's
    peak is of the residual alone), searched within 1 % of ``period_s``."""
    fid = "empirical:periodic"

    def chi2(log_p: float) -> float:
        design.extra[fid] = _periodic_family(design.blocks.t_s, float(np.exp(log_p)))[:2]
        try:
            return design.score(current, fid, None)[0]
        finally:
            del design.extra[fid]

    x0 = float(np.log(period_s))
    res = minimize_scalar(chi2, bounds=(x0 - 0.01, x0 + 0.01), method="bounded", options={"xatol": 1e-5})
    best = float(np.exp(res.x)) if res.fun < chi2(x0) else period_s
    return _periodic_family(design.blocks.t_s, best)


def shares(design: Design, signature: np.ndarray, flagged_axes: np.ndarray) -> tuple[dict[str, float], dict]:
    """Which share of the signature's weighted variance (on the axes where it shows) is a function of time, of
    temperature, of the direction of temperature change, and of orientation; and the time features found.

    Each is a least-squares fit of a basis: time, a slow piecewise-linear function (knots every :data:`KNOT_S`),
    the best single step and a sinusoid (with its second harmonic) at the signature's dominant period, so that a
    wander, a step and a periodic disturbance are all functions of time; temperature, powers 0..3 of dT;
    direction, the sign of the last ramp; orientation, an offset per position. The bases overlap (a step is also
    partly an offset per temperature), so the shares are sequential: the kind that explains most alone takes its
    share, each next one only what it adds to those before (type-I sums of squares); they sum to at most 1. The
    dominant period (s), the share the sinusoid at it explains alone, and the step's time (h) are returned with the
    share each kind explains alone."""
    b = design.blocks
    w = 1.0 / design.sigma**2
    axes = np.flatnonzero(flagged_axes)
    dt = b.temp_c - design.rec.normal_temp_c
    scale = max(float(np.max(np.abs(dt))), 1.0)
    ramp = design.blocks.mean(design.rec.ramp_sign.astype(float))
    present = [int(p) for p in np.unique(b.position_idx) if p >= 0]
    t_step, _, step_share = best_step(b.t_s, signature[:, axes], w[:, axes])
    period = best_period_s(b.t_s, signature, w) if axes.size else None
    time_cols = [time_basis(b.t_s), (b.t_s >= t_step).astype(float)[:, None]]
    periodic = None
    if period is not None:
        ph = 2 * np.pi * b.t_s / period
        periodic = np.stack([np.sin(ph), np.cos(ph), np.sin(2 * ph), np.cos(2 * ph)], axis=1)
        time_cols.append(periodic)
    bases = {
        "time": np.concatenate(time_cols, axis=1),
        "temperature": np.stack([(dt / scale) ** k for k in range(4)], axis=1),
        "direction of temperature change": np.stack([np.ones(b.size), ramp], axis=1),
        "orientation": np.stack([(b.position_idx == p).astype(float) for p in present], axis=1),
    }
    sw = np.sqrt(w[:, axes])  # (B, a)
    y = signature[:, axes] * sw
    mean = np.sum(y * sw, axis=0) / np.sum(sw * sw, axis=0)
    yc = y - mean * sw
    total = float(np.sum(yc**2))

    def explained(names: list[str], extra: Sequence[np.ndarray] = ()) -> float:
        """Weighted sum of squares (about the mean) a joint fit of the bases ``names`` (and ``extra``) explains."""
        if not (names or extra) or total <= 0:
            return 0.0
        basis = np.concatenate([np.ones((b.size, 1))] + [bases[n] for n in names] + list(extra), axis=1)
        out = 0.0
        for k in range(axes.size):
            xw = basis * sw[:, k : k + 1]
            coef, *_ = np.linalg.lstsq(xw, y[:, k], rcond=None)
            res = y[:, k] - xw @ coef
            out += float(np.sum(yc[:, k] ** 2) - np.sum(res**2))
        return max(out, 0.0)

    alone = {n: explained([n]) / total if total > 0 else 0.0 for n in bases}
    out, taken, have = {}, [], 0.0
    for n in sorted(bases, key=lambda n: -alone[n]):
        taken.append(n)
        now = explained(taken)
        out[n] = round(max(now - have, 0.0) / total, 3) if total > 0 else 0.0
        have = max(have, now)
    features = {
        "alone": {n: round(v, 3) for n, v in alone.items()},
        "dominant_period_s": period,
        "periodic_share": round(explained([], [periodic]) / total, 3) if periodic is not None and total > 0 else 0.0,
        "step_at_h": t_step / 3600.0,
        "step_share": round(step_share, 3),
    }
    return out, features


def best_step(t_s: np.ndarray, r: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray, float]:
    """The single step in time that best explains the residual ``r`` (B, 3): its time (s), size per axis (V), and
    the share of the residual's weighted variance it explains."""
    order = np.argsort(t_s)
    t, r, w = t_s[order], r[order], w[order]
    cw = np.cumsum(w, axis=0)
    cwr = np.cumsum(w * r, axis=0)
    tot_w, tot_wr = cw[-1], cwr[-1]
    n1, s1 = cw[:-1], cwr[:-1]
    n2, s2 = tot_w - n1, tot_wr - s1
    gain = (s1**2 / n1 + s2**2 / n2 - tot_wr**2 / tot_w).sum(axis=1)  # chi2 reduction of each split
    k = int(np.argmax(gain))
    size = s2[k] / n2[k] - s1[k] / n1[k]
    var = float(np.sum(w * (r - tot_wr / tot_w) ** 2))
    return float(0.5 * (t[k] + t[k + 1])), size, float(gain[k] / var) if var > 0 else 0.0


def describe(
    fid: str,
    desc: dict,
    residual: np.ndarray,
    design: Design,
    share: dict[str, float],
    where: dict,
    peak: float,
    period_s: float | None = None,
    *,
    unit: str,
) -> tuple[str, dict]:
    """Sentences for a person (what the residual looks like, where, how large; labelled empirical) and the
    numbers behind them. ``peak``: in the output unit ``unit`` (V or m/s^2)."""
    axes = "/".join(where["axes"]) or "no axis"
    ranked = sorted(share.items(), key=lambda kv: -kv[1])
    kind = fid.split(":", 1)[1]
    extra: dict = {}
    if kind == "step":
        t_step = desc["step_at_h"] * 3600.0
        size = np.asarray(desc["coef"], dtype=float)[:3]
        shape = (
            f"a step at about {t_step / 3600:.2f} h into the run of "
            + ", ".join(f"{a} {small_number(x, '+.1f', unit=unit)}" for a, x in zip(AXES, size))
            + f" {small_name(unit)}"
        )
        extra = {"step_v": size.tolist()}
    elif kind.startswith("time"):
        shape = f"a wander over time (an empirical function of time with knots every {desc['knot_s'] / 60:.0f} min)"
    elif kind == "periodic":
        shape = f"periodic, with a period of about {desc['period_s'] / 60:.1f} min"
    elif kind == "orientation":
        shape = "a different offset in each orientation"
    else:
        shape = "a function of temperature beyond the base polynomial"
    temps = ", ".join(f"{t:+.0f}" for t in where["temps_c"]) or "-"
    signature = f"Of its variance, {ranked[0][1]:.0%} is a function of {ranked[0][0]}"
    if ranked[1][1] >= 0.05:
        signature += f", {ranked[1][1]:.0%} more of {ranked[1][0]}"
    if ranked[0][0] == "time" and period_s is not None and kind != "periodic":
        signature += f" (its dominant period: {period_s / 60:.1f} min)"
    return (
        f"A mismatch no catalogue effect explains: {shape}, up to {small(peak, unit=unit)} on {axes} (temperatures "
        f"{temps} C). {signature}. An empirical correction ({kind}, not physics) takes it out."
    ), extra


__all__ = [
    "KNOT_S",
    "THRESHOLD",
    "families",
    "find_unexplained",
    "shares",
    "describe",
    "time_basis",
    "best_period_s",
    "best_step",
]
