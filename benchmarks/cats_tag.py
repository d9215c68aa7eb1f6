"""The real CATS tag recording (tests/data/real/cats_tag): thermocal's sweep calibration against the peer tool's
method, on data neither was fitted on.

The recording: a MEMS logger at 1 Hz, three periods of about a day, one axis vertical (pointing down) in each,
the temperature drifting 5-28 C and never holding a plateau. Its authors' periods (README) delimit the
orientations.

Split: the recording is cut into 2-hour blocks from its first sample; even blocks are the calibration data, odd
blocks the held-out data. Every temperature of a period is seen on both sides, and nothing of a held-out block is
fitted: thermocal's calibration run is the recording with the held-out blocks deleted (their voltmeter and
thermosensor rows removed, so the run has a 2-hour gap after every block, one of them where the tag was turned);
the peer fits only the calibration rows. The compensation is applied to the whole recording.

Figure of merit: within each period and axis, the standard deviation of the 10-min means of the compensated output
over the held-out blocks (mm/s^2); the specific force is constant within a period, so whatever varies is what the
temperature model left. Compared, per axis and period:

- raw: the recorded signal;
- peer linear / peer piecewise: scikit-diveMove's ``IMUcalibrate.build_tmodels`` as its README describes it, written
  here: per period and axis, the Savitzky-Golay-smoothed signal (window 99 samples, order 2) regressed on the
  temperature, linearly or piecewise-linearly with one breakpoint (chosen by least squares), and the signal
  standardised to a reference temperature (y - f(T) + f(T_ref)). Nine separate models (three per period);
- thermocal: ``calibrate --method differential`` without a base passport (one model for the unit: per-axis bias and
  scale factor, and the cross-axis terms the orientations excite, as polynomials in temperature whose order, and
  whether the cross-axis and rate terms are fitted, are chosen by two-fold validation within the calibration blocks; the
  constants at T0 from the orientations), then ``apply`` (the passport's model at every sample), in g times
  g_local.

Run: ``python benchmarks/cats_tag.py [RUN_DIR]``; prints the table and the averages.
"""

from __future__ import annotations

import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import polars as pl
from scipy.signal import savgol_filter

SPLIT_S = 7200.0
MEAN_S = 600.0
SAVGOL = (99, 2)
PERIODS = [
    ("2021-09-20T09:00", "2021-09-21T10:33", "-z"),
    ("2021-09-21T10:40", "2021-09-22T11:55", "-x"),
    ("2021-09-22T12:14", "2021-09-23T11:19", "-y"),
]
DEFAULT_RUN = Path(__file__).resolve().parents[1] / "tests" / "data" / "real" / "cats_tag" / "run"
_NS = 1_000_000_000


def _ns(text: str) -> int:
    return int(datetime.fromisoformat(text).replace(tzinfo=UTC).timestamp()) * _NS


def period_bounds_ns() -> list[tuple[int, int]]:
    return [(_ns(a), _ns(b)) for a, b, _ in PERIODS]


def calibration_mask(t_ns: np.ndarray) -> np.ndarray:
    """True for the calibration samples (even 2-hour blocks from the first sample)."""
    return (((t_ns - t_ns[0]) / _NS) // SPLIT_S).astype(np.int64) % 2 == 0


def calibration_run(run, keep: np.ndarray):
    """The run with the held-out blocks deleted: the voltmeter rows not in ``keep`` and the thermosensor rows of the
    same 2-hour blocks removed (not set to NaN: the run has gaps where they were)."""
    from pipeline.run import Run

    t0 = int(run.voltmeter["t_ns"][0])
    temp_t = run.au_temperature["t_ns"].to_numpy()
    temp_keep = ((temp_t - t0) // int(SPLIT_S * _NS)) % 2 == 0
    return Run(
        meta=run.meta,
        voltmeter=run.voltmeter.filter(pl.Series(keep)),
        au_temperature=run.au_temperature.filter(pl.Series(temp_keep)),
        chamber=run.chamber,
        fixture=run.fixture,
        source=run.source,
    )


def ten_minute_spread(t_ns: np.ndarray, x: np.ndarray, held_out: np.ndarray) -> np.ndarray:
    """(periods, 3): within each period, the standard deviation of the 10-min means of ``x`` (n, 3) over the
    held-out samples (bins of 10 min from the period's start, kept when 90 % of their samples are held out and
    finite)."""
    out = np.zeros((len(PERIODS), 3))
    step = float(np.median(np.diff(t_ns))) / _NS
    for p, (a, b) in enumerate(period_bounds_ns()):
        sel = (t_ns >= a) & (t_ns < b) & held_out & np.isfinite(x).all(axis=1)
        bins = ((t_ns[sel] - a) / _NS // MEAN_S).astype(np.int64)
        xs = x[sel]
        ids, start, counts = np.unique(bins, return_index=True, return_counts=True)
        full = counts >= 0.9 * MEAN_S / step
        means = np.add.reduceat(xs, start, axis=0) / counts[:, None]
        out[p] = means[full].std(axis=0, ddof=1)
    return out


def _hinge_fit(temp: np.ndarray, y: np.ndarray):
    """Continuous piecewise-linear fit with one breakpoint (grid over the temperature's 10-90 % quantiles): the
    function T -> y."""
    best = None
    for tb in np.quantile(temp, np.linspace(0.1, 0.9, 33)):
        X = np.column_stack([np.ones_like(temp), temp, np.maximum(temp - tb, 0.0)])
        coef, res, *_ = np.linalg.lstsq(X, y, rcond=None)
        sse = float(np.sum((X @ coef - y) ** 2))
        if best is None or sse < best[0]:
            best = (sse, tb, coef)
    _, tb, coef = best
    return lambda T: coef[0] + coef[1] * T + coef[2] * np.maximum(T - tb, 0.0)


def peer_compensation(
    t_ns: np.ndarray,
    u: np.ndarray,
    temp_c: np.ndarray,
    fit_mask: np.ndarray,
    *,
    piecewise: bool,
    ref_temp_c: float = 20.0,
) -> np.ndarray:
    """The peer's per-period, per-axis standardisation (module doc), fitted on the ``fit_mask`` samples: (n, 3)
    with NaN outside the periods."""
    out = np.full_like(u, np.nan)
    for a, b in period_bounds_ns():
        inp = (t_ns >= a) & (t_ns < b)
        fit = inp & fit_mask
        idx = np.flatnonzero(fit)
        # Savitzky-Golay over each contiguous run of calibration samples
        cuts = np.flatnonzero(np.diff(idx) > 1) + 1
        smooth = np.empty((idx.size, 3))
        for part in np.split(np.arange(idx.size), cuts):
            seg = u[idx[part]]
            w = min(SAVGOL[0], part.size - (1 - part.size % 2))
            smooth[part] = savgol_filter(seg, w, SAVGOL[1], axis=0) if w > SAVGOL[1] else seg
        for c in range(3):
            if piecewise:
                f = _hinge_fit(temp_c[idx], smooth[:, c])
            else:
                coef = np.polyfit(temp_c[idx], smooth[:, c], 1)
                f = np.poly1d(coef)
            out[inp, c] = u[inp, c] - f(temp_c[inp]) + f(ref_temp_c)
    return out


def compare(run_dir: str | Path = DEFAULT_RUN) -> dict:
    """The table (mm/s^2): ``{"raw" | "peer_linear" | "peer_piecewise" | "thermocal": (periods, 3) array}``, the
    passport and the timings."""
    from pipeline.apply import apply_passport
    from pipeline.calibrate.differential import calibrate as calibrate_differential
    from pipeline.io.runs import read_run

    run = read_run(run_dir)
    t_ns = run.t_ns()
    u = run.u_v()
    temp = np.interp(
        t_ns.astype(float), run.au_temperature["t_ns"].to_numpy().astype(float), run.au_temperature["temp_c"].to_numpy()
    )
    cal = calibration_mask(t_ns)
    held = ~cal
    t = time.perf_counter()
    mc = calibrate_differential([calibration_run(run, cal)])
    cal_s = time.perf_counter() - t
    applied = apply_passport(mc.passport, run).table
    a_mps2 = applied.select("ax_g", "ay_g", "az_g").to_numpy() * run.meta.g_local_mps2
    table = {
        "raw": ten_minute_spread(t_ns, u, held),
        "peer_linear": ten_minute_spread(t_ns, peer_compensation(t_ns, u, temp, cal, piecewise=False), held),
        "peer_piecewise": ten_minute_spread(t_ns, peer_compensation(t_ns, u, temp, cal, piecewise=True), held),
        "thermocal": ten_minute_spread(t_ns, a_mps2, held),
    }
    return {
        "table": {k: v * 1e3 for k, v in table.items()},
        "passport": mc.passport,
        "warnings": list(mc.warnings),
        "calibrate_s": cal_s,
    }


def format_table(result: dict) -> str:
    tab = result["table"]
    head = (
        f"{'method':<16}"
        + "".join(f"{f'P{p + 1}({PERIODS[p][2]}) {ax}':>12}" for p in range(3) for ax in "xyz")
        + f"{'mean':>9}"
    )
    lines = ["CATS tag, held-out 2-h blocks: std of 10-min means within each period, mm/s^2", head]
    for k, v in tab.items():
        lines.append(f"{k:<16}" + "".join(f"{x:12.2f}" for x in v.ravel()) + f"{v.mean():9.2f}")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    run_dir = argv[1] if len(argv) > 1 else DEFAULT_RUN
    res = compare(run_dir)
    print(format_table(res))
    d = res["passport"]["differential"]
    print(
        f"thermocal: calibrate {res['calibrate_s']:.1f} s; terms x {d['terms']['x']}, y {d['terms']['y']}, "
        f"z {d['terms']['z']}; poly order {d['poly_order']}, rate order {d['rate_order']}; valid "
        f"{res['passport']['valid_temp_c']} C"
    )
    sel = d.get("model_selection")
    if sel:
        print(
            "model chosen by two-fold validation within the calibration blocks (score: mm/s^2): "
            + ", ".join(
                f"poly{c['poly_order']}{'+rate' + str(c['rate_order']) if c.get('rate_order') else ''}"
                f"{'+cross' if c['cross_axis'] else ''} {c['score_g'] * 9806.65:.2f}"
                for c in sel["candidates"]
            )
        )


if __name__ == "__main__":
    main(sys.argv)
