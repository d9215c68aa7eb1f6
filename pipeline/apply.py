"""A passport applied to a recording: the compensated specific force at every voltmeter sample (docs/contract.md,
"apply output").

The passport's full model is used, whatever the method that made it: the constants at T0, the thermal model
(polynomial or piecewise linear, :mod:`pipeline.thermal`) and, for a passport of the differential method, its rate
terms and the lag of the sensing element (:mod:`pipeline.calibrate.differential`). Method 1 of seed 000 inverts the
model at each sample's temperature: ``a = K(T)^-1 (U - U0(T))`` in g.

A passport extended by ``diagnose`` (``extended_model``: a refitted base thermal model plus catalogue effects) is
applied with the extended model wherever its terms are functions of what the recording itself holds: time since the
first voltmeter sample (drift, warm-up), temperature and its history (curvature, the element's lag, hysteresis by
the direction the temperature last came from), the specific force (scale nonlinearity, solved iteratively). Terms
that need the fixture's moves (``tilt_settling``) are left out, with one warning naming them; the fixture's face
error is the fixture's, not the unit's, and is never compensated (:mod:`pipeline.effects.model`).

The temperature at a sample is the AU thermosensor interpolated at its time (smoothed as when the passport was made
where the passport has rate terms). One output row per input row, in the input's order; a sample whose voltages or
temperature are not finite gives NaN, never a dropped row. ``in_range`` says whether the temperature lies within the
passport's valid range (:attr:`pipeline.passport.document.Passport.valid_range_c`: the range its data covered);
outside it the model is still applied and :func:`apply_passport` returns one warning.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.dynamics import Thermosensor, first_order_lag, ramp_direction, smooth_temperature
from pipeline.errors import ThermocalError
from pipeline.model import specific_force_g
from pipeline.passport.document import Passport, failed_verification, load_passport
from pipeline.run import NS_PER_S as _NS
from pipeline.run import SLAB_SAMPLES as _SLAB  # samples compensated at a time (the K(T) stack: 72 bytes a sample)
from pipeline.run import Run
from pipeline.utc import utc_text
from pipeline.words import printable

APPLY_COLUMNS = ("t_ns", "ax_g", "ay_g", "az_g", "temp_c", "in_range")
#: ``apply --out``'s file format by the name's suffix (lower case; no suffix: Parquet), docs/contract.md
OUTPUT_FORMATS = {"": "parquet", ".parquet": "parquet", ".pq": "parquet", ".mcap": "mcap", ".csv": "csv"}


def output_format(path: str | Path) -> str:
    """The format :func:`write_applied` writes to ``path``: ``parquet``, ``mcap`` or ``csv`` by its suffix. Any
    other suffix is refused in one line before anything is read (a ``.csv`` or ``.json`` name holding Parquet would
    mislead whoever opens it)."""
    suffix = Path(path).suffix.lower()
    if suffix not in OUTPUT_FORMATS:
        raise ThermocalError(
            f"apply writes Parquet (.parquet, .pq or no suffix), MCAP (.mcap) or CSV (.csv), not a '{suffix}' file",
            path=str(path),
        )
    return OUTPUT_FORMATS[suffix]


@dataclass
class Applied:
    """The compensated recording: ``table`` with :data:`APPLY_COLUMNS` (one row per voltmeter row), the validity
    range used (C, or None when the passport states none), and warnings for the user."""

    table: pl.DataFrame
    valid_temp_c: tuple[float, float] | None
    warnings: list[str] = field(default_factory=list)


def _model(p: Passport):
    """(model with constants_at(T[, rate]), lag tau s, smoothing window s or None, warnings, extended) of a passport;
    for a passport with an extended model (``extended`` True), the part of that model apply can evaluate
    (:func:`_applicable_extended`)."""
    from pipeline.thermal import DifferentialModel

    warnings: list[str] = []
    if p.extended is not None:
        return _applicable_extended(p.extended, warnings), 0.0, None, warnings, True
    if p.rate_terms is not None:
        return (
            DifferentialModel(p.thermal_model, p.rate_terms),
            p.rate_terms.lag_tau_s,
            p.rate_terms.temp_smooth_s,
            warnings,
            False,
        )
    return p.thermal_model, 0.0, None, warnings, False


def _applicable_extended(ext, warnings: list[str]):
    """The extended model without the terms that need the fixture (its moves: ``Effect.needs_fixture``), and one
    warning naming those."""
    from pipeline.effects.model import ExtendedModel  # the effect catalogue (scipy.signal): only for such passports

    left = [e for e in ext.effects if e.needs_fixture]
    if left:
        warnings.append(
            "the passport's extended model is applied without "
            + "; ".join(
                f"{e.id} (it needs {e.needs_fixture}, which apply does not locate in the recording)" for e in left
            )
        )
    return ExtendedModel(ext.base, [e for e in ext.effects if not e.needs_fixture], ext.source)


def _extended_context(run: Run, t_ns: np.ndarray, temp_c: np.ndarray, ext):
    """What the extended model's terms read at the samples ``t_ns``: a function ``(s0, s1) -> (SignalContext,
    element temperature C or None)`` for a slab of samples. Times are s since the first voltmeter sample (as in a
    diagnosis), the direction of the last ramp and the element's lag come from the whole temperature record; no
    position or move is known (the terms that need them are not in ``ext``)."""
    from pipeline.effects.base import SignalContext

    start_ns = int(t_ns[0]) if t_ns.size else 0
    tt, temp = run.thermosensor()
    order = np.argsort(tt, kind="stable")
    th_s, th_c = (tt[order] - start_ns) / _NS, temp[order]
    lagged = first_order_lag(th_s, th_c, ext.lag_tau_s) if ext.lag_tau_s is not None and th_s.size >= 2 else None
    ramp_at = ramp_direction(run, start_ns)  # from the whole record, once

    def at(s0: int, s1: int):
        t_s = (t_ns[s0:s1] - start_ns) / _NS
        tc = np.where(np.isfinite(temp_c[s0:s1]), temp_c[s0:s1], float(ext.base.normal_temp_c))
        element = None if lagged is None else np.interp(t_s, th_s, lagged)
        ramp = ramp_at(t_s)
        n = t_s.size
        ctx = SignalContext(
            t_s=t_s,
            temp_c=tc,
            a_g=np.zeros((n, 3)),
            position_idx=np.full(n, -1),
            move_start_s=np.zeros(0),
            arrive_s=np.zeros(0),
            constants=ext.base,
            normal_temp_c=float(ext.base.normal_temp_c),
            ramp_sign=ramp,
            start_ns=start_ns,
        )
        return ctx, element

    return at


def _temperature_at(
    run: Run, t_ns: np.ndarray, lag_tau_s: float, smooth_s: float | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """AU temperature (C) and, with ``smooth_s``, its rate (C/min) at the times ``t_ns``; NaN outside the finite
    thermosensor record."""
    tt = run.au_temperature["t_ns"].to_numpy()
    temp = run.au_temperature["temp_c"].to_numpy()
    ok = np.isfinite(temp)
    tt, temp = tt[ok], temp[ok]
    order = np.argsort(tt, kind="stable")
    tt, temp = tt[order], temp[order]
    if tt.size == 0:
        return np.full(t_ns.size, np.nan), None
    t_ref = int(tt[0])
    x = (t_ns - t_ref) / _NS
    xs = (tt - t_ref) / _NS
    outside = (t_ns < tt[0]) | (t_ns > tt[-1])
    rate = None
    if smooth_s is not None and tt.size >= 5:
        sm, rt = smooth_temperature(xs, temp, smooth_s)
        values, rate = Thermosensor(xs, sm, rt, t_ref).at(x, lag_tau_s)
    else:
        values = np.interp(x, xs, temp)
    values = np.where(outside, np.nan, values)
    return values, rate


def apply_passport(passport: Passport | dict, run: Run) -> Applied:
    """The passport's model applied to every voltmeter sample of ``run`` (see the module doc): specific force in
    g along the unit's axes, the AU temperature at each sample, ``in_range``. ``passport``: a :class:`Passport` (a
    document is loaded once here, :func:`pipeline.passport.document.load_passport`)."""
    passport = load_passport(passport)
    model, lag_s, smooth_s, warnings, is_extended = _model(passport)
    t_ns = run.voltmeter["t_ns"].to_numpy()
    temp_c, rate = _temperature_at(run, t_ns, lag_s, smooth_s)
    n = t_ns.size
    a = np.empty((n, 3))
    cols = [run.voltmeter[c].to_numpy() for c in ("ux", "uy", "uz")]
    extended = _extended_context(run, t_ns, temp_c, model) if is_extended else None
    for s0 in range(0, n, _SLAB):
        s1 = min(s0 + _SLAB, n)
        u = np.column_stack([c[s0:s1] for c in cols])
        good = np.isfinite(temp_c[s0:s1])
        if extended is not None:
            with np.errstate(invalid="ignore"):
                out = model.specific_force_g(u, *extended(s0, s1))
        else:
            tc = np.where(good, temp_c[s0:s1], float(model.normal_temp_c))
            K, U0 = model.constants_at(tc) if rate is None else model.constants_at(tc, np.where(good, rate[s0:s1], 0.0))
            with np.errstate(invalid="ignore"):
                out = specific_force_g(K, U0, u)
        out[~good] = np.nan
        a[s0:s1] = out
    if passport.status == "fail":
        warnings.append(failed_verification(f"the passport ({passport.unit} v{passport.version})"))
    if passport.unit and run.meta.unit_serial and passport.unit != run.meta.unit_serial:
        warnings.append(
            f"the passport is unit {passport.unit}'s (v{passport.version}) but the run records unit "
            f"{run.meta.unit_serial}: applied all the same, though each unit has its own constants"
        )
    rng = passport.valid_range_c
    if rng is None:
        in_range = np.isfinite(temp_c)
        warnings.append("the passport states no valid temperature range: in_range only marks a known temperature")
    else:
        with np.errstate(invalid="ignore"):
            in_range = (temp_c >= rng[0]) & (temp_c <= rng[1])
        out_n = int(np.count_nonzero(~in_range))
        if out_n:
            first = utc_text(int(t_ns[np.flatnonzero(~in_range)[0]]))
            warnings.append(
                f"{out_n} of {n} samples lie outside the passport's valid temperature range "
                f"{rng[0]:g} .. {rng[1]:g} C (the first at {first}); the model is extrapolated there"
            )
    table = pl.DataFrame(
        {
            "t_ns": pl.Series(t_ns, dtype=pl.Int64),
            "ax_g": a[:, 0],
            "ay_g": a[:, 1],
            "az_g": a[:, 2],
            "temp_c": temp_c,
            "in_range": pl.Series(in_range, dtype=pl.Boolean),
        }
    )
    return Applied(table=table, valid_temp_c=rng, warnings=warnings)


def write_applied(
    applied: Applied,
    path: str | Path,
    *,
    passport: Passport | dict | None = None,
    run: Run | None = None,
    verification=None,
) -> Path:
    """Write the compensated recording in the format of its suffix (:func:`output_format`): Parquet, MCAP (one JSON
    channel ``apply`` of row blocks) or CSV (a header row, then one line a row), with the passport used and how it
    was verified (``verification``: :class:`pipeline.passport.verification.Verification`) in the file's metadata
    (Parquet key-value metadata, the MCAP ``thermocal.apply`` record, the CSV's leading ``# thermocal.KEY: VALUE``
    lines). The file is written beside and renamed into place, so a failure leaves no partial file."""
    path = Path(path)
    fmt = output_format(path)
    tmp = path.with_name(f".{path.name}.partial")
    passport = load_passport(passport) if passport is not None else None
    meta = {
        "passport_unit": str(passport.unit or "") if passport is not None else "",
        "passport_version": str(passport.version if passport.version is not None else "")
        if passport is not None
        else "",
        "run_id": run.meta.run_id if run is not None else "",
        "valid_temp_c": ""
        if applied.valid_temp_c is None
        else f"{applied.valid_temp_c[0]:g},{applied.valid_temp_c[1]:g}",
        "passport_verification": verification.label if verification is not None else "not checked",
    }
    try:
        if fmt == "mcap":
            _write_mcap(applied.table, tmp, meta)
        elif fmt == "csv":
            with open(tmp, "w", encoding="utf-8", newline="") as f:
                # one line a key whatever the run's metadata holds (a run_id with a newline wrote a line of its own,
                # outside the comments: a CSV of other columns)
                f.writelines(f"# thermocal.{k}: {printable(v, lines=False)}\n" for k, v in meta.items())
                applied.table.write_csv(f)
        else:
            applied.table.write_parquet(tmp, metadata={f"thermocal.{k}": v for k, v in meta.items()})
        tmp.replace(path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise ThermocalError(f"cannot write the output ({e.strerror or e})", path=str(path)) from None
    return path


def _write_mcap(table: pl.DataFrame, path: Path, meta: dict[str, str], block_rows: int = 1000) -> None:
    """MCAP: a ``thermocal.apply`` metadata record and one JSON message per block of rows (columns as lists)."""
    import json

    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="thermocal")
        try:
            w.add_metadata("thermocal.apply", meta)
            schema = w.register_schema(
                "thermocal.apply_block",
                "jsonschema",
                json.dumps({"type": "object", "properties": {c: {"type": "array"} for c in APPLY_COLUMNS}}).encode(),
            )
            ch = w.register_channel("apply", "json", schema)
            t = table["t_ns"].to_numpy()
            for s0 in range(0, table.height, block_rows):
                block = table.slice(s0, block_rows)
                body = {
                    c: [None if isinstance(v, float) and not np.isfinite(v) else v for v in block[c].to_list()]
                    for c in APPLY_COLUMNS
                }
                stamp = int(t[s0])
                w.add_message(ch, log_time=stamp, publish_time=stamp, data=json.dumps(body).encode())
        finally:
            w.finish()
