"""What the segmentation costs per unit as the rate grows (issue 22: 16 units at 100 Hz segmented within the
decode floor's budget), side by side with what the hold means alone cost (the floor of any segmentation: every
sample read once).

    .venv/bin/python benchmarks/segmentation_rate.py [--rates 10,100] [--repeat 5]

For each rate: one unit of the standard program simulated (``pipeline.simulate.chamber``), then the best of
``--repeat`` process-time measurements (s) of

- ``segment_run`` (static stretches, plateaus, names, hold means, the creep fit of :mod:`pipeline.settling`, the
  thermosensor weights of each hold's temperature);
- the creep fit's moments of one 300-s hold (:func:`pipeline.settling.hold_moments`: its cost should grow far
  less than the rate, since it works on blocks of samples);
- the floor: every sample read once (``numpy.mean`` of each of the three channels).

Prints a markdown table: CPU s per unit, per million voltmeter samples, and ``segment_run`` over the floor.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def _best_cpu_s(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rates", default="10,100", help="voltmeter rates (Hz), comma-separated")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    from pipeline.segment import segment_run
    from pipeline.settling import hold_moments
    from pipeline.simulate.chamber import SimConfig, simulate

    print(f"1-min load {os.getloadavg()[0]:.1f}; process time (s), best of {args.repeat}\n")
    print(
        "| rate Hz | samples M | segment_run s | creep moments of one 300-s hold ms | floor: 3 column means s | "
        "segment_run / floor |"
    )
    print("|---:|---:|---:|---:|---:|---:|")
    for rate_hz in (float(r) for r in args.rates.split(",")):
        run = simulate(SimConfig(rate_hz=rate_hz)).run
        u = [run.voltmeter[c].to_numpy() for c in ("ux", "uy", "uz")]
        rng = np.random.default_rng(1)
        hold_t_s = np.arange(0.0, 300.0, 1.0 / rate_hz)  # one 300-s hold
        hold_u = rng.normal(0.0, 5e-6, (hold_t_s.size, 3))
        hold_temp_c = 20.0 + rng.normal(0.0, 0.002, hold_t_s.size)
        seg_s = _best_cpu_s(lambda run=run: segment_run(run), args.repeat)
        mom_s = _best_cpu_s(
            lambda t=hold_t_s, h=hold_u, c=hold_temp_c: hold_moments(t, [h[:, i] for i in range(3)], h.mean(0), c),
            args.repeat,
        )
        floor_s = _best_cpu_s(lambda u=u: [float(np.mean(c)) for c in u], args.repeat)
        print(
            f"| {rate_hz:g} | {u[0].size / 1e6:.2f} | {seg_s:.3f} | {mom_s * 1e3:.1f} | {floor_s:.3f} | "
            f"{seg_s / floor_s:.0f} |"
        )


if __name__ == "__main__":
    main()
