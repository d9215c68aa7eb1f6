"""Transformations of a recording that remove nothing a calibration needs, and the comparison of what comes out
(issue 21: "same data, same passport"). Used by ``test_same_data_same_passport``.

A transformation takes a :class:`~pipeline.run.Run` and returns one run (or several, the pieces of a split) holding
the same information: a gap (rows removed from some streams over a time span), a stream read at another rate
(every k-th sample kept, or interpolated onto a faster grid), the chamber stream left out, all times shifted, rows
shuffled, the run cut into pieces given in any order, an exact duplicate of a file. Times are in seconds from the
recording's first voltmeter sample.

The pipeline is run as ``thermocal calibrate --method auto`` and ``thermocal diagnose`` run it, without the
registry and Prefect: :func:`calibrate_runs` (select the runs, join the files of one recording when the pipeline
does, choose the method, observe, fit) and :func:`diagnose_verdict`. :func:`same_passport` says how two passports
differ beyond their stated uncertainty.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl
from hypothesis import HealthCheck, Phase, settings

from pipeline.run import NS_PER_S, Run

STREAMS = ("voltmeter", "au_temperature", "chamber", "fixture")
#: the sampled streams (the fixture log is a list of events)
SAMPLED = ("voltmeter", "au_temperature", "chamber")
#: coefficients may differ by this many standard uncertainties (both passports' combined) before they differ
K_SIGMA = 4.0


#: a deeper local search (THERMOCAL_HYPOTHESIS_EXAMPLES=N): every property over every recording, N examples each
DEEP = "THERMOCAL_HYPOTHESIS_EXAMPLES" in os.environ


def property_settings(default_examples: int) -> settings:
    """The properties' hypothesis settings: ``THERMOCAL_HYPOTHESIS_EXAMPLES`` examples (else ``default_examples``),
    derandomized (CI sees the same examples every run), no example database, no shrinking (each example calibrates
    and diagnoses a recording: a failing one is reported as found), no deadline."""
    return settings(
        max_examples=int(os.environ.get("THERMOCAL_HYPOTHESIS_EXAMPLES", str(default_examples))),
        deadline=None,
        derandomize=True,
        database=None,
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=list(HealthCheck),
    )


def start_ns(run: Run) -> int:
    return int(run.voltmeter["t_ns"].min())


def duration_s(run: Run) -> float:
    t = run.voltmeter["t_ns"]
    return (int(t.max()) - int(t.min())) / NS_PER_S


def _frames(run: Run, fn, streams=STREAMS) -> Run:
    return dataclasses.replace(
        run, **{s: fn(s, getattr(run, s)) for s in streams if getattr(run, s) is not None}, warnings=list(run.warnings)
    )


def gap(run: Run, t0_s: float, t1_s: float, streams=STREAMS) -> Run:
    """``run`` without the rows of ``streams`` in [t0_s, t1_s] (a logger that recorded nothing then)."""
    lo, hi = start_ns(run) + int(t0_s * NS_PER_S), start_ns(run) + int(t1_s * NS_PER_S)
    return _frames(run, lambda _, df: df.filter((pl.col("t_ns") < lo) | (pl.col("t_ns") > hi)), streams)


def decimate(run: Run, stream: str, interval_s: float) -> Run:
    """``stream`` read every ``interval_s``: the first sample of each interval kept (a slower logger)."""

    def keep(_, df):
        t = df["t_ns"].to_numpy()
        k = (t - t[0]) // int(interval_s * NS_PER_S)
        return df.filter(pl.Series(np.concatenate(([True], np.diff(k) != 0))))

    return _frames(run, keep, (stream,))


def interpolate(run: Run, stream: str, rate_hz: float) -> Run:
    """``stream`` on a regular grid at ``rate_hz`` (faster than recorded), each column interpolated linearly."""

    def regrid(_, df):
        t = df["t_ns"].to_numpy()
        grid = np.arange(t[0], t[-1] + 1, int(round(NS_PER_S / rate_hz)), dtype=np.int64)
        cols = {"t_ns": grid}
        for c in df.columns[1:]:
            cols[c] = np.interp(grid.astype(np.float64), t.astype(np.float64), df[c].to_numpy())
        return pl.DataFrame(cols).cast(df.schema)

    return _frames(run, regrid, (stream,))


def without(run: Run, stream: str) -> Run:
    """``run`` without an optional stream (``chamber`` or ``fixture``)."""
    return dataclasses.replace(run, **{stream: None}, warnings=list(run.warnings))


def shift(run: Run, dt_s: float) -> Run:
    """Every time of ``run`` moved by ``dt_s`` (and ``started_utc`` with it: the metadata says when it began)."""
    dt = int(round(dt_s * NS_PER_S))
    moved = _frames(run, lambda _, df: df.with_columns(pl.col("t_ns") + dt))
    return moved


def write_shuffled(run: Run, path, seed: int):
    """``run`` written as a Parquet run directory at ``path`` whose stream files hold their rows in a random order
    (as another tool may write them: plain Parquet, no page checksums). Returns the path."""
    from pipeline.io.runs import write_run

    rng = np.random.default_rng(seed)
    write_run(run, path, "parquet")
    for f in sorted(Path(path).glob("*.parquet")):
        df = pl.read_parquet(f)
        df[rng.permutation(df.height)].write_parquet(f)
    return Path(path)


def split(run: Run, cuts_s, order=None) -> list[Run]:
    """``run`` cut into pieces at ``cuts_s`` (s from its start): each piece holds every stream's rows between two
    cuts and a run_id of its own (``<run_id>-p<k>``: the files of one recording). ``order``: the pieces' order
    (default as cut)."""
    t0 = start_ns(run)
    edges = [None, *sorted(t0 + int(c * NS_PER_S) for c in cuts_s), None]
    pieces = []
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        keep = pl.lit(True)
        if lo is not None:
            keep = keep & (pl.col("t_ns") >= lo)
        if hi is not None:
            keep = keep & (pl.col("t_ns") < hi)
        piece = _frames(run, lambda _, df, keep=keep: df.filter(keep))
        pieces.append(
            dataclasses.replace(piece, meta=dataclasses.replace(run.meta, run_id=f"{run.meta.run_id}-p{k + 1}"))
        )
    pieces = [p for p in pieces if p.voltmeter.height and p.au_temperature.height]
    return [pieces[i] for i in order] if order is not None else pieces


# ---------------------------------------------------------------------------------------------------------------
# the pipeline as the commands run it


def calibrate_runs(runs: list[Run], method: str = "auto", base_passport: dict | None = None):
    """What ``thermocal calibrate RUN... --method <method>`` computes (without writing it): the runs selected and,
    where the pipeline joins the files of one recording, joined; the method chosen on them; observed; fitted.
    Returns the :class:`~pipeline.calibrate.result.CalibrationResult` and the method used."""
    from pipeline.calibrate import inputs, methods
    from pipeline.calibrate.settings import CalibrationSettings

    settings = CalibrationSettings()
    runs, _ = inputs.select_runs(runs)
    join = getattr(inputs, "join_runs", None)
    if join is not None:
        runs = [join(runs)]
    seg = None
    if method == "auto":
        method, base_passport, seg, _ = methods.resolve_auto(runs[0], settings, base_passport)
    recipe = methods.by_name(method)
    observed = [
        recipe.observe(r, settings, base_passport=base_passport, segmentation=seg if k == 0 else None)
        for k, r in enumerate(runs)
    ]
    return recipe.calibrate_observed(observed, settings, base_passport=base_passport), method


def diagnose_verdict(runs: list[Run]) -> str:
    """``thermocal diagnose``'s verdict on the recording (its files joined as ``calibrate`` joins them), against
    the passport fitted from it."""
    from pipeline.calibrate import inputs
    from pipeline.diagnose.diagnosis import diagnose_run

    join = getattr(inputs, "join_runs", None)
    run = join(runs) if join is not None and len(runs) > 1 else runs[0]
    return diagnose_run(run).report["verdict"]


# ---------------------------------------------------------------------------------------------------------------
# comparison


@dataclass
class Difference:
    """One way two passports differ: what, the two values and the allowance."""

    what: str
    a: object
    b: object
    allowed: float | None = None

    def __str__(self) -> str:
        allowed = f" (allowed {self.allowed:.3g})" if self.allowed is not None else ""
        return f"{self.what}: {self.a} vs {self.b}{allowed}"


def _coefficients(p: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every fitted coefficient with its standard uncertainty, by name."""
    out = {}
    unc = p.get("uncertainty") or {}
    for name in ("K", "U0"):
        out[name] = (np.asarray(p["coefficients"][name], float), np.asarray(unc["coefficients"][name], float))
    tm, tu = p.get("thermal_model") or {}, unc.get("thermal_model") or {}
    for group in ("alpha", "beta", "gamma"):
        for key, v in (tm.get(group) or {}).items():
            out[f"{group}.{key}"] = (np.asarray(v, float), np.asarray(tu[group][key], float))
    return out


def same_passport(a: dict, b: dict, k_sigma: float = K_SIGMA) -> list[Difference]:
    """How passport ``b`` differs from ``a`` beyond what they state: method, status, thermal model kind and order,
    which constants are undetermined, and every coefficient with a stated uncertainty by more than ``k_sigma`` times
    the two stated standard uncertainties combined. Empty: the same passport."""
    out = []
    for key in ("method", "status", "output_unit"):
        if a.get(key) != b.get(key):
            out.append(Difference(key, a.get(key), b.get(key)))
    for key in ("kind", "order"):
        if a["thermal_model"].get(key) != b["thermal_model"].get(key):
            out.append(Difference(f"thermal_model.{key}", a["thermal_model"].get(key), b["thermal_model"].get(key)))
    ua, ub = (sorted((p.get("uncertainty") or {}).get("undetermined") or {}) for p in (a, b))
    if ua != ub:
        out.append(Difference("undetermined", ua, ub))
    if out:
        return out
    ca, cb = _coefficients(a), _coefficients(b)
    for name in sorted(set(ca) | set(cb)):
        if name not in ca or name not in cb:
            out.append(Difference(name, name in ca, name in cb))
            continue
        (va, sa), (vb, sb) = ca[name], cb[name]
        allowed = k_sigma * np.sqrt(sa**2 + sb**2) + 1e-12 * np.maximum(np.abs(va), np.abs(vb))
        # a value with no stated uncertainty (undetermined, kept nominal or given by one orientation alone: the
        # passport says so, and both must) is not compared
        bad = ~(np.abs(va - vb) <= allowed) & np.isfinite(allowed)
        for idx in zip(*np.nonzero(bad)):
            out.append(Difference(f"{name}{list(idx)}", float(va[idx]), float(vb[idx]), float(allowed[idx])))
    return out
