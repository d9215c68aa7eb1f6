"""Verification at the VP positions (seed 000, eq. 14): gravity-module error dg = |a_hat| - 1 in g, before and
after compensation, judged against tolerances."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from pipeline import compensate
from pipeline.model import gravity_module_error_g


@dataclass(frozen=True)
class Tolerances:
    """|dg| limits in g after compensation: ``normal_g`` within ``normal_band_c`` (C) of T0, ``operating_range_g``
    over the rest of the range; ``grade`` the unit class they are the limits of (:data:`GRADES`) and ``basis`` where
    the grade and limits came from (``--grade``, the run's ``unit_grade``, the default; a limit given on the command
    line), for the passport and the texts that state them."""

    normal_g: float = 3e-4
    operating_range_g: float = 1e-3
    normal_band_c: float = 3.0
    grade: str = "navigation"
    basis: str = ""

    def limit_g(self, temp_c: float, normal_temp_c: float) -> float:
        return self.normal_g if abs(temp_c - normal_temp_c) <= self.normal_band_c else self.operating_range_g

    def to_dict(self) -> dict:
        return asdict(self)

    def text(self) -> str:
        """One line: the grade and its limits, e.g. ``grade consumer: |dg| <= 0.01 g within 3 C of T0, 0.03 g
        over the range (unit_grade of the run)``."""
        basis = f" ({self.basis})" if self.basis else ""
        return (
            f"grade {self.grade}: |dg| <= {self.normal_g:g} g within {self.normal_band_c:g} C of T0, "
            f"{self.operating_range_g:g} g over the range{basis}"
        )


#: The unit grades (docs/physics.md, "Unit grades") and their verification limits, |dg| after compensation at T0 / over
#: the range. The one table of them: ``calibrate --grade``, the run's ``unit_grade`` and ``trends`` read it.
GRADES: dict[str, Tolerances] = {
    "navigation": Tolerances(3e-4, 1e-3, grade="navigation"),
    "tactical": Tolerances(1e-3, 3e-3, grade="tactical"),
    "industrial": Tolerances(3e-3, 1e-2, grade="industrial"),
    "consumer": Tolerances(1e-2, 3e-2, grade="consumer"),
}
#: the grade of a unit whose run and command line name none (seed 000's tolerances)
DEFAULT_GRADE = "navigation"


def grade_tolerances(grade: str) -> Tolerances:
    """The limits of ``grade`` (:data:`GRADES`); ValueError naming the grades for any other name."""
    try:
        return GRADES[grade]
    except KeyError:
        raise ValueError(f"unknown unit grade {grade!r} ({', '.join(GRADES)})") from None


def resolve_tolerances(
    grade: str | None,
    run_grade: str | None,
    *,
    normal_g: float | None = None,
    operating_range_g: float | None = None,
) -> Tolerances:
    """The limits a calibration verifies with: the grade named on the command line (``grade``), else the run's
    ``unit_grade`` (``run_grade``), else :data:`DEFAULT_GRADE`; ``normal_g`` / ``operating_range_g`` given (the
    command line's ``--tol-normal-g`` / ``--tol-range-g``) replace that grade's. ``basis`` says which."""
    if grade is not None:
        name, basis = grade, "--grade"
    elif run_grade:
        name, basis = run_grade, "unit_grade of the run"
    else:
        name, basis = DEFAULT_GRADE, "the default grade: neither --grade nor the run's unit_grade names one"
    tol = grade_tolerances(name)
    given = [f for f, v in (("--tol-normal-g", normal_g), ("--tol-range-g", operating_range_g)) if v is not None]
    if given:
        basis += f"; {' and '.join(given)} given"
    return replace(
        tol,
        normal_g=tol.normal_g if normal_g is None else float(normal_g),
        operating_range_g=tol.operating_range_g if operating_range_g is None else float(operating_range_g),
        basis=basis,
    )


@dataclass(frozen=True)
class VerificationRow:
    """One VP segment: dg in g uncompensated (normal-temperature constants), by method 1 and method 2 (full eq. 6/7
    and simplified eq. 8/9), the tolerance applied and the verdict (on method 1)."""

    temp_c: float
    position: str
    run_id: str
    t_start_ns: int
    t_end_ns: int
    dg_uncompensated_g: float
    dg_method1_g: float
    dg_method2_g: float
    dg_method2_simplified_g: float
    tolerance_g: float
    passed: bool
    #: index of the plateau (within its run) the segment lies on or settles towards; None where not known (rows of
    #: passports written before it was recorded)
    plateau: int | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def verify_positions(
    model,
    positions: list[str],
    u_v: np.ndarray,
    temp_c: np.ndarray,
    *,
    normal_temp_c: float,
    tolerances: Tolerances = Tolerances(),
    run_ids: list[str] | None = None,
    spans_ns: list[tuple[int, int]] | None = None,
    plateaus: list[int | None] | None = None,
) -> list[VerificationRow]:
    """dg at each verification segment (mean outputs ``u_v`` (m, 3) V at mean temperatures ``temp_c`` (m,) C);
    ``run_ids``, ``spans_ns`` (start, end ns) and ``plateaus`` (plateau index in its run) say where each is."""
    u_v = np.atleast_2d(np.asarray(u_v, dtype=float))
    temp_c = np.asarray(temp_c, dtype=float)
    dg0 = gravity_module_error_g(compensate.uncompensated(model, u_v))
    dg1 = gravity_module_error_g(compensate.method1(model, u_v, temp_c))
    dg2 = gravity_module_error_g(compensate.method2(model, u_v, temp_c, full=True))
    dg2s = gravity_module_error_g(compensate.method2(model, u_v, temp_c, full=False))
    rows = []
    for k, pos in enumerate(positions):
        lim = tolerances.limit_g(float(temp_c[k]), normal_temp_c)
        span = spans_ns[k] if spans_ns else (0, 0)
        rows.append(
            VerificationRow(
                temp_c=round(float(temp_c[k]), 3),
                position=pos,
                run_id=run_ids[k] if run_ids else "",
                t_start_ns=int(span[0]),
                t_end_ns=int(span[1]),
                dg_uncompensated_g=float(dg0[k]),
                dg_method1_g=float(dg1[k]),
                dg_method2_g=float(dg2[k]),
                dg_method2_simplified_g=float(dg2s[k]),
                tolerance_g=lim,
                passed=bool(abs(dg1[k]) <= lim),
                plateau=None if plateaus is None or (p := plateaus[k]) is None else int(p),
            )
        )
    return rows


#: a failing VP further than this (C) outside the calibrated range is extrapolated to; nearer, it lies on the edge
#: plateau itself (its VPs scatter by hundredths of a degree about the plateau's test positions)
OUTSIDE_RANGE_C = 1.0


def failed_outside(rows: list[dict], valid_temp_c) -> str | None:
    """Where failing rows (``rows``: :meth:`VerificationRow.to_dict` of a passport, ``passed`` false) lie outside
    the temperatures the passport's data covered (``valid_temp_c``, lo and hi in C) by more than
    :data:`OUTSIDE_RANGE_C`, the clause saying how many
    of how many failed, how many of them outside and at which temperatures (C), and how far (C) the thermal model
    was extrapolated to them; None when every failing row lies within the range (or none fails)."""
    failing = [r for r in rows if not r.get("passed", True)]
    if not failing or not valid_temp_c:
        return None
    lo, hi = float(valid_temp_c[0]), float(valid_temp_c[1])
    beyond = {id(r): max(lo - r["temp_c"], r["temp_c"] - hi) for r in failing}
    out = [r for r in failing if beyond[id(r)] > OUTSIDE_RANGE_C]
    if not out:
        return None
    at = ", ".join(f"{t:+.1f}" for t in sorted({round(float(r["temp_c"]), 1) for r in out}))
    return (
        f"at {len(failing)} of {len(rows)} verification positions, {len(out)} of them at {at} C, outside the "
        f"calibrated {lo:+.1f} .. {hi:+.1f} C (the thermal model extrapolated by up to "
        f"{max(beyond[id(r)] for r in out):.0f} C)"
    )


def overall_status(rows: list[VerificationRow]) -> str:
    """``pass`` when every VP segment is within tolerance, ``fail`` otherwise, ``unverified`` without VP data."""
    if not rows:
        return "unverified"
    return "pass" if all(r.passed for r in rows) else "fail"


def summary_by_temperature(rows: list[VerificationRow], cluster_tol_c: float = 3.0) -> list[dict]:
    """Max |dg| per verification temperature, before and after each compensation (g)."""
    from pipeline.thermal import cluster_temperatures

    if not rows:
        return []
    temps = np.array([r.temp_c for r in rows])
    labels = cluster_temperatures(temps, cluster_tol_c)
    out = []
    for c in range(labels.max() + 1):
        sel = [r for r, lab in zip(rows, labels) if lab == c]
        out.append(
            {
                "temp_c": round(float(np.mean([r.temp_c for r in sel])), 2),
                "n": len(sel),
                "max_abs_dg_uncompensated_g": max(abs(r.dg_uncompensated_g) for r in sel),
                "max_abs_dg_method1_g": max(abs(r.dg_method1_g) for r in sel),
                "max_abs_dg_method2_g": max(abs(r.dg_method2_g) for r in sel),
                "max_abs_dg_method2_simplified_g": max(abs(r.dg_method2_simplified_g) for r in sel),
            }
        )
    return out


def verification_visits(rows: list[dict], cluster_tol_c: float = 3.0) -> list[dict]:
    """The verification rows (dicts, as in a passport's ``verification``) by visit of a temperature: rows of one
    temperature cluster that follow each other in time (in one run) on one plateau make one visit (two plateaus
    at one temperature are two visits, with nothing verified between them or not). Visits coldest first, those of
    one temperature in time order; each ``{"rows", "temp_c" (mean, C), "visit" (1, 2, ...), "visits" (at that
    temperature)}``."""
    from pipeline.thermal import cluster_temperatures

    if not len(rows):
        return []
    rows = sorted(rows, key=lambda r: (r.get("run_id", ""), r.get("t_start_ns", 0)))
    labels = cluster_temperatures(np.array([r["temp_c"] for r in rows], dtype=float), cluster_tol_c)
    groups: list[list[int]] = []  # row indices of each visit, in time order
    for i, lab in enumerate(labels):
        if (
            i
            and lab == labels[i - 1]
            and rows[i].get("run_id") == rows[i - 1].get("run_id")
            and rows[i].get("plateau") == rows[i - 1].get("plateau")
        ):
            groups[-1].append(i)
        else:
            groups.append([i])
    cluster_temp = {
        c: float(np.mean([r["temp_c"] for r, lab in zip(rows, labels) if lab == c])) for c in set(labels.tolist())
    }
    order = sorted(range(len(groups)), key=lambda g: (cluster_temp[labels[groups[g][0]]], g))
    count = {c: sum(labels[g[0]] == c for g in groups) for c in cluster_temp}
    seen: dict[int, int] = {}
    out = []
    for g in order:
        c = int(labels[groups[g][0]])
        seen[c] = seen.get(c, 0) + 1
        sel = [rows[i] for i in groups[g]]
        out.append(
            {"rows": sel, "temp_c": float(np.mean([r["temp_c"] for r in sel])), "visit": seen[c], "visits": count[c]}
        )
    return out
