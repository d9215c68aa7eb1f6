"""``thermocal diagnose`` on the 1 kHz standard run (about 59 M samples), next to the 10 Hz run of the same layout.

    .venv/bin/python benchmarks/diagnose_1khz.py [--layouts parquet,mcap-protobuf] [--rates 10,1000]
                                                 [--effect time_drift] [--seed 5] [--no-effect] [--out benchmarks/out]

Each measurement is one fresh Python process (so that ``ru_maxrss`` is that diagnosis's peak), run under
``flock`` on :data:`LOCK` (other jobs measuring on the same machine wait their turn). The process reads the run
(``read_run``), diagnoses it (``diagnose_run``: segmentation, passport fitted from the run, the static record, the
fits) and draws the PNG, as the command does; the main steps inside are timed by wrapping them, with the peak RSS
reached by the end of each ("fits": the rest of ``diagnose_run``, on the blocks).

Runs: the clean standard runs of :mod:`make_runs` (``std_{rate}hz_*``, made if missing), and (unless
``--no-effect``) a run with one concealed effect at 1 kHz and at 10 Hz, same seed and effect, made by
:func:`pipeline.simulate.large.simulate_chunked` (Parquet, in ``benchmarks/out/``; under a minute at 1 kHz here). The
findings of each rate must be the same.

Prints a markdown table: wall and CPU seconds, peak RSS against the decoded samples (8 bytes per number of every
stream), the verdict and the findings, with the machine's 1-minute load average around each measurement.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from make_runs import LAYOUTS, OUT, make_runs  # noqa: E402

#: measurements wait for this lock (other benchmark jobs on the machine take it too); THERMOCAL_BENCH_LOCK moves it
LOCK = Path(os.environ.get("THERMOCAL_BENCH_LOCK", Path(tempfile.gettempdir()) / "thermocal-bench.lock"))
#: the concealed effects' sizes (a fifth of the catalogue defaults, as in tests/test_diagnose_concealed.py); only
#: effects that act sample by sample (simulate_chunked refuses the others)
EFFECTS = {
    "time_drift": {"r_v_per_h": [0.6e-6, -0.4e-6, 0.8e-6]},
    "thermal_hysteresis": {"h_v": [10e-6, -8e-6, 6e-6]},
    "warmup_transient": {"a_v": [60e-6, -40e-6, 30e-6], "tau_s": 900.0},
    "scale_nonlinearity": {"k2_v_per_g2": [6e-6, -4e-6, 5e-6]},
    "fixture_face_error": {"sigma_deg": 0.002, "seed": 3},
    "temperature_curvature": {"c_v_per_c3": [0.3e-9, -0.2e-9, 0.2e-9], "c_rel_per_c3": [0.2e-9, 0.3e-9, -0.2e-9]},
}


# --- the measured process ---------------------------------------------------------------------------------------


def child(path: Path) -> None:
    """Read and diagnose ``path`` in this (fresh) process; print the figures as one JSON line."""
    import pipeline.diagnose.diagnosis as diagnose
    from pipeline.diagnose.plot import plot_residuals
    from pipeline.io.runs import read_run

    stages: dict[str, list[float]] = {}

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            t = time.perf_counter()
            out = fn(*args, **kwargs)
            wall, rss = time.perf_counter() - t, _peak_gb()
            prev = stages.get(name, [0.0, 0.0])
            stages[name] = [round(prev[0] + wall, 2), round(rss, 2)]
            return out

        return wrapper

    for name in ("segment_settings_for", "segment_run", "fit_passport", "static_record"):
        setattr(diagnose, name, timed(name, getattr(diagnose, name)))
    load0 = os.getloadavg()[0]
    wall0, usage0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    run = timed("read_run", read_run)(path)
    numbers = sum(df.height * sum(1 for c in df.columns if c != "position") for df in run.streams().values())
    samples = run.voltmeter.height
    result = timed("diagnose_run", diagnose.diagnose_run)(run)
    with tempfile.TemporaryDirectory() as tmp:
        timed("plot", plot_residuals)(
            Path(tmp) / "r.png",
            result.t_h,
            result.before_v,
            result.after_v,
            result.sigma_v,
            result.windows_h,
            result.located_h,
            title="benchmark",
        )
    usage1 = resource.getrusage(resource.RUSAGE_SELF)
    rep = result.report
    print(
        json.dumps(
            {
                "samples": samples,
                "numbers": numbers,
                "wall_s": round(time.perf_counter() - wall0, 2),
                "cpu_s": round(usage1.ru_utime + usage1.ru_stime - usage0.ru_utime - usage0.ru_stime, 2),
                "peak_gb": round(_peak_gb(), 3),
                "load_start": round(load0, 1),
                "stages": stages,
                "verdict": rep["verdict"],
                "findings": [
                    f["effect"] + (f"(~{'/'.join(f['confounded_with'])})" if f.get("confounded_with") else "")
                    for f in rep["findings"]
                ],
                "parameters": {f["effect"]: _rounded(f["parameters"]) for f in rep["findings"]},
                "noise_v": rep["noise_v"]["per_sample"],
                "blocks": rep["blocks"],
                "rms_after_v": rep["rms_after_v"],
            }
        )
    )


def _rounded(value):
    """A finding's parameters with 3 significant digits (for the printout)."""
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(v) for v in value]
    return float(f"{value:.3g}") if isinstance(value, float) else value


def _peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


# --- the driver -------------------------------------------------------------------------------------------------


def measure(path: Path) -> dict:
    """One fresh process diagnosing ``path``, under the benchmark lock; the load average before and after."""
    LOCK.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1")
    cmd = ["flock", str(LOCK), sys.executable, __file__, "--child", str(path)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = proc.communicate()
    if proc.returncode:
        raise SystemExit(f"diagnose {path} failed:\n{err[-3000:]}")
    res = json.loads(out.strip().splitlines()[-1])
    res["load_end"] = round(os.getloadavg()[0], 1)
    return res


def effect_runs(effect: str, seed: int, rates: list[int], out: Path) -> dict[int, Path]:
    """The standard run with ``effect`` (size of :data:`EFFECTS`) at each rate, written as Parquet if missing
    (simulated in chunks, under the benchmark lock: a few minutes of two cores at 1 kHz)."""
    paths = {}
    for rate in rates:
        path = out / f"eff_{effect}_s{seed}_{rate}hz_parquet"
        if not path.exists():
            code = (
                "import sys; from pipeline.simulate.chamber import SimConfig; "
                "from pipeline.simulate.large import simulate_chunked; from pipeline.io.runs import write_run; "
                f"res = simulate_chunked(SimConfig(rate_hz={float(rate)}, seed={seed}, "
                f"effects=[({effect!r}, {EFFECTS[effect]!r})])); write_run(res.run, sys.argv[1], 'parquet')"
            )
            t = time.perf_counter()
            subprocess.run(["flock", str(LOCK), sys.executable, "-c", code, str(path)], check=True)
            print(f"made {path} in {time.perf_counter() - t:.0f} s", file=sys.stderr)
        paths[rate] = path
    return paths


def row(name: str, rate: int, r: dict) -> str:
    decoded = r["peak_gb"] * 2**30 / (8 * r["numbers"])
    st = dict(r["stages"])
    total = st.pop("diagnose_run")
    inner = ("segment_settings_for", "segment_run", "fit_passport", "static_record")
    st = {
        **{k: v for k, v in st.items() if k != "plot"},
        "fits": [total[0] - sum(st[k][0] for k in inner if k in st), total[1]],
        "plot": st["plot"],
    }
    stages = ", ".join(
        f"{k.replace('_run', '').replace('segment_settings_for', 'settings')} {v[0]:.1f} s/{v[1]:.2f} GB"
        for k, v in st.items()
    )
    return (
        f"| {name} | {rate} | {r['samples'] / 1e6:.2f} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
        f"{r['peak_gb']:.2f} | {decoded:.2f} | {r['load_start']}-{r['load_end']} | {r['verdict']}: "
        f"{', '.join(r['findings']) or '-'} | {stages} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--layouts", default="parquet,mcap-protobuf", help=f"of {', '.join(LAYOUTS)}")
    ap.add_argument("--rates", default="10,1000")
    ap.add_argument("--effect", default="time_drift", choices=sorted(EFFECTS))
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--no-effect", action="store_true", help="only the clean standard runs")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    if args.child:
        child(args.child)
        return
    rates = [int(r) for r in args.rates.split(",")]
    runs = []
    for rate in rates:
        paths = make_runs(rate, args.out)
        runs += [(layout, rate, paths[layout]) for layout in args.layouts.split(",")]
    if not args.no_effect:
        runs += [
            (f"parquet, {args.effect}, seed {args.seed}", rate, path)
            for rate, path in effect_runs(args.effect, args.seed, rates, args.out).items()
        ]
    fitted = []
    lines = [
        "| run | Hz | M samples | wall s | CPU s | peak RSS GB | peak / decoded | load | verdict: findings "
        "| stages: wall / peak RSS by its end |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for name, rate, path in sorted(runs, key=lambda r: (r[0], r[1])):
        res = measure(path)
        print(f"  {name} {rate} Hz: {res}", file=sys.stderr, flush=True)
        lines.append(row(name, rate, res))
        fitted += [f"- {name}, {rate} Hz: {effect} {params}" for effect, params in res["parameters"].items()]
    print(
        f"\n{os.cpu_count()} CPUs; each row one fresh process under {LOCK}; load = 1-min load average at its "
        "start and end\n"
    )
    print("\n".join(lines))
    if fitted:
        print("\nFitted parameters of the findings:\n\n" + "\n".join(fitted))


if __name__ == "__main__":
    main()
