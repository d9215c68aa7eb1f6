"""Calibration of one unit from segmented runs: per-plateau constants, the thermal model, VP verification.

The steps, each a pure function (the Prefect flow in ``flows/calibrate.py`` calls them one per task):

1. ``observations_from_segmentation``: the averaged static segments of one run as :class:`Observation` rows;
2. ``fit_unit``: per-plateau constants (six-position closed form or least squares), then the thermal model, with
   the segment averages referred to their plateau's mean temperature (the unit is still settling during a plateau's
   positions, so each position is at a slightly different temperature);
3. ``verify_unit``: dg at every VP observation, uncompensated and by both compensation methods.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from pipeline.constants import fit_constants
from pipeline.errors import CalibrationError
from pipeline.positions import (
    TEST_POSITIONS,
    gravity_vector_g,
    is_test_position,
    is_verification_position,
)
from pipeline.segment import SegmentSettings, segment_run
from pipeline.thermal import ThermalModel, cluster_temperatures, fit_thermal_model
from pipeline.uncertainty import (
    ThermalSigma,
    design_matrix,
    estimator_matrix,
    excess_scatter_v,
    plateau_sigma,
    segment_noise_var_v2,
    thermal_sigma,
)
from pipeline.verify import (
    Tolerances,
    VerificationRow,
    overall_status,
    verify_positions,
)


@dataclass(frozen=True)
class CalibrationSettings:
    """Everything that changes a passport. ``thermal_model``: auto | poly1 | poly2 | poly3 | piecewise;
    ``constants_method``: auto | six_position | least_squares."""

    thermal_model: str = "auto"
    constants_method: str = "auto"
    cluster_tol_c: float = 3.0
    temperature_referencing_passes: int = 2
    tolerances: Tolerances = field(default_factory=Tolerances)
    segment: SegmentSettings = field(default_factory=SegmentSettings)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Observation:
    """One averaged static segment: named position, mean outputs (V), mean AU temperature (C)."""

    run_id: str
    plateau: int | None          # plateau index within its run (None: not on a plateau)
    position: str
    u_v: tuple[float, float, float]
    std_v: tuple[float, float, float]
    count: int
    temp_c: float
    t_start_ns: int
    t_end_ns: int
    source: str = ""             # the file or directory the run was read from ("" for a run made in memory)


@dataclass(frozen=True)
class PlateauConstants:
    run_id: str
    plateau: int
    temp_c: float
    K: np.ndarray                # (3, 3) V/g
    U0: np.ndarray               # (3,) V
    positions: tuple[str, ...]
    method: str
    residual_rms_v: float
    K_sigma: np.ndarray | None = None     # (3, 3) V/g, standard uncertainty of K (None: not estimated)
    U0_sigma: np.ndarray | None = None    # (3,) V

    def to_dict(self) -> dict:
        return {"temp_c": round(self.temp_c, 4), "run_id": self.run_id, "plateau": self.plateau,
                "K": self.K.tolist(), "U0": self.U0.tolist(), "positions": list(self.positions),
                "method": self.method, "residual_rms_v": self.residual_rms_v}


@dataclass
class UnitFit:
    unit: str
    normal_temp_c: float
    per_plateau: list[PlateauConstants]
    model: ThermalModel
    skipped: list[str]           # one line per plateau that could not be used, and why
    uncertainty: ThermalSigma | None = None      # of K0, U00 and the thermal model's coefficients
    valid_temp_c: tuple[float, float] | None = None   # the calibration temperatures the data covered (C)
    excess_scatter_v: np.ndarray | None = None   # (3,) V, segment scatter beyond the measured noise (pooled)


def observations_from_segmentation(run_id: str, segmentation, source: str = "") -> list[Observation]:
    """Named static segments on plateaus (and VP segments anywhere) as observations (``source``: the run's file)."""
    out = []
    for s in segmentation.segments:
        if s.position is None or s.count == 0:
            continue
        if s.plateau is None and not is_verification_position(s.position):
            continue
        out.append(Observation(run_id=run_id, plateau=s.plateau, position=s.position, u_v=tuple(s.mean_v),
                               std_v=tuple(s.std_v), count=int(s.count), temp_c=float(s.temp_c),
                               t_start_ns=int(s.t_start_ns), t_end_ns=int(s.t_end_ns), source=source))
    return out


def unit_of(runs) -> str:
    """The one unit serial of ``runs``; CalibrationError when none are given or they are of different units."""
    serials = sorted({r.meta.unit_serial for r in runs})
    if not serials:
        raise CalibrationError("no runs given")
    if len(serials) != 1:
        raise CalibrationError(f"runs of different units given together: {', '.join(serials)}")
    return serials[0]


def observe_run(run, settings: SegmentSettings = SegmentSettings()) -> tuple[list[Observation], list[str]]:
    """Segment a run and return its observations and the segmenter's and reader's warnings.

    A run with no named static position on any temperature plateau is of no use to a calibration:
    :class:`CalibrationError` naming the file, the stream at fault and the time span.
    """
    seg = segment_run(run, settings)
    obs = observations_from_segmentation(run.meta.run_id, seg, run.source)
    warnings = list(run.warnings) + list(seg.warnings)
    if not any(o.plateau is not None for o in obs):
        raise _unusable_run(run, seg.plateaus, warnings, settings)
    return obs, warnings


def _unusable_run(run, plateaus, warnings: list[str], settings: SegmentSettings) -> CalibrationError:
    if not plateaus:
        t = run.au_temperature["t_ns"]
        temp = run.au_temperature["temp_c"].fill_nan(None)
        reads = f", it reads {temp.min():.2f}..{temp.max():.2f} C" if temp.null_count() < temp.len() else ""
        return CalibrationError(f"no temperature plateau: the AU temperature never stays within "
                                f"{settings.plateau_rate_c_per_min} C/min for {settings.plateau_min_s:.0f} s{reads}",
                                path=run.source, stream="au_temperature",
                                where=f"t_ns={t.min()}..{t.max()}")
    why = f" ({'; '.join(warnings)})" if warnings else ""
    return CalibrationError(f"no named static position on any of the {len(plateaus)} temperature plateau(s){why}",
                            path=run.source, stream="voltmeter",
                            where=f"t_ns={plateaus[0].t_start_ns}..{plateaus[-1].t_end_ns}")


def _group_plateaus(obs: list[Observation]) -> dict[tuple[str, int], list[Observation]]:
    groups: dict[tuple[str, int], list[Observation]] = {}
    for o in obs:
        if o.plateau is not None and is_test_position(o.position):
            groups.setdefault((o.run_id, o.plateau), []).append(o)
    return groups


def _fit_plateaus(groups, shift_v: dict[int, np.ndarray], method: str, skipped: list[str] | None
                  ) -> list[PlateauConstants]:
    fits = []
    for (run_id, p), rows in groups.items():
        names = [o.position for o in rows]
        missing = [tp for tp in TEST_POSITIONS if tp not in names]
        if missing:
            # a position carried through the ramp onto a VP plateau is not an attempt at calibration
            if skipped is not None and len(set(names)) > 1:
                skipped.append(f"{run_id} plateau {p} at {np.mean([o.temp_c for o in rows]):.1f} C "
                               f"(t_ns={min(o.t_start_ns for o in rows)}..{max(o.t_end_ns for o in rows)}): "
                               f"fewer than six test positions (missing {', '.join(missing)})")
            continue
        u = np.array([np.asarray(o.u_v) - shift_v.get(id(o), 0.0) for o in rows])
        # one weight per segment: a position carried through a ramp and soak is a long segment taken while the
        # unit settled; it should not outweigh the program's own hold of that position
        cf = fit_constants(names, u, method=method)
        fits.append(PlateauConstants(
            run_id=run_id, plateau=p, temp_c=float(np.mean([o.temp_c for o in rows])), K=cf.K, U0=cf.U0,
            positions=tuple(dict.fromkeys(names)), method=cf.method,
            residual_rms_v=float(np.sqrt(np.mean(cf.residual_v ** 2)))))
    return fits


def fit_unit(unit: str, observations: list[Observation], settings: CalibrationSettings = CalibrationSettings(),
             normal_temp_c: float = 20.0) -> UnitFit:
    """Per-plateau constants and the thermal model from a unit's observations (any number of runs)."""
    groups = _group_plateaus(observations)
    skipped: list[str] = []
    fits = _fit_plateaus(groups, {}, settings.constants_method, skipped)
    if not fits:
        on_plateaus = [o for rows in groups.values() for o in rows]
        where = (f"t_ns={min(o.t_start_ns for o in on_plateaus)}..{max(o.t_end_ns for o in on_plateaus)}"
                 if on_plateaus else None)
        raise CalibrationError("no temperature plateau with the six test positions TP1..TP6"
                               + (f" ({'; '.join(skipped)})" if skipped else ""),
                               path=", ".join(sorted({o.source for o in observations if o.source})) or None,
                               stream="voltmeter", where=where)
    def thermal(kind: str, temps=None, K=None, U0=None) -> ThermalModel:
        temps = np.array([f.temp_c for f in fits]) if temps is None else temps
        try:
            return fit_thermal_model(temps, np.array([f.K for f in fits]) if K is None else K,
                                     np.array([f.U0 for f in fits]) if U0 is None else U0,
                                     kind, normal_temp_c, settings.cluster_tol_c)
        except ValueError as e:
            distinct = sorted({round(float(t)) for t in temps})
            raise CalibrationError(f"thermal model {kind}: {e}; calibration temperatures found: "
                                   f"{', '.join(f'{t:+d} C' for t in distinct)}", stream="au_temperature") from None

    for _ in range(settings.temperature_referencing_passes):
        # Refer every segment average to its plateau's mean temperature. The local slopes come from the smooth
        # default polynomial (a piecewise model's slopes are chords, wrong at the breakpoints themselves).
        local = thermal("auto")
        shift = {}
        plateau_temp = {(f.run_id, f.plateau): f.temp_c for f in fits}
        for key, rows in groups.items():
            if key not in plateau_temp:
                continue
            t_seg = np.array([o.temp_c for o in rows])
            a = np.array([gravity_vector_g(o.position) for o in rows])
            Ks, U0s = local.constants_at(t_seg)
            Kp, U0p = local.constants_at(np.full(len(rows), plateau_temp[key]))
            d = np.einsum("nij,nj->ni", Ks - Kp, a) + (U0s - U0p)
            shift.update({id(o): d[k] for k, o in enumerate(rows)})
        fits = _fit_plateaus(groups, shift, settings.constants_method, None)
    fits, tau_v = _with_uncertainty(fits, groups, shift if settings.temperature_referencing_passes else {})
    nominal, K_nom, U0_nom = _at_calibration_temperatures(fits, thermal("auto"), normal_temp_c,
                                                          settings.cluster_tol_c)
    model = thermal(settings.thermal_model, nominal, K_nom, U0_nom)
    sigma = thermal_sigma(lambda t, K, U0: thermal(settings.thermal_model, t, K, U0), nominal, K_nom, U0_nom,
                          np.array([f.K_sigma for f in fits]), np.array([f.U0_sigma for f in fits]))
    temps = [f.temp_c for f in fits]
    fits.sort(key=lambda f: (f.temp_c, f.run_id, f.plateau))
    return UnitFit(unit=unit, normal_temp_c=normal_temp_c, per_plateau=fits, model=model, skipped=skipped,
                   uncertainty=sigma, valid_temp_c=(round(min(temps), 1), round(max(temps), 1)),
                   excess_scatter_v=tau_v)


def _with_uncertainty(fits: list[PlateauConstants], groups, shift_v: dict[int, np.ndarray]
                      ) -> tuple[list[PlateauConstants], np.ndarray]:
    """The plateau fits with the standard uncertainties of their constants (:mod:`pipeline.uncertainty`): the
    noise measured in each segment plus the excess scatter of the fits' residuals, pooled over the plateaus."""
    parts = []
    for f in fits:
        rows = groups[(f.run_id, f.plateau)]
        names = [o.position for o in rows]
        u = np.array([np.asarray(o.u_v) - shift_v.get(id(o), 0.0) for o in rows])
        A = design_matrix(names)
        resid = u - A @ np.vstack([f.K.T, f.U0])
        parts.append((estimator_matrix(names, f.method), A, resid,
                      segment_noise_var_v2(np.array([o.std_v for o in rows]), np.array([o.count for o in rows]))))
    tau_v = excess_scatter_v([p[2] for p in parts], [p[3] for p in parts], [p[0] for p in parts],
                             [p[1] for p in parts])
    out = []
    for f, (W, _, _, var) in zip(fits, parts):
        K_sig, U0_sig = plateau_sigma(W, var + tau_v ** 2)
        out.append(replace(f, K_sigma=K_sig, U0_sigma=U0_sig))
    return out, tau_v


def _at_calibration_temperatures(fits: list[PlateauConstants], local: ThermalModel, normal_temp_c: float,
                                 cluster_tol_c: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def verify_unit(model, observations: list[Observation], normal_temp_c: float,
                tolerances: Tolerances = Tolerances()) -> tuple[list[VerificationRow], str]:
    """dg at every VP observation on a plateau; returns the rows (by time) and the overall status."""
    vp = sorted((o for o in observations if is_verification_position(o.position) and o.plateau is not None),
                key=lambda o: (o.run_id, o.t_start_ns))
    if not vp:
        return [], "unverified"
    rows = verify_positions(model, [o.position for o in vp], np.array([o.u_v for o in vp]),
                            np.array([o.temp_c for o in vp]), normal_temp_c=normal_temp_c, tolerances=tolerances,
                            run_ids=[o.run_id for o in vp], spans_ns=[(o.t_start_ns, o.t_end_ns) for o in vp])
    return rows, overall_status(rows)


def plateau_summary(observations: list[Observation], cluster_tol_c: float = 3.0) -> list[dict]:
    """``[{"temp_c", "positions"}]`` per plateau, in time order (for ``calibrate --json``)."""
    groups: dict[tuple[str, int], list[Observation]] = {}
    for o in observations:
        if o.plateau is not None:
            groups.setdefault((o.run_id, o.plateau), []).append(o)
    out = []
    for (run_id, p), rows in sorted(groups.items(), key=lambda kv: (kv[0][0], min(o.t_start_ns for o in kv[1]))):
        rows.sort(key=lambda o: o.t_start_ns)
        out.append({"temp_c": round(float(np.mean([o.temp_c for o in rows])), 2), "run_id": run_id,
                    "positions": [o.position for o in rows]})
    return out


def calibration_result(fit: UnitFit, rows: list[VerificationRow], status: str, plateaus: list[dict],
                       published) -> dict:
    """The ``calibrate --json`` object of contract.md for a published passport."""
    return {
        "unit": fit.unit, "version": published.version, "passport": str(published.path),
        "passport_sha256": published.sha256, "created": published.created,
        "plateaus": plateaus,
        "verification": [{"temp_c": r.temp_c, "position": r.position, "dg_uncompensated_g": r.dg_uncompensated_g,
                          "dg_method1_g": r.dg_method1_g, "dg_method2_g": r.dg_method2_g} for r in rows],
        "status": status,
    }
