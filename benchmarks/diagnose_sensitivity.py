"""Sensitivity of ``thermocal diagnose``: per catalogue effect, the smallest size it still names correctly.

For each effect, the catalogue's default parameters (pipeline/effects/) are scaled by a factor s (for
``thermal_lag`` the time constant, for ``fixture_face_error`` the angular sigma, for the others every size
parameter; time constants of the other effects are kept). A size counts as named when, on every seed, diagnose's
first finding is that effect (or a confounded group holding it) and the fit improves. The factor is bisected in
log scale between a size that fails and one that passes. The run is the standard program (docs/physics.md) written to
MCAP and read back, 5 uV per-sample noise, the passport fitted from the run.

Prints a markdown table: the smallest named size, its parameters, the peak of the effect on static samples, and
that peak against the per-sample noise and the noise of a 30 s block mean.

    .venv/bin/python benchmarks/diagnose_sensitivity.py [--rate-hz 10] [--seeds 3] [--steps 6] [--effects ID,...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.diagnose.diagnosis import diagnose_run
from pipeline.effects.catalogue import EFFECTS, make_effect
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig, simulate


def scaled_params(effect_id: str, s: float) -> dict:
    """The effect's default parameters with its size scaled by ``s``."""
    d = make_effect(effect_id).params()
    if effect_id == "thermal_lag":
        return {"tau_s": d["tau_s"] * s}
    if effect_id == "fixture_face_error":
        return {"sigma_deg": d["sigma_deg"] * s, "seed": d["seed"]}
    keep = {"tau_s"}
    return {
        k: (np.asarray(v) * s).tolist() if k not in keep and isinstance(v, (list, float)) else v for k, v in d.items()
    }


#: how each parameter is shown: scale to the unit, unit
_SHOWN = {
    "tau_s": (1.0, "s"),
    "h_v": (1e6, "uV"),
    "r_v_per_h": (1e9, "nV/h"),
    "a_v": (1e6, "uV"),
    "c_v_per_c3": (1e12, "pV/C^3"),
    "c_rel_per_c3": (1e12, "1e-12/C^3"),
    "k2_v_per_g2": (1e6, "uV/g^2"),
    "f": (1e6, "ppm"),
}


def describe(effect_id: str, p: dict) -> str:
    if effect_id == "fixture_face_error":
        return f"sigma {p['sigma_deg'] * 3600:.2g} arcsec per axis"
    parts = []
    for k, v in p.items():
        if k not in _SHOWN:
            continue
        scale, unit = _SHOWN[k]
        if isinstance(v, list):
            parts.append(f"{k} ({', '.join(f'{x * scale:.2g}' for x in v)}) {unit}")
        else:
            parts.append(f"{k} {v * scale:.3g} {unit}")
    return ", ".join(parts)


def named(effect_id: str, s: float, seeds: list[int], rate_hz: float, tmp: Path) -> tuple[bool, float, float]:
    """Whether every seed's diagnosis names the effect first; the peak effect (V) on static samples; time (s)."""
    ok, peak, t_total = True, 0.0, 0.0
    for seed in seeds:
        res = simulate(SimConfig(seed=seed, rate_hz=rate_hz, effects=[(effect_id, scaled_params(effect_id, s))]))
        ctx = res.context
        static = ctx.position_idx >= 0
        peak = max(
            peak, float(np.abs(make_effect(effect_id, scaled_params(effect_id, s)).delta_u_v(ctx)[static]).max())
        )
        path = write_run(res.run, tmp / f"{effect_id}-{seed}.mcap", "mcap")
        t0 = time.process_time()
        rep = diagnose_run(read_run(path)).report
        t_total += time.process_time() - t0
        f = rep["findings"]
        first = [f[0]["effect"]] + f[0].get("confounded_with", []) if f else []
        if effect_id not in first or not rep["rms_after_v"] < rep["rms_before_v"]:
            ok = False
            break
    return ok, peak, t_total


def smallest(effect_id: str, seeds: list[int], rate_hz: float, steps: int, tmp: Path) -> dict:
    """Bisect the scale factor (log scale) for the smallest size named on every seed."""
    hi, lo = 1.0, None
    ok, peak_hi, _ = named(effect_id, hi, seeds, rate_hz, tmp)
    while not ok and hi < 64:
        hi *= 4
        ok, peak_hi, _ = named(effect_id, hi, seeds, rate_hz, tmp)
    s = hi
    while lo is None:
        s /= 4
        ok, peak, _ = named(effect_id, s, seeds, rate_hz, tmp)
        if ok:
            hi, peak_hi = s, peak
        else:
            lo = s
        if s < 1e-4:
            break
    for _ in range(steps if lo is not None else 0):
        mid = float(np.sqrt(lo * hi))
        ok, peak, _ = named(effect_id, mid, seeds, rate_hz, tmp)
        if ok:
            hi, peak_hi = mid, peak
        else:
            lo = mid
    return {"effect": effect_id, "scale": hi, "params": scaled_params(effect_id, hi), "peak_v": peak_hi}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate-hz", type=float, default=10.0)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--effects", default=",".join(EFFECTS))
    args = ap.parse_args(argv)
    seeds = list(range(args.seeds))
    noise_v = 5e-6
    block_v = noise_v / np.sqrt(30 * args.rate_hz)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for effect_id in args.effects.split(","):
            t0 = time.time()
            r = smallest(effect_id, seeds, args.rate_hz, args.steps, Path(d))
            print(f"{effect_id}: scale {r['scale']:.3g} ({time.time() - t0:.0f} s)", file=sys.stderr, flush=True)
            rows.append(r)
    print(
        f"Standard program, {args.rate_hz:g} Hz, 5 uV per-sample noise, seeds {seeds}; smallest size named first "
        f"on every seed (x default of pipeline/effects/):\n"
    )
    print("| effect | smallest size named | x default | peak effect (uV) | / sample noise | / 30 s block noise |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| `{r['effect']}` | {describe(r['effect'], r['params'])} | {r['scale']:.3g} | "
            f"{r['peak_v'] * 1e6:.2f} | {r['peak_v'] / noise_v:.2f} | {r['peak_v'] / block_v:.1f} |"
        )


if __name__ == "__main__":
    main()
