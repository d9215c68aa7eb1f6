"""The fleet over time (``thermocal trends``, docs/contract.md "trends"): which constants drift across a unit's
passports and when they reach the unit grade's limit, which units stand out from the fleet of their type.

Every passport is read through the registry's verification (:meth:`Registry.verified_history`: canonical bytes,
hashes, signature, parent link, log); a unit whose chain has a problem is listed in ``not_verified`` and only its
versions that verify with all their ancestors are used. Files this user verified in full before
(:mod:`pipeline.passport.verified_cache`, keyed by their exact bytes) skip the checks of their bytes alone.

**Time.** A version's time is when the recording it was fitted from was made: the start of its first verification
segment (``verification[].t_start_ns``, the recording's own clock), else, for a passport without verification rows
(a differential one), its ``created_utc``. Versions of one recording (a recalibration of the same data) count
once: the newest.

**Drift** (per unit and constant: the 12 constants K and U0 at T0). Over the unit's versions that measured their own
constants (not a failed calibration, not a differential passport whose constants came from its base passport), the
weighted least-squares line ``c(t) = a + b t`` with weights ``1/u_k**2`` (``u_k`` the passport's standard
uncertainty of the constant) gives the rate ``b`` with ``sigma_b = 1/sqrt(sum w (t - t_w)**2)``. Where the points
scatter about the line more than their uncertainties allow (Birge ratio ``R = sqrt(chi2/(n - 2)) > 1``), ``sigma_b``
is multiplied by ``R``. The drift is significant when ``|b| / sigma_b > z_crit``, the two-sided normal quantile of a
family-wise false-alarm probability ``alpha`` (1 %) shared by all ``m`` unit-constant series tested (Bonferroni:
``z_crit = Phi^-1(1 - alpha / (2 m))``, 4.3 for 50 units, 4.9 for 1,000): a fleet whose constants hold lists
nothing with probability at least 99 %.

**Unsteady**: a series of three or more versions whose scatter about its line is itself significant
(``chi2 = sum w (c - a - b t)**2`` with ``n - 2`` degrees of freedom, p-value below ``alpha / m'``, Bonferroni over
the ``m'`` such series): the constant moved beyond its uncertainties, but not at one rate (a drift that reversed, a
step). Reported with its most recent rate (the last two versions) and when that rate would reach the limit.

**The limit** a drift is dated against: the unit grade's |dg| limit at T0 (``tolerances.normal_g`` of the current
passport; for a passport written before grades, the smallest limit of its verification rows; else the default
grade's, :data:`pipeline.verify.GRADES` [:data:`~pipeline.verify.DEFAULT_GRADE`]: navigation, 3e-4 g, docs/physics.md
"Unit grades"). A constant's change, alone, makes ``|dg|`` in the worst
orientation (to first order in the change, ``dg = a . da`` with ``da = -K^-1 (dK a + dU0)``): ``|dU0_i| / |K_ii|``
for an offset, ``|dK_ii| / |K_ii|`` (times 1 g) for a gain, ``|dK_ij| / (2 |K_ii|)`` for a cross-axis sensitivity
(at 45 degrees between axes i and j). The limit of a constant is the change that makes the grade's |dg| alone;
``due_utc`` is when the fitted line, from the time of the current passport (the one in use), has changed by that
much: ``t_current + limit / |b|``.

**Outliers** (per unit type: units of one grade and output unit whose gains agree within a factor 1.5). For each
of the offsets U0, the gains K_ii and the first-order temperature coefficients of offset and gain (alpha_i, beta_ii
of a polynomial model; each segment's of a piecewise one, among passports with the same breakpoints), over the
current passports of the type: the median ``med`` and the fleet's robust sigma ``s = 1.4826 MAD``; a unit's robust
z is ``(c - med) / sqrt(s**2 + u**2)`` (``u`` its own standard uncertainty). It is an outlier when ``|z|`` exceeds
``max(8, t_q)``, ``t_q`` the Student-t quantile of ``alpha / (2 m)`` with ``0.37 (n - 1)`` degrees of freedom (the
MAD of n values is as certain as the standard deviation of about 0.37 n normal values), Bonferroni over the ``m``
comparisons; types of fewer than 10 units are not assessed. Cross-axis sensitivities and their coefficients are
not compared: a type's spread over decades with either sign (seed 000's type: 0.3 to 16 mV/g), which a median
and MAD do not describe (in simulated fleets of 20 units of that type, 8 % would list a unit at 10 fleet sigmas).
"""

from __future__ import annotations

import contextlib
import gc
import math
import multiprocessing
import os
import threading
from collections.abc import Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np

from pipeline.errors import ThermocalError
from pipeline.passport.document import output_unit_of
from pipeline.passport.registry import Registry
from pipeline.passport.significance import sigma_of, value_of
from pipeline.passport.signing import TrustStore, trusted_keys
from pipeline.passport.text import per
from pipeline.passport.verified_cache import VerifiedCache
from pipeline.positions import AXES
from pipeline.verify import DEFAULT_GRADE, GRADES

#: the constants whose drift is tested, in the names of ``passport diff``
DRIFT_CONSTANTS: tuple[str, ...] = tuple(f"K.{a}{b}" for a in AXES for b in AXES) + tuple(f"U0.{a}" for a in AXES)
#: the constants compared with the fleet (cross-axis sensitivities are not: see the module doc)
OUTLIER_CONSTANTS: tuple[str, ...] = tuple(f"U0.{a}" for a in AXES) + tuple(f"K.{a}{a}" for a in AXES)
SECONDS_PER_YEAR = 365.25 * 86400.0
#: robust sigma of a normal sample from its median absolute deviation
MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class TrendSettings:
    """The tests' parameters (module doc): ``false_alarm`` the family-wise false-alarm probability of each kind of
    finding (drift, unsteady, outlier); ``outlier_floor`` the smallest robust z called an outlier; ``min_fleet`` the
    fewest units of a type assessed for outliers; ``mad_efficiency`` the degrees of freedom per unit of the MAD;
    ``gain_ratio`` the largest ratio of gains within one unit type."""

    false_alarm: float = 0.01
    outlier_floor: float = 8.0
    min_fleet: int = 10
    mad_efficiency: float = 0.37
    gain_ratio: float = 1.5

    def to_dict(self) -> dict:
        return {
            "false_alarm": self.false_alarm,
            "outlier_floor": self.outlier_floor,
            "min_fleet": self.min_fleet,
            "mad_efficiency": self.mad_efficiency,
            "gain_ratio": self.gain_ratio,
        }


@dataclass(frozen=True)
class Point:
    """One version of a unit as the trends read it: its time (s since the Unix epoch, from ``time_basis``), status,
    whether its constants at T0 are its own measurement (not a differential passport's copy of its base), the
    numbers the tests use (value and standard uncertainty by ``passport diff`` name: the 12 constants and the
    first-order temperature coefficients of offset and gain), its thermal model's shape, output unit and unit grade
    with the |dg| limit at T0 (g) and where that came from (:func:`grade_limit`)."""

    version: int
    time_s: float
    time_basis: str
    status: str | None
    own_constants: bool
    numbers: dict[str, tuple[float | None, float | None]]
    thermal_shape: str
    output_unit: str
    grade: tuple[str, float, str]

    @property
    def time_utc(self) -> str:
        return utc_of(self.time_s)

    def value(self, name: str) -> float | None:
        return self.numbers.get(name, (None, None))[0]

    def sigma(self, name: str) -> float | None:
        return self.numbers.get(name, (None, None))[1]

    def gain(self, name: str) -> float | None:
        """|K_ii| of the row of ``name``: row i of U0.i, K.ij, alpha.i[n], beta.ii[n], segments[k].alpha.i, ..."""
        a = name.rsplit(".", 1)[-1][:1]
        g = self.value(f"K.{a}{a}") if a in AXES else None
        return abs(g) if g else None

    @classmethod
    def of(cls, version: int, doc: dict) -> Point:
        """The point of passport ``doc`` (version ``version``)."""
        time_s, basis = version_time(doc)
        shape, thermal = _thermal_features(doc)
        return cls(
            version=version,
            time_s=time_s,
            time_basis=basis,
            status=doc.get("status"),
            own_constants=doc.get("base_passport") is None,
            numbers={n: (value_of(doc, n), sigma_of(doc, n)) for n in (*DRIFT_CONSTANTS, *thermal)},
            thermal_shape=shape,
            output_unit=output_unit_of(doc),
            grade=grade_limit(doc),
        )


@dataclass
class UnitHistory:
    """A unit's verified versions (oldest first), its current version (None: none usable) and the problems of its
    chain (empty: every version verified)."""

    unit: str
    points: list[Point]
    current: int | None
    problems: list[str] = field(default_factory=list)

    def point(self, version: int | None) -> Point | None:
        return next((p for p in self.points if p.version == version), None)


@dataclass
class Series:
    """The evidence of one unit-constant series (for the page's figures): times (s), values and sigmas, the
    versions, the fitted line (value at ``t_ref_s`` and rate per second) and the limit's band about the current
    value."""

    unit: str
    constant: str
    versions: list[int]
    time_s: np.ndarray
    value: np.ndarray
    sigma: np.ndarray
    intercept: float
    t_ref_s: float
    rate_per_s: float
    limit: float | None
    current_time_s: float
    current_value: float
    output_unit: str


@dataclass
class FleetValues:
    """The fleet an outlier was compared with: the type, the constant, every unit's value and the marked unit."""

    unit: str
    constant: str
    unit_type: str
    units: list[str]
    values: np.ndarray
    median: float
    sigma: float


@dataclass
class TrendsResult:
    """What ``trends`` found: the JSON object (:meth:`as_dict`) and, for the page, the series and fleets behind
    each finding."""

    report: dict
    series: dict[tuple[str, str], Series] = field(default_factory=dict)
    fleets: dict[tuple[str, str], FleetValues] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return self.report


def utc_of(time_s: float) -> str:
    """Seconds since the Unix epoch as ``2026-03-01T12:00:00Z`` (to the second)."""
    t = datetime(1970, 1, 1, tzinfo=UTC) + timedelta(seconds=float(time_s))
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def _seconds(text: str) -> float:
    t = datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return t.timestamp()


def version_time(doc: dict) -> tuple[float, str]:
    """A passport's time (s since the Unix epoch) and where it came from (module doc): the start of its first
    verification segment, else its ``created_utc``. ThermocalError when it has neither."""
    rows = [r.get("t_start_ns") for r in doc.get("verification") or [] if isinstance(r, dict)]
    starts = [int(t) for t in rows if isinstance(t, int) and not isinstance(t, bool)]
    if starts:
        return min(starts) / 1e9, "verification"
    try:
        return _seconds(doc["created_utc"]), "created_utc"
    except (KeyError, TypeError, ValueError):
        raise ThermocalError(
            f"{doc.get('unit')} v{doc.get('version')}: no verification rows and created_utc is not a UTC time"
        ) from None


def grade_limit(doc: dict) -> tuple[str, float, str]:
    """The unit grade, its |dg| limit at T0 (g) and where it came from, of a passport (module doc)."""
    tol = doc.get("tolerances")
    if isinstance(tol, dict) and isinstance(tol.get("normal_g"), (int, float)):
        return str(doc.get("unit_grade") or tol.get("grade") or "stated"), float(tol["normal_g"]), "the passport's"
    stated = [r.get("tolerance_g") for r in doc.get("verification") or [] if isinstance(r, dict)]
    limits = [float(x) for x in stated if isinstance(x, (int, float)) and x > 0]
    if limits:
        return DEFAULT_GRADE, min(limits), "the passport's verification rows (written before grades)"
    return DEFAULT_GRADE, GRADES[DEFAULT_GRADE].normal_g, f"no limit stated: the {DEFAULT_GRADE} grade's"


def worst_dg_factor(constant: str) -> float:
    """The worst-orientation |dg| (in g) of a unit change of ``constant`` relative to its row's gain |K_ii|
    (module doc): 1 for U0 and K_ii, 1/2 for K_ij."""
    if constant.startswith("K.") and constant[2] != constant[3]:
        return 0.5
    return 1.0


def read_history(
    registry: Registry, unit: str, trust: TrustStore | None = None, cache: VerifiedCache | None = None
) -> UnitHistory:
    """The unit's verified versions as :class:`Point` (:meth:`Registry.verified_history`: the versions that verify
    with all their ancestors; ``cache``: files this user verified in full before) and its current version
    (docs/contract.md: the newest approved, else the newest that did not fail; None when that version is not among
    the verified ones)."""
    docs, problems, current = registry.verified_history(unit, trust, cache)
    points = [Point.of(v, doc) for v, doc in sorted(docs.items())]
    if current not in docs or docs[current].get("status") == "fail":
        current = None
    return UnitHistory(unit, points, current, [str(p) for p in problems])


#: The fewest units read by more than one process (below, starting the processes costs more than it saves).
PARALLEL_MIN_UNITS = 200


@contextlib.contextmanager
def _no_cycle_collection() -> Iterator[None]:
    """The cyclic garbage collector paused (a registry's read allocates hundreds of thousands of containers, none
    of them in a cycle: reference counting frees them; the collector's passes cost about a fifth of the read)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _read_units(root: str, units: list[str]) -> list[UnitHistory]:
    """:func:`read_history` of ``units`` (a worker process's share of :func:`read_fleet`)."""
    registry, trust = Registry(root), trusted_keys()
    cache = VerifiedCache.open(trust)
    with _no_cycle_collection():
        return [read_history(registry, u, trust, cache) for u in units]


def _start_method() -> str:
    """How :func:`read_fleet` starts its worker processes: forked from this process when it runs no other thread (the
    workers start with its modules imported, about half a CPU second each less than a new interpreter), else spawned
    (a fork of a process that runs threads, such as a Prefect flow's, may copy a lock another thread holds)."""
    return "fork" if threading.active_count() == 1 and "fork" in multiprocessing.get_all_start_methods() else "spawn"


def read_fleet(registry: Registry, units: Iterable[str] | None = None, workers: int | None = None) -> list[UnitHistory]:
    """:func:`read_history` of every unit of the registry (or of ``units``), in the registry's order. ``workers``
    processes read a share of the units each (default: one per CPU for :data:`PARALLEL_MIN_UNITS` units or more,
    else 1: this process; started as :func:`_start_method` says); each verifies what it reads, exactly as one
    process would. A share whose process fails is read again here, so an error is this process's own (the same one
    line)."""
    names = registry.units() if units is None else list(units)
    if workers is None:
        workers = (os.cpu_count() or 1) if len(names) >= PARALLEL_MIN_UNITS else 1
    trust = trusted_keys()
    if workers <= 1 or len(names) < 2:
        cache = VerifiedCache.open(trust)
        with _no_cycle_collection():
            return [read_history(registry, u, trust, cache) for u in names]
    shares = [names[k::workers] for k in range(workers)]
    root = str(registry.root.resolve())
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(_start_method())) as pool:
        futures = [pool.submit(_read_units, root, share) for share in shares]
        read: dict[str, UnitHistory] = {}
        for share, future in zip(shares, futures):
            try:
                histories = future.result()
            except Exception:  # (the same error again, raised here: its one line, its type)
                histories = [read_history(registry, u, trust, VerifiedCache.open(trust)) for u in share]
            read.update((h.unit, h) for h in histories)
    return [read[u] for u in names]


# ---------------------------------------------------------------------------------------------------------------
# drift


def _constant_points(h: UnitHistory) -> list[Point]:
    """The versions whose constants count for the drift: their own measurement, not failed; of several versions of
    one recording (the same time), the newest."""
    by_time: dict[float, Point] = {}
    for p in h.points:
        if p.own_constants and p.status != "fail":
            by_time[p.time_s] = p  # oldest first: a newer version of the same recording replaces the older
    return [by_time[t] for t in sorted(by_time)]


def _fits(rows: list[tuple]) -> dict[str, np.ndarray]:
    """Weighted least-squares lines through many series at once (one row of ``rows`` each: its times t_s, values y
    and standard uncertainties s, padded into one array with weight 0): per series the rate b (per s), its sigma
    from the weights, the value at the weighted mean time, that time, the degrees of freedom (n - 2) and chi2."""
    n = np.array([len(r[3]) for r in rows], dtype=int)
    width = int(n.max()) if n.size else 0
    used = np.arange(width)[None, :] < n[:, None]
    t, y, w = (np.zeros((len(rows), width)) for _ in range(3))
    t[used] = np.concatenate([r[3] for r in rows]) if rows else []
    y[used] = np.concatenate([r[4] for r in rows]) if rows else []
    w[used] = 1.0 / np.concatenate([r[5] for r in rows]) ** 2 if rows else []
    sw = w.sum(axis=1)
    tm = (w * t).sum(axis=1) / sw
    ym = (w * y).sum(axis=1) / sw
    dt = np.where(used, t - tm[:, None], 0.0)
    stt = (w * dt * dt).sum(axis=1)
    b = (w * dt * (y - ym[:, None])).sum(axis=1) / stt
    chi2 = (w * (y - ym[:, None] - b[:, None] * dt) ** 2).sum(axis=1)
    return {"b": b, "sigma_b": 1.0 / np.sqrt(stt), "ym": ym, "tm": tm, "dof": n - 2, "chi2": chi2}


def _drift(
    fleet: list[UnitHistory], settings: TrendSettings, result: TrendsResult
) -> tuple[list[dict], list[dict], dict]:
    rows: list[tuple] = []
    for h in fleet:
        pts = _constant_points(h)
        if len(pts) < 2:
            continue
        t = np.array([p.time_s for p in pts])
        vals = np.array([[p.value(c) for c in DRIFT_CONSTANTS] for p in pts], dtype=float)
        sigs = np.array([[p.sigma(c) for c in DRIFT_CONSTANTS] for p in pts], dtype=float)
        ok = np.isfinite(vals) & np.isfinite(sigs) & (sigs > 0)
        if ok.all() and t[-1] > t[0]:  # (the usual case: every constant of every version, times increasing)
            rows.extend((h, c, pts, t, vals[:, j], sigs[:, j]) for j, c in enumerate(DRIFT_CONSTANTS))
            continue
        for j, c in enumerate(DRIFT_CONSTANTS):
            sel = ok[:, j]
            if sel.sum() >= 2 and np.ptp(t[sel]) > 0:
                keep = [p for p, k in zip(pts, sel) if k]
                rows.append((h, c, keep, t[sel], vals[sel, j], sigs[sel, j]))
    # scipy.special's functions, which scipy.stats' norm.isf and chi2.sf call (the same numbers), without importing
    # scipy.stats (~1 s of the command's start); here: a process that only reads (read_fleet's) does not load scipy
    from scipy.special import chdtrc, ndtri

    m = len(rows)
    fit = _fits(rows)
    dof_v, chi2_v = fit["dof"], fit["chi2"]
    m_chi = int((dof_v >= 1).sum())
    alpha = settings.false_alarm
    z_crit = float(-ndtri(alpha / (2 * m))) if m else None
    p_crit = alpha / m_chi if m_chi else None
    with np.errstate(divide="ignore", invalid="ignore"):
        birge_v = np.where(dof_v >= 1, np.sqrt(chi2_v / np.maximum(dof_v, 1)), np.nan)
        sigma_v = fit["sigma_b"] * np.maximum(1.0, np.nan_to_num(birge_v, nan=1.0))
        z_v = fit["b"] / sigma_v
        p_v = np.where(dof_v >= 1, chdtrc(np.maximum(dof_v, 1), chi2_v), np.nan)
    drift_v = np.abs(z_v) > z_crit if z_crit is not None else np.zeros(m, dtype=bool)
    unsteady_v = p_v < p_crit if p_crit is not None else np.zeros(m, dtype=bool)
    drifting, unsteady = [], []
    for k in np.flatnonzero(drift_v | unsteady_v):  # (only the series with a finding: the rest is in the arrays)
        h, c, pts, t, y, s = rows[k]
        b, ym, tm, chi2, sb_eff, z = (
            float(fit["b"][k]),
            float(fit["ym"][k]),
            float(fit["tm"][k]),
            float(chi2_v[k]),
            float(sigma_v[k]),
            float(z_v[k]),
        )
        dof = int(dof_v[k])
        birge = float(birge_v[k]) if dof >= 1 else None
        p_value = float(p_v[k]) if dof >= 1 else None
        is_drift, is_unsteady = bool(drift_v[k]), bool(unsteady_v[k])
        cur = h.point(h.current) or pts[-1]
        grade, normal_g, grade_basis = cur.grade
        u = cur.output_unit
        gain = cur.gain(c)
        limit = normal_g * gain / worst_dg_factor(c) if gain else None
        scale, scaled_unit = _scale(c, gain)
        cur_value = cur.value(c)
        evidence = [
            {"version": p.version, "time_utc": p.time_utc, "value": float(v), "sigma": float(e)}
            for p, v, e in zip(pts, y, s)
        ]
        common = {
            "unit": h.unit,
            "constant": c,
            "constant_unit": u if c.startswith("U0") else per(u, "g"),
            "grade": grade,
            "limit_g": normal_g,
            "limit_basis": grade_basis,
            "limit": limit,
            "limit_scaled": normal_g * 1e6 / worst_dg_factor(c),
            "current_version": cur.version,
            "versions": evidence,
        }
        series = Series(
            h.unit,
            c,
            [p.version for p in pts],
            t,
            y,
            s,
            ym,
            tm,
            b,
            limit,
            cur.time_s,
            float(cur_value) if cur_value is not None else float(y[-1]),
            common["constant_unit"],
        )
        if is_drift:
            rate_y = b * SECONDS_PER_YEAR
            due = cur.time_s + limit / abs(b) if limit and b else None
            drifting.append(
                {
                    **common,
                    "rate_per_year": rate_y,
                    "sigma_per_year": sb_eff * SECONDS_PER_YEAR,
                    "z": z,
                    "z_threshold": z_crit,
                    "rate_scaled_per_year": rate_y * scale if scale else None,
                    "scaled_unit": f"{scaled_unit}/year",
                    "due_utc": utc_of(due) if due is not None and abs(due) < 1e11 else None,
                    "chi2": chi2,
                    "dof": dof,
                    "birge_ratio": birge,
                }
            )
            result.series[(h.unit, c)] = series
        if is_unsteady:
            dt = float(t[-1] - t[-2])
            recent = float(y[-1] - y[-2]) / dt
            recent_sigma = math.hypot(float(s[-1]), float(s[-2])) / dt
            due = cur.time_s + limit / abs(recent) if limit and recent else None
            unsteady.append(
                {
                    **common,
                    "chi2": chi2,
                    "dof": dof,
                    "p_value": p_value,
                    "p_threshold": p_crit,
                    "line_rate_per_year": b * SECONDS_PER_YEAR,
                    "recent_rate_per_year": recent * SECONDS_PER_YEAR,
                    "recent_sigma_per_year": recent_sigma * SECONDS_PER_YEAR,
                    "recent_rate_scaled_per_year": recent * SECONDS_PER_YEAR * scale if scale else None,
                    "scaled_unit": f"{scaled_unit}/year",
                    "due_utc": utc_of(due) if due is not None and abs(due) < 1e11 else None,
                }
            )
            result.series.setdefault((h.unit, c), series)
    drifting.sort(key=lambda e: (-abs(e["z"]), e["unit"], e["constant"]))
    unsteady.sort(key=lambda e: (e["p_value"], e["unit"], e["constant"]))
    test = {
        "drift": {
            "series_tested": m,
            "z_threshold": z_crit,
            "rule": "weighted least-squares line over the unit's versions (weights 1/sigma^2); sigma of the rate "
            "times the Birge ratio when above 1; drifting when |rate|/sigma > Phi^-1(1 - false_alarm/(2 m)), m "
            "the unit-constant series tested (Bonferroni)",
        },
        "unsteady": {
            "series_tested": m_chi,
            "p_threshold": p_crit,
            "rule": "chi2 of the points about their line, n - 2 degrees of freedom; unsteady when its p-value is "
            "below false_alarm/m' (Bonferroni over the m' series of three or more versions)",
        },
    }
    return drifting, unsteady, test


def _scale(constant: str, gain: float | None) -> tuple[float | None, str]:
    """Engineering scale of a constant: U0 and alpha (output unit) -> micro-g (/|K_ii|); K -> ppm of the row's gain;
    beta (1/C) -> ppm."""
    if constant.startswith(("U0.", "alpha.")) or ".alpha." in constant:
        return (1e6 / gain if gain else None), "micro-g" + ("/C" if "alpha" in constant else "")
    if constant.startswith("K."):
        return (1e6 / gain if gain else None), "ppm of gain"
    return 1e6, "ppm/C"


# ---------------------------------------------------------------------------------------------------------------
# outliers


def _thermal_features(doc: dict) -> tuple[str, list[str]]:
    """The thermal model's shape (units are compared with those of the same shape) and its first-order
    coefficients of offset and gain, in the names of ``passport diff``."""
    tm = doc.get("thermal_model") or {}
    if tm.get("kind") == "polynomial":
        names = [f"alpha.{a}[1]" for a in AXES] + [f"beta.{a}{a}[1]" for a in AXES]
        return f"polynomial order {tm.get('order')}", names
    if tm.get("kind") == "piecewise_linear":
        segs = range(len(tm.get("segments") or []))
        names = [
            f"segments[{k}].{g}.{a * (1 if g == 'alpha' else 2)}" for k in segs for g in ("alpha", "beta") for a in AXES
        ]
        return f"piecewise linear at {tm.get('breakpoints_c')} C", names
    return "none", []


def _unit_types(current: list[tuple[str, Point]], ratio: float) -> dict[str, str]:
    """Unit type of each unit (module doc): grade, output unit, signs of the gains, and gains within ``ratio``."""
    groups: dict[tuple, list[tuple[float, str]]] = {}
    for unit, p in current:
        k = [p.value(f"K.{a}{a}") for a in AXES]
        if any(g is None or g == 0 for g in k):
            continue
        gains = np.array(k, dtype=float)
        key = (p.grade[0], p.output_unit, tuple(np.sign(gains).astype(int)))
        groups.setdefault(key, []).append((float(np.log(np.abs(gains).mean())), unit))
    out: dict[str, str] = {}
    for (grade, u, signs), members in groups.items():
        members.sort()
        cut = [0] + [i for i in range(1, len(members)) if members[i][0] - members[i - 1][0] > math.log(ratio)]
        for lo, hi in zip(cut, cut[1:] + [len(members)]):
            chunk = members[lo:hi]
            gain = math.exp(float(np.median([g for g, _ in chunk]))) * (1 if sum(signs) > 0 else -1)
            label = f"{grade} grade, {u}, gain {gain:.3g} {per(u, 'g')}"
            out.update({unit: label for _, unit in chunk})
    return out


def _outliers(fleet: list[UnitHistory], settings: TrendSettings, result: TrendsResult) -> tuple[list[dict], dict]:
    from scipy.special import stdtrit  # (stats.t.isf(q, df) = -stdtrit(df, q): see _drift)

    current = [(h.unit, p) for h in fleet if (p := h.point(h.current)) is not None]
    types = _unit_types(current, settings.gain_ratio)
    groups: dict[tuple[str, str], list[tuple[str, Point, float, float]]] = {}
    for unit, p in current:
        if unit not in types:
            continue
        thermal = [n for n in p.numbers if n not in DRIFT_CONSTANTS]
        for name in (*OUTLIER_CONSTANTS, *thermal):
            v, s = p.numbers[name]
            if v is None:
                continue
            key = (types[unit] if name in OUTLIER_CONSTANTS else f"{types[unit]}, {p.thermal_shape}", name)
            groups.setdefault(key, []).append((unit, p, v, s if s is not None else 0.0))
    assessed = {k: g for k, g in groups.items() if len(g) >= settings.min_fleet}
    m = sum(len(g) for g in assessed.values())
    found: list[dict[str, Any]] = []
    thresholds: dict[int, float] = {}
    for (unit_type, name), members in sorted(assessed.items()):
        x = np.array([v for _, _, v, _ in members])
        u = np.array([s for _, _, _, s in members])
        med = float(np.median(x))
        s_fleet = MAD_TO_SIGMA * float(np.median(np.abs(x - med)))
        denom = np.sqrt(s_fleet**2 + u**2)
        if not np.all(denom > 0):
            continue
        z = (x - med) / denom
        df = max(1.0, settings.mad_efficiency * (len(x) - 1))
        threshold = max(settings.outlier_floor, float(-stdtrit(df, settings.false_alarm / (2 * m))))
        thresholds[len(x)] = threshold
        for k in np.flatnonzero(np.abs(z) > threshold):
            unit, p, v, s = members[int(k)]
            scale, scaled_unit = _scale(name, p.gain(name))
            found.append(
                {
                    "unit": unit,
                    "version": p.version,
                    "constant": name,
                    "value": v,
                    "sigma": s or None,
                    "fleet_median": med,
                    "fleet_sigma": s_fleet,
                    "robust_z": float(z[k]),
                    "z_threshold": threshold,
                    "fleet_units": len(x),
                    "unit_type": unit_type,
                    "difference_scaled": (v - med) * scale if scale else None,
                    "scaled_unit": scaled_unit,
                }
            )
            result.fleets[(unit, name)] = FleetValues(unit, name, unit_type, [mm[0] for mm in members], x, med, s_fleet)
    found.sort(key=lambda e: (-abs(e["robust_z"]), e["unit"], e["constant"]))
    small = sorted({t for (t, _), g in groups.items() if len(g) < settings.min_fleet})
    test = {
        "comparisons": m,
        "z_threshold_by_fleet_size": {str(n): t for n, t in sorted(thresholds.items())},
        "types_not_assessed": small,
        "rule": "robust z = (value - fleet median) / sqrt((1.4826 MAD)^2 + sigma^2) over the current passports of "
        "one unit type; outlier when |z| > max(outlier_floor, Student-t quantile of false_alarm/(2 m) with "
        "mad_efficiency (n - 1) degrees of freedom), m the comparisons (Bonferroni); offsets, gains and "
        "first-order temperature coefficients of offset and gain",
    }
    return found, test


# ---------------------------------------------------------------------------------------------------------------
# the report


def analyse(fleet: list[UnitHistory], settings: TrendSettings = TrendSettings()) -> TrendsResult:
    """Drift, unsteady constants and outliers of the fleet's histories (module doc); the report is the
    ``trends --json`` object of docs/contract.md with ``unsteady``, ``not_verified`` and ``tests`` besides."""
    result = TrendsResult(report={})
    drifting, unsteady, drift_test = _drift(fleet, settings, result)
    outliers, outlier_test = _outliers(fleet, settings, result)
    result.report = {
        "units": len(fleet),
        "versions": sum(len(h.points) for h in fleet),
        "drifting": drifting,
        "outliers": outliers,
        "unsteady": unsteady,
        "not_verified": [
            {"unit": h.unit, "problems": h.problems, "versions_used": [p.version for p in h.points]}
            for h in fleet
            if h.problems
        ],
        "tests": {**drift_test, "outliers": outlier_test, "settings": settings.to_dict()},
    }
    return result


def fleet_trends(
    registry: Registry | str | os.PathLike, settings: TrendSettings = TrendSettings(), workers: int | None = None
) -> TrendsResult:
    """Read every unit of the registry (verified; ``workers`` as :func:`read_fleet`) and :func:`analyse` them."""
    reg = registry if isinstance(registry, Registry) else Registry(registry)
    if not reg.root.is_dir():
        from pipeline.errors import RegistryError

        raise RegistryError("no registry here (not a directory)", path=str(reg.root))
    return analyse(read_fleet(reg, workers=workers), settings)


def _g(x: float | None, unit: str = "") -> str:
    return "-" if x is None else f"{x:.4g}{(' ' + unit) if unit else ''}"


def trends_text(report: dict) -> str:
    """The report for a person: one block per finding kind with each entry's figures, the tests' thresholds, the
    units whose chain did not verify."""
    tests = report["tests"]
    lines = [f"{report['units']} units, {report['versions']} passport versions (every one verified before use)"]
    d = tests["drift"]
    lines.append(
        f"drifting (|rate|/sigma > {_g(d['z_threshold'])}, Bonferroni over {d['series_tested']} series): "
        f"{len(report['drifting']) or 'none'}"
    )
    for e in report["drifting"]:
        lines.append(
            f"  {e['unit']} {e['constant']}: {_g(e['rate_scaled_per_year'], e['scaled_unit'])} "
            f"({_g(e['rate_per_year'], e['constant_unit'] + '/year')} +- {_g(e['sigma_per_year'])}, "
            f"{abs(e['z']):.1f} sigma) over v{', v'.join(str(v['version']) for v in e['versions'])}; "
            f"reaches the {e['grade']} limit {e['limit_scaled']:.4g} {e['scaled_unit'].removesuffix('/year')} "
            + (f"on {e['due_utc'][:10]}" if e["due_utc"] else "never")
        )
    u = tests["unsteady"]
    lines.append(
        f"unsteady (scatter about the line, p < {_g(u['p_threshold'])} over {u['series_tested']} series): "
        f"{len(report['unsteady']) or 'none'}"
    )
    for e in report["unsteady"]:
        lines.append(
            f"  {e['unit']} {e['constant']}: chi2 {e['chi2']:.1f} on {e['dof']} dof (p {e['p_value']:.2g}); "
            f"recent rate {_g(e['recent_rate_scaled_per_year'], e['scaled_unit'])}, line "
            f"{_g(e['line_rate_per_year'], e['constant_unit'] + '/year')}; at the recent rate the limit comes "
            + (f"on {e['due_utc'][:10]}" if e["due_utc"] else "never")
        )
    o = tests["outliers"]
    sizes = ", ".join(f"{_g(t)} for {n} units" for n, t in o["z_threshold_by_fleet_size"].items()) or "no type assessed"
    lines.append(
        f"outliers (|robust z| > {sizes}; {o['comparisons']} comparisons): {len(report['outliers']) or 'none'}"
    )
    for e in report["outliers"]:
        lines.append(
            f"  {e['unit']} v{e['version']} {e['constant']}: {_g(e['value'])} against the fleet's median "
            f"{_g(e['fleet_median'])} (robust sigma {_g(e['fleet_sigma'])}, {e['fleet_units']} units of "
            f"{e['unit_type']}): z {e['robust_z']:+.1f}"
        )
    for t in o["types_not_assessed"]:
        lines.append(f"  not assessed (fewer than {tests['settings']['min_fleet']} units): {t}")
    for e in report["not_verified"]:
        used = ", ".join(f"v{v}" for v in e["versions_used"]) or "none"
        lines.append(f"NOT VERIFIED {e['unit']}: {e['problems'][0]} (versions used: {used})")
    return "\n".join(lines)
