"""Is there a thermal lag in the real CATS tag recording (tests/data/real/cats_tag)? Evidence from the data
alone, apart from ``diagnose`` (whose fine generic function of time absorbs what a lag would explain).

If the sensing element lagged the thermosensor by tau, the output would follow the temperature the element had
tau earlier: u = f(T - tau dT/dt) to first order, so on the fast cool-downs (up to ~25 C/h in 10-min means) and
warm-ups the 10-min means would form a loop against temperature (cooling and warming disagree at one temperature)
that one value of tau closes on every axis the temperature moves strongly (one element, one lag).

Per period of the authors (one orientation each) and axis: 10-min means of the output, of the temperature and of
its rate (the slope of the temperature within the bin, C/h). Model: u = cubic in (T - tau dT/dt) [+ a linear drift
in time], fitted on the even 2-hour blocks (as ``cats_tag.py`` splits them), judged by the standard deviation of
the held-out (odd) blocks' residual, for tau on a grid from -15 to +30 min (negative: the thermosensor lags the
element). Prints, per (period, axis), the best tau on the calibration blocks and the held-out figures at tau = 0
and at that tau, and for the axes the temperature moves most the tau that minimises their joint held-out residual.

Run: ``python benchmarks/cats_lag.py [RUN_DIR]`` (~3 s).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.io.runs import read_run

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
from cats_tag import DEFAULT_RUN, SPLIT_S, period_bounds_ns  # noqa: E402

MEAN_S = 600.0
#: axes whose 10-min means move by more than this over a period (mm/s^2) are the ones a lag would show on
STRONG_MM = 150.0
TAUS_S = np.arange(-900.0, 1801.0, 15.0)
_NS = 1_000_000_000


def bins(run_dir: Path) -> list[dict]:
    """Per period: 10-min means (full bins only) of time (s from the recording's start), temperature (C), its rate
    (C/h, slope within the bin), the outputs (m/s^2, (n, 3)), and whether the bin is a calibration (even) one."""
    run = read_run(run_dir)
    v = run.voltmeter.sort("t_ns")
    t_ns = v["t_ns"].to_numpy()
    temp = run.au_temperature.sort("t_ns")
    temp_c = np.interp(t_ns, temp["t_ns"].to_numpy(), temp["temp_c"].to_numpy())
    u = v.select(["ux", "uy", "uz"]).to_numpy()
    t_s = (t_ns - t_ns[0]) / _NS
    out = []
    for a, b in period_bounds_ns():
        m = (t_ns >= a) & (t_ns <= b)
        ts = t_s[m]
        df = pl.DataFrame(
            {
                "bin": ((ts - ts[0]) // MEAN_S).astype(np.int64),
                "t": ts,
                "T": temp_c[m],
                "ux": u[m, 0],
                "uy": u[m, 1],
                "uz": u[m, 2],
            }
        )
        g = (
            df.group_by("bin")
            .agg(
                pl.len().alias("n"),
                pl.col("t").mean(),
                pl.col("T").mean(),
                pl.col("ux").mean(),
                pl.col("uy").mean(),
                pl.col("uz").mean(),
                (pl.cov("t", "T") / pl.col("t").var()).alias("rate"),
            )
            .filter(pl.col("n") >= 0.9 * MEAN_S)
            .sort("bin")
        )
        tb = g["t"].to_numpy()
        out.append(
            {
                "t_s": tb,
                "temp_c": g["T"].to_numpy(),
                "rate_c_per_h": g["rate"].to_numpy() * 3600.0,
                "u": g.select(["ux", "uy", "uz"]).to_numpy(),
                "even": (tb // SPLIT_S) % 2 == 0,
            }
        )
    return out


def heldout_mm(p: dict, axis: int, tau_s: float, drift: bool) -> tuple[float, float]:
    """Std (mm/s^2) of the residual of the cubic in T - tau dT/dt (+ drift) fitted on the even bins: on the
    held-out (odd) bins, and on the calibration bins."""
    te = p["temp_c"] - tau_s * p["rate_c_per_h"] / 3600.0
    x = (te - te.mean()) / 10.0
    cols = [x**k for k in range(4)] + ([p["t_s"] / 86400.0] if drift else [])
    a = np.stack(cols, axis=1)
    y = p["u"][:, axis]
    c, *_ = np.linalg.lstsq(a[p["even"]], y[p["even"]], rcond=None)
    r = y - a @ c
    return float(np.std(r[~p["even"]]) * 1e3), float(np.std(r[p["even"]]) * 1e3)


def analyse(run_dir: Path = DEFAULT_RUN) -> dict:
    """Rows per (period, axis) and the joint profile over the strongly moving axes, with and without drift."""
    periods = bins(run_dir)
    rows, strong = [], []
    for k, p in enumerate(periods):
        for i in range(3):
            span = float(np.ptp(p["u"][:, i]) * 1e3)
            row = {
                "period": k,
                "axis": "xyz"[i],
                "span_mm": span,
                "max_rate_c_per_h": float(np.abs(p["rate_c_per_h"]).max()),
            }
            for drift in (False, True):
                prof = np.array([heldout_mm(p, i, tau, drift) for tau in TAUS_S])
                best = int(np.argmin(prof[:, 1]))  # chosen on the calibration bins
                key = "drift" if drift else "plain"
                row[key] = {
                    "heldout_tau0_mm": float(prof[TAUS_S == 0.0, 0][0]),
                    "best_tau_s": float(TAUS_S[best]),
                    "heldout_best_mm": float(prof[best, 0]),
                    "profile_heldout": prof[:, 0],
                }
            rows.append(row)
            if span > STRONG_MM:
                strong.append(row)
    joint = {}
    for key in ("plain", "drift"):
        ss = np.sum([r[key]["profile_heldout"] ** 2 for r in strong], axis=0)
        j = int(np.argmin(ss))
        joint[key] = {
            "tau_s": float(TAUS_S[j]),
            "rms_heldout_mm": float(np.sqrt(ss[j] / len(strong))),
            "rms_heldout_tau0_mm": float(np.sqrt(ss[TAUS_S == 0.0][0] / len(strong))),
            "rms_heldout_60s_mm": float(np.sqrt(ss[TAUS_S == 60.0][0] / len(strong))),
            "rms_heldout_300s_mm": float(np.sqrt(ss[TAUS_S == 300.0][0] / len(strong))),
        }
    return {"rows": rows, "strong": [(r["period"], r["axis"]) for r in strong], "joint": joint}


def main(argv: list[str]) -> None:
    res = analyse(Path(argv[0]) if argv else DEFAULT_RUN)
    print(
        "| period | axis | span of 10-min means (mm/s^2) | max rate (C/h) | held-out, tau 0 | best tau on cal. (s) "
        "| held-out there | + drift: tau 0 | + drift: best tau (s) | held-out there |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in res["rows"]:
        p, d = r["plain"], r["drift"]
        print(
            f"| {r['period']} | {r['axis']} | {r['span_mm']:.0f} | {r['max_rate_c_per_h']:.1f} | "
            f"{p['heldout_tau0_mm']:.2f} | {p['best_tau_s']:+.0f} | {p['heldout_best_mm']:.2f} | "
            f"{d['heldout_tau0_mm']:.2f} | {d['best_tau_s']:+.0f} | {d['heldout_best_mm']:.2f} |"
        )
    print(f"\nAxes moving by more than {STRONG_MM:.0f} mm/s^2: {res['strong']}")
    for key, j in res["joint"].items():
        print(
            f"joint ({key}): best tau {j['tau_s']:+.0f} s, held-out RMS {j['rms_heldout_mm']:.2f} mm/s^2 "
            f"(tau 0: {j['rms_heldout_tau0_mm']:.2f}, 60 s: {j['rms_heldout_60s_mm']:.2f}, "
            f"300 s: {j['rms_heldout_300s_mm']:.2f})"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
