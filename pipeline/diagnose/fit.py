"""The statistics of ``diagnose``: the base model refit jointly with catalogue terms, scored by BIC, greedy.

The base model is linear in its coefficients: per channel i,

    U_i = sum_{n=0..order} dT^n (sum_j c_nij a_j + d_ni)          (dT = T - T0, or T_e - T0 with thermal lag)

so on block means (:class:`pipeline.diagnose.signal.Blocks`) it is a weighted linear least-squares problem, exact
block by block (the specific force is constant inside a block, and the block means of dT^n are taken over the
micro-samples). It is fitted as a correction to a reference model (the passport's), which keeps the numbers small.
Each catalogue term adds linear columns (the effect's ``fit_columns``, :mod:`pipeline.effects`) and at most one
nonlinear time constant, found on a log grid and refined. A term is scored against the current model by

    dBIC = chi2(with the term) - chi2(without) + (added rank + nonlinear parameters) ln(N)

with N the number of block values, the joint fit of base, accepted terms and candidate being computed by
projecting the candidate's columns off the current model (Frisch-Waugh-Lovell: the same coefficients and chi2 as
refitting everything). A term is accepted when dBIC < -``threshold`` and its fitted values are physically
plausible (time constants inside the searched range, sizes within physical limits). Selection is greedy: the best
term is accepted, the model refitted, and the search repeated; after the first effect the threshold is at least
``imperfection_rel`` of its dBIC (a model that explains a large effect to 0.3 % of its size leaves residuals that
other terms would gladly absorb). Terms whose fitted contributions are nearly
collinear with the accepted one's (cosine above ``confound_cos``) and whose score is within the confounding
margin of it are confounded under the run's program: reported with it, not accepted separately.

Sums over the blocks are matrix products (:func:`_gram`, :func:`_per_channel_gram`: BLAS; a recording of days has
tens of thousands of blocks, where ``numpy.einsum``'s own loops took 80 % of diagnose's time); ``diagnose_run``
holds BLAS to one thread (a threaded BLAS on a busy machine is slower than one core).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from pipeline.diagnose.signal import Blocks, StaticRecord
from pipeline.effects.catalogue import effect_class


def _flat(a: np.ndarray) -> np.ndarray:
    """(B, 3, p) or (B, 3) as (3 B, p) or (3 B, 1) (p may be 0)."""
    return a.reshape(a.shape[0] * a.shape[1], a.shape[2] if a.ndim == 3 else 1)


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum over blocks and channels of a[b, i, p] b[b, i, q] -> (p, q) (``a``, ``b``: (B, 3, .) or (B, 3))."""
    return _flat(a).T @ _flat(b)


def _per_channel_gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum over blocks of a[b, i, k] b[b, i, c] -> (3, k, c), channel by channel."""
    return np.matmul(a.transpose(1, 2, 0), b.transpose(1, 0, 2))


#: eigenvalues of a (unit-column) normal matrix below this are combinations the data cannot tell apart
_RANK_TOL = 1e-10


@dataclass(frozen=True)
class SelectionSettings:
    """Thresholds of the greedy selection (dBIC beyond the BIC penalty; confounding)."""

    threshold: float = 20.0
    imperfection_rel: float = 1e-5
    confound_cos: float = 0.9
    confound_margin_rel: float = 0.02
    confound_margin_abs: float = 20.0


@dataclass
class FitResult:
    """One weighted least-squares fit of the base plus the terms of ``state``.

    ``coef`` per column (the 3 x nb base columns, channel by channel, then the terms'), ``chi2``, ``rank``,
    ``fitted`` (B, 3) V; for each term its column slice and labels; ``base_coef`` (3, order+1, 4) the correction
    to the reference model per channel and power: c_n,i,j (V/g/C^n, j = x, y, z) and d_n,i (V/C^n). ``rw`` (B, 3)
    is the weighted residual; the weighted unit-norm columns and the kept eigen-pairs of their normal matrix are
    kept to project further terms off this fit (:meth:`project`).
    """

    state: tuple[tuple[str, float | None], ...]
    coef: np.ndarray
    chi2: float
    rank: int
    fitted: np.ndarray
    slices: dict[str, slice]
    labels: dict[str, list[str]]
    base_coef: np.ndarray
    rw: np.ndarray = field(repr=False)
    fw: np.ndarray = field(repr=False)  # (B, 3, nb) weighted unit-norm base columns per channel
    tw: np.ndarray = field(repr=False)  # (B, 3, p) weighted unit-norm term columns
    evecs: np.ndarray = field(repr=False)
    evals: np.ndarray = field(repr=False)
    scale: np.ndarray = field(repr=False)  # column norms (coef = normalised coef / scale)

    def coef_sigma(self) -> np.ndarray:
        """Standard uncertainty of every coefficient from the weighted normal matrix (the block sigmas as given;
        a direction the data cannot determine gets inf)."""
        var_n = (
            np.einsum("ik,k,ik->i", self.evecs, 1.0 / self.evals, self.evecs)
            if self.evals.size
            else np.zeros(self.scale.size)
        )
        sig = np.sqrt(var_n) / self.scale
        undetermined = np.abs(self.evecs).sum(axis=1) == 0 if self.evals.size else np.ones(self.scale.size, bool)
        return np.where(undetermined, np.inf, sig)

    def coef_covariance(self, idx: np.ndarray) -> np.ndarray:
        """Covariance (k, k) of the coefficients at indices ``idx`` from the weighted normal matrix (the block
        sigmas as given)."""
        v = self.evecs[np.asarray(idx)]
        s = self.scale[np.asarray(idx)]
        return (v / self.evals[None, :]) @ v.T / np.outer(s, s)

    def term_coef(self, effect_id: str) -> np.ndarray:
        return self.coef[self.slices[effect_id]]

    def project(self, cw: np.ndarray) -> np.ndarray:
        """The projection (B, 3, c) of weighted columns ``cw`` (B, 3, c) on the span of this fit's columns."""
        nb = self.fw.shape[2]
        xt = np.concatenate([_per_channel_gram(self.fw, cw).reshape(3 * nb, -1), _gram(self.tw, cw)])
        m = self.evecs @ ((self.evecs.T @ xt) / self.evals[:, None])
        on_base = np.matmul(self.fw.transpose(1, 0, 2), m[: 3 * nb].reshape(3, nb, -1)).transpose(1, 0, 2)
        return on_base + (_flat(self.tw) @ m[3 * nb :]).reshape(cw.shape)


@dataclass
class Trial:
    """A candidate term scored against the current model: its time constant, coefficients, dBIC, catalogue
    parameters, why it is implausible (None: plausible), and what it changes in the model (weighted, (B, 3))."""

    effect: str
    value: float | None
    chi2: float
    added_rank: int
    delta_bic: float
    params: dict[str, Any]
    reason: str | None
    change_w: np.ndarray = field(repr=False)


@dataclass
class Selection:
    """The outcome of the greedy search: final state and fit, the base-only fit, the accepted trials in order,
    confounded groups, and the scores of every round."""

    state: tuple[tuple[str, float | None], ...]
    final: FitResult
    base: FitResult
    accepted: list[Trial]
    confounded: dict[str, list[str]]
    rounds: list[list[dict]] = field(default_factory=list)


def _key(value: float | None) -> float | None:
    return None if value is None else round(float(value), 9)


class Design:
    """Block data (``y`` (B, 3) V, ``sigma`` (B, 3) V), the reference model and cached columns of one recording."""

    def __init__(self, rec: StaticRecord, blocks: Blocks, reference, sigma_v: np.ndarray):
        self.rec = rec
        self.blocks = blocks
        self.order = int(reference.order)
        self.reference_model = reference
        self.ctx = rec.context(reference)
        self.y = blocks.mean(rec.u_v)
        # reference model per block and power n: K_n a + U0_n (B, order+1, 3); with dT^n block means -> exact
        k_abs = [reference.K0] + [reference.rel[n] * reference.K0 for n in range(self.order)]
        u_abs = [reference.U00] + [reference.alpha[n] for n in range(self.order)]
        self._ref_terms = np.stack([np.einsum("ij,bj->bi", k, blocks.a_g) + u for k, u in zip(k_abs, u_abs)], axis=1)
        self._powers: dict[float | None, np.ndarray] = {}
        self._columns: dict[tuple[str, float | None], tuple[list[str], np.ndarray]] = {}
        #: block-level columns of terms outside the catalogue (empirical corrections): id -> (labels, (B, 3, p))
        self.extra: dict[str, tuple[list[str], np.ndarray]] = {}
        self.base_mask = np.ones(4 * (self.order + 1), dtype=bool)
        self.set_sigma(sigma_v)

    def set_base_mask(self, mask: np.ndarray) -> None:
        """Which base columns (per channel: dT^n a_x, dT^n a_y, dT^n a_z, dT^n for n = 0..order) the fits may
        change; the others stay the reference model's (a given passport is not refitted beyond them)."""
        self.base_mask = np.asarray(mask, dtype=bool).reshape(-1)
        self._powers.clear()

    def set_sigma(self, sigma_v: np.ndarray) -> None:
        """Block sigmas (B, 3) V; fits weigh by their inverse."""
        self.sigma = np.asarray(sigma_v, dtype=float)

    @property
    def n_values(self) -> int:
        return int(self.y.size)

    # ---- columns
    def moves_temperature(self, effect_id: str) -> bool:
        """The term moves the temperature the base model is evaluated at (thermal lag) instead of adding columns;
        a term outside the catalogue (:attr:`extra`, an empirical correction) never does."""
        return (
            effect_id not in self.extra
            and not effect_id.startswith("empirical")
            and effect_class(effect_id).acts_on == "temperature"
        )

    def element_temperature_c(self, lag_tau_s: float | None) -> np.ndarray:
        return self.rec.element_temperature_c(lag_tau_s)

    def reference(self, lag_tau_s: float | None) -> np.ndarray:
        """Block means (B, 3) V of the reference model at the thermosensor or element temperature (exact from the
        block means of dT^n: the specific force is constant in a block)."""
        return np.einsum("bn,bni->bi", self.powers(lag_tau_s), self._ref_terms)

    def powers(self, lag_tau_s: float | None) -> np.ndarray:
        """Block means of dT^n, n = 0..order (B, order+1), at the thermosensor or the lagged element temperature."""
        key = _key(lag_tau_s)
        if key not in self._powers:
            dt = self.element_temperature_c(key) - self.rec.normal_temp_c
            self._powers[key] = self.blocks.mean(dt[:, None] ** np.arange(self.order + 1)[None, :])
            if len(self._powers) > 256:
                self._powers.pop(next(iter(self._powers)))
        return self._powers[key]

    def features(self, lag_tau_s: float | None) -> np.ndarray:
        """(B, nb) base columns of one channel: dT^n a_x, dT^n a_y, dT^n a_z, dT^n for n = 0..order."""
        p = self.powers(lag_tau_s)
        a1 = np.concatenate([self.blocks.a_g, np.ones((self.blocks.size, 1))], axis=1)
        return (p[:, :, None] * a1[:, None, :]).reshape(self.blocks.size, -1) * self.base_mask[None, :]

    def base_prediction(self, fit: FitResult, lag_tau_s: float | None) -> np.ndarray:
        """(B, 3) V: the fit's base model (reference + correction) at the thermosensor or element temperature."""
        return self.reference(lag_tau_s) + np.einsum(
            "bk,ik->bi", self.features(lag_tau_s), fit.base_coef.reshape(3, -1)
        )

    def term_columns(self, effect_id: str, value: float | None) -> tuple[list[str], np.ndarray]:
        """Labels and (B, 3, p) columns of a catalogue term (block means of its unit-parameter delta_u_v)."""
        if effect_id in self.extra:
            return self.extra[effect_id]
        key = (effect_id, _key(value))
        if key not in self._columns:
            labels, cols = effect_class(effect_id).fit_columns(self.ctx, key[1])
            mats = [self.blocks.mean(c) for c in cols]
            self._columns[key] = (labels, np.stack(mats, axis=2) if mats else np.zeros((self.blocks.size, 3, 0)))
            if len(self._columns) > 512:
                self._columns.pop(next(iter(self._columns)))
        return self._columns[key]

    # ---- fits
    def fit(self, state) -> FitResult:
        """Weighted least squares of the base plus the terms of ``state`` ((effect id, value) pairs), by the
        normal equations with unit columns; directions the data cannot tell apart are left out of the rank.
        The base columns are block-diagonal over the channels, which the products exploit."""
        state = tuple(state)
        lag = next((v for e, v in state if self.moves_temperature(e)), None)
        slices, labels, mats = {}, {}, []
        nb = 4 * (self.order + 1)
        col = 3 * nb
        for effect_id, value in state:
            lab, m = self.term_columns(effect_id, value)
            slices[effect_id] = slice(col, col + m.shape[2])
            labels[effect_id] = lab
            mats.append(m)
            col += m.shape[2]
        ref = self.reference(lag)
        w = 1.0 / self.sigma
        yw = (self.y - ref) * w
        fw = self.features(lag)[:, None, :] * w[:, :, None]  # (B, 3, nb)
        tw = (np.concatenate(mats, axis=2) if mats else np.zeros((self.blocks.size, 3, 0))) * w[:, :, None]
        nf = np.sqrt(np.einsum("bik,bik->ik", fw, fw))
        nt = np.sqrt(np.einsum("bip,bip->p", tw, tw))
        nf[nf == 0] = 1.0
        nt[nt == 0] = 1.0
        fw = fw / nf
        tw = tw / nt
        p = tw.shape[2]
        g = np.zeros((3 * nb + p, 3 * nb + p))
        gff = _per_channel_gram(fw, fw)
        gft = _per_channel_gram(fw, tw).reshape(3 * nb, p)
        for i in range(3):
            g[i * nb : (i + 1) * nb, i * nb : (i + 1) * nb] = gff[i]
        g[: 3 * nb, 3 * nb :] = gft
        g[3 * nb :, : 3 * nb] = gft.T
        g[3 * nb :, 3 * nb :] = _gram(tw, tw)
        rhs = np.concatenate([_per_channel_gram(fw, yw[:, :, None]).reshape(-1), _gram(tw, yw)[:, 0]])
        evals, evecs = np.linalg.eigh(g)
        keep = evals > _RANK_TOL * max(evals[-1], 1e-300)
        v, lam = evecs[:, keep], evals[keep]
        cn = v @ ((v.T @ rhs) / lam)
        pred = np.matmul(fw.transpose(1, 0, 2), cn[: 3 * nb].reshape(3, nb, 1))[:, :, 0].T
        pred = pred + (_flat(tw) @ cn[3 * nb :]).reshape(yw.shape)
        rw = yw - pred
        c = cn / np.concatenate([nf.reshape(-1), nt])
        return FitResult(
            state,
            c,
            float(np.sum(rw * rw)),
            int(keep.sum()),
            ref + pred / w,
            slices,
            labels,
            c[: 3 * nb].reshape(3, self.order + 1, 4),
            rw,
            fw,
            tw,
            v,
            lam,
            np.concatenate([nf.reshape(-1), nt]),
        )

    def score(
        self, current: FitResult, effect_id: str, value: float | None
    ) -> tuple[float, int, np.ndarray, list[str], np.ndarray]:
        """chi2, added rank, coefficients, labels and weighted change (B, 3) of the fitted values when the term is
        added to ``current`` (thermal lag: refit with the lagged temperature)."""
        if self.moves_temperature(effect_id):
            fr = self.fit(current.state + ((effect_id, value),))
            return fr.chi2, fr.rank - current.rank, np.zeros(0), [], current.rw - fr.rw
        labels, cols = self.term_columns(effect_id, value)
        cw = cols / self.sigma[:, :, None]
        norms = np.sqrt(np.einsum("bic,bic->c", cw, cw))
        norms[norms == 0] = 1.0
        cw = cw / norms
        perp = cw - current.project(cw)
        evals, evecs = np.linalg.eigh(_gram(perp, perp))
        keep = evals > _RANK_TOL * max(evals[-1], 1.0) if evals.size else np.zeros(0, bool)
        if not keep.any():
            return current.chi2, 0, np.zeros(cols.shape[2]), labels, np.zeros_like(current.rw)
        v = evecs[:, keep]
        coef = v @ ((v.T @ _gram(perp, current.rw)[:, 0]) / evals[keep])
        change = (_flat(perp) @ coef).reshape(current.rw.shape)
        r = current.rw - change
        return float(np.sum(r * r)), int(keep.sum()), coef / norms, labels, change

    def trial(self, current: FitResult, effect_id: str, ln_n: float) -> Trial:
        """Score a candidate at its best time constant (grid, then refined); implausible values get a reason."""
        term = effect_class(effect_id)
        on_edge = False
        if term.nonlinear is None:
            value = None
        else:
            grid = np.asarray(term.grid)
            chi = np.array([self.score(current, effect_id, float(g))[0] for g in grid])
            k = int(np.argmin(chi))
            on_edge = k in (0, grid.size - 1)
            value = float(grid[k])
            if not on_edge:
                res = minimize_scalar(
                    lambda x: self.score(current, effect_id, float(np.exp(x)))[0],
                    bounds=(np.log(grid[k - 1]), np.log(grid[k + 1])),
                    method="bounded",
                    options={"xatol": 0.01},
                )
                if res.fun < chi[k]:
                    value = float(np.exp(res.x))
        chi2, added, coef, labels, change = self.score(current, effect_id, value)
        params = term.fit_parameters(coef, value, labels)
        reason = term.implausible(params)
        if on_edge and reason is None:
            reason = f"time constant {value:.3g} s at the edge of the searched range"
        if term.nonlinear is not None:
            added += 1  # the time constant is a parameter too
        if added == 0 and reason is None:
            reason = "not separable from the base model under this run's program"
        dbic = chi2 - current.chi2 + added * ln_n
        return Trial(effect_id, value, chi2, added, float(dbic), params, reason, change)


def select_terms(
    design: Design, candidates: list[str], settings: SelectionSettings = SelectionSettings(), initial: tuple = ()
) -> Selection:
    """Greedy forward selection of catalogue terms (see the module doc), on top of the terms of ``initial``
    (e.g. an empirical correction held in the model)."""
    ln_n = float(np.log(design.n_values))
    state: tuple = tuple(initial)
    base = design.fit(())
    current = design.fit(state)
    accepted: list[Trial] = []
    confounded: dict[str, list[str]] = {}
    left = list(candidates)
    rounds = []
    while left:
        trials = [design.trial(current, e, ln_n) for e in left]
        rounds.append(
            [
                {
                    "effect": t.effect,
                    "delta_bic": round(t.delta_bic, 1),
                    "value": None if t.value is None else round(t.value, 3),
                    "implausible": t.reason,
                }
                for t in sorted(trials, key=lambda t: t.delta_bic)
            ]
        )
        limit = settings.threshold
        if accepted:  # no model is exact: what is left of a large effect must not be read as another one
            limit = max(limit, settings.imperfection_rel * abs(accepted[0].delta_bic))
        good = sorted((t for t in trials if t.reason is None and t.delta_bic < -limit), key=lambda t: t.delta_bic)
        if not good:
            break
        best = good[0]
        margin = max(settings.confound_margin_abs, settings.confound_margin_rel * abs(best.delta_bic))
        group = []
        for t in trials:
            if t is best or t.delta_bic > best.delta_bic + margin:
                continue
            cos = float(
                np.sum(t.change_w * best.change_w)
                / (np.linalg.norm(t.change_w) * np.linalg.norm(best.change_w) + 1e-300)
            )
            if cos > settings.confound_cos:
                group.append(t.effect)
        confounded[best.effect] = group
        accepted.append(best)
        state = _refine(design, state + ((best.effect, best.value),))
        current = design.fit(state)
        left = [e for e in left if e != best.effect and e not in group]
    return Selection(state=state, final=current, base=base, accepted=accepted, confounded=confounded, rounds=rounds)


def _refine(design: Design, state: tuple) -> tuple:
    """One pass re-optimising each accepted term's time constant with the other terms held."""
    terms = list(state)
    if len(terms) < 2:
        return state
    for k, (effect_id, value) in enumerate(terms):
        if value is None or effect_id in design.extra:
            continue
        others = tuple(s for j, s in enumerate(terms) if j != k)
        grid = np.asarray(effect_class(effect_id).grid)
        x0 = np.log(value)

        def chi2(x: float, others: tuple = others, effect_id: str = effect_id) -> float:
            return design.fit(others + ((effect_id, float(np.exp(x))),)).chi2

        res = minimize_scalar(
            chi2,
            bounds=(max(np.log(grid[0]), x0 - 0.7), min(np.log(grid[-1]), x0 + 0.7)),
            method="bounded",
            options={"xatol": 0.01},
        )
        if res.fun < chi2(x0):
            terms[k] = (effect_id, float(np.exp(res.x)))
    return tuple(terms)


def block_noise_factor(design: Design, fit: FitResult, min_since_start_s: float = 64.0) -> np.ndarray:
    """Per-channel factor (>= 1) by which the scatter of the residuals of consecutive regular blocks exceeds the
    expected noise: an Allan-type check that lets correlated noise widen the block sigma honestly.

    Uses second differences of three consecutive blocks of one stretch (a left-out effect that varies smoothly
    cancels) and a robust spread (the few blocks where an effect steps do not count).
    """
    b = design.blocks
    r = design.y - fit.fitted
    s2 = design.sigma**2
    ok = (b.since_start_s[:-2] >= min_since_start_s) & (b.stretch[2:] == b.stretch[:-2])
    if ok.sum() < 10:
        return np.ones(3)
    z = ((r[2:] - 2 * r[1:-1] + r[:-2]) / np.sqrt(s2[2:] + 4 * s2[1:-1] + s2[:-2]))[ok]
    mad = np.median(np.abs(z - np.median(z, axis=0)), axis=0)
    return np.maximum(1.0, 1.4826 * mad)


__all__ = ["SelectionSettings", "FitResult", "Trial", "Selection", "Design", "select_terms", "block_noise_factor"]
