"""Seed 003's differential method on simulated temperature-cycle runs: do the temperature-rate terms matter?

Setup: a unit (seed 000's, and one random unit) held in each of the six TP orientations (fixture face errors
1.5 deg per rotation component) while the chamber cycles +20 -> -40 -> +70 -> +20 C at 1 C/min with 30 min soaks
(``program.differential_program``), voltmeter 10 Hz with 5 uV noise, thermosensor 0.01 C; the sensing element
lags the thermosensor by tau (``thermal_lag``). The normal-temperature constants come from a tilt calibration
(six-position, short program) of the same unit. Each model is fitted on one run and judged on another (other noise,
other face errors).

Printed: the paper's figure of merit, the standard deviation over the full cycle of the 10 s means of the
compensated output (max and median over 6 orientations x 3 axes, micro-g; the paper: 10 ug level), for
- ``uncomp``: normal-temperature constants only;
- ``static``: polynomial order 3 in dT for bias, scale and cross-axis terms, no rate terms;
- ``paper``: plus the paper's rate terms r^n, n = 1, 2;
- ``rate*dT``: plus r^n dT (the lag's first-order expansion with a curved bias);
- ``lag``: polynomials at the element temperature, tau fitted;
and the recovered coefficients against the truth over -40..+70 C: max |U0 error| (uV) and max |K error| / 0.55.

Run: ``.venv/bin/python benchmarks/differential_rate_terms.py`` (about a minute).
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.calibrate.differential_fit import (
    DifferentialModel,
    DifferentialSettings,
    block_data,
    compensate_blocks,
    fit_differential,
    window_std_g,
)
from pipeline.calibrate.tilt import fit_unit, observe_run
from pipeline.positions import TEST_POSITIONS
from pipeline.simulate import program
from pipeline.simulate.chamber import SimConfig, simulate, unit_for
from pipeline.thermal import PolynomialModel

T0 = 20.0
PROGRAM = "differential_six"
MODELS = {
    "static": DifferentialSettings(rate_order=0),
    "paper": DifferentialSettings(),
    "rate*dT": DifferentialSettings(rate_dt_order=1),
    "lag": DifferentialSettings(rate_order=0, lag_fit=True),
}


def base_constants(unit_seed):
    """K0, U0 at T0 from a tilt calibration (short program) of the unit."""
    run = simulate(SimConfig(program="short", seed=8, unit_seed=unit_seed)).run
    model = fit_unit("unit", observe_run(run)[0]).model
    return np.asarray(model.K0), np.asarray(model.U00)


def cycle_run(seed, face_seed, tau_s, unit_seed):
    effects = [("fixture_face_error", {"sigma_deg": 1.5, "seed": face_seed})]
    if tau_s > 0:
        effects.append(("thermal_lag", {"tau_s": tau_s}))
    return simulate(SimConfig(program=PROGRAM, seed=seed, unit_seed=unit_seed, rate_hz=10.0, effects=effects)).run


def main() -> None:
    t_start = time.perf_counter()
    program.PROGRAMS[PROGRAM] = lambda: program.differential_program(tuple(TEST_POSITIONS))
    temps = np.linspace(-40.0, 70.0, 111)
    print("10 s standard deviation over the full cycle, held-out run: max / median over orientations and axes, ug")
    print(f"{'unit':>9} {'tau s':>6} | {'uncomp':>13} | " + " | ".join(f"{m:>13}" for m in MODELS) + " | fitted tau s")
    coef_rows = []
    for unit_seed, taus in ((None, (0.0, 60.0, 120.0, 300.0)), (3, (120.0,))):
        K0, U0 = base_constants(unit_seed)
        truth = unit_for(SimConfig(unit_seed=unit_seed))
        Kt, Ut = truth.constants_at(temps)
        label = "seed000" if unit_seed is None else f"random:{unit_seed}"
        for tau in taus:
            fit_d = block_data(cycle_run(2, 4, tau, unit_seed), K0, U0)
            held = block_data(cycle_run(3, 5, tau, unit_seed), K0, U0)
            none = DifferentialModel(PolynomialModel(K0, U0, T0, 0, np.zeros((0, 3)), np.zeros((0, 3, 3))))
            cells = []
            for model in [none] + [fit_differential([fit_d], K0, U0, T0, st).model for st in MODELS.values()]:
                s = window_std_g(held, compensate_blocks(model, held)) * 1e6
                cells.append(f"{s.max():6.1f} /{np.median(s):5.1f}")
                Kf, Uf = model.constants_at(temps)
                coef_rows.append(
                    (label, tau, len(cells) - 1, np.abs(Uf - Ut).max() * 1e6, np.abs(Kf - Kt).max() / 0.55)
                )
            print(f"{label:>9} {tau:6.0f} | " + " | ".join(f"{c:>13}" for c in cells) + f" | {model.lag_tau_s:6.1f}")
    print("\nrecovered constants against the truth over -40..+70 C: max |U0 err| uV, max |K err| / 0.55")
    names = ["uncomp"] + list(MODELS)
    print(f"{'unit':>9} {'tau s':>6} | " + " | ".join(f"{m:>16}" for m in names))
    for label, tau in dict.fromkeys((r[0], r[1]) for r in coef_rows):
        rows = [r for r in coef_rows if r[0] == label and r[1] == tau]
        print(f"{label:>9} {tau:6.0f} | " + " | ".join(f"{r[3]:7.1f} {r[4]:8.1e}" for r in rows))
    print(f"\n(took {time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
