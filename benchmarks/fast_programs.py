"""Fast programs against the standard program (issue 23): the same calibration in a fraction of the chamber time?

Setup: seed 000's unit, voltmeter 10 Hz with 5 uV noise, thermosensor 1 Hz with 0.01 C, the AU case 600 s behind
the chamber air in every program (the standard program's), seed 0. Programs:

- ``standard``: physics.md's standard program (soaks of 60/90 min, 300-s holds), calibrated by ``--method auto``
  (tilt);
- ``stepped``: issue 23's no-soak program ``20@0:TP; -40@0:TP; -10@0:VP; 20@0:TP+VP; 45@0:VP; 70@0:TP;
  20@0:TP+VP`` at 2 C/min with 120-s holds and 20-s moves, calibrated by ``--method auto`` (ramp);
- ``fast``: the fast program (positions TP1..TP6, VP1..VP6 cycled on ramps +20 -> +70 -> -40 -> +20 C at
  1.5 C/min with 30-min dwells at the ends, 240-s holds, 20-s moves), ``--method auto`` (ramp); and, with a lag,
  the same runs with the lag left to the up and down legs (``fast, legs``: neither lag nor hysteresis fitted, Niu
  et al.'s balanced average).

Cases: clean; the sensing element lagging the thermosensor by 120 s and 600 s (``thermal_lag``); hysteresis
(``thermal_hysteresis``, h = 50, -40, 30 uV). Printed per program and case: chamber hours, the method auto picked,
status, max and RMS |dg| at the VP holds after compensation (method 1, micro-g; means over ``--seeds`` noise
seeds, 3: at the noise floor the largest of 20-30 rows is itself a random number), and for seed 0: the constants
at T0 against the truth
(largest |error| of K in ppm of the row's gain and of U0 in micro-V, and the largest |error| / stated sigma), the
thermal model against the truth at -40 and +70 C (ppm of gain, micro-V), the lag found, and what ``diagnose``
finds on the run with the passport.

Run: ``.venv/bin/python benchmarks/fast_programs.py`` (about 10 min; ``--no-diagnose`` skips diagnose).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pipeline.calibrate import ramp
from pipeline.calibrate.methods import by_name, resolve_auto
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.passport.document import load_passport
from pipeline.simulate.chamber import SimConfig, simulate, unit_for
from pipeline.simulate.program import fast_program, parse_program, standard_program

ISSUE_PROGRAM = "20@0:TP; -40@0:TP; -10@0:VP; 20@0:TP+VP; 45@0:VP; 70@0:TP; 20@0:TP+VP"
CASES = {
    "clean": [],
    "lag 120 s": [("thermal_lag", {"tau_s": 120.0})],
    "lag 600 s": [("thermal_lag", {"tau_s": 600.0})],
    "hysteresis": [("thermal_hysteresis", {})],
}


def programs():
    return {
        "standard": standard_program(),
        "stepped": parse_program(ISSUE_PROGRAM, rate_c_per_min=2.0, hold_s=120.0, move_s=20.0),
        "fast": fast_program(),
    }


def figures(run, truth, settings: CalibrationSettings, legs_only: bool = False) -> dict:
    """Calibrate ``run`` (``--method auto``, or the ramp method without the lag fit) and compare with the truth."""
    method, _, seg, _ = resolve_auto(run, settings)
    if legs_only:
        method = "ramp"
        obs = ramp.observe(run, settings, segmentation=seg)
        res = ramp.calibrate_observed([obs], settings, ramp=ramp.RampSettings(lag_fit=False, hysteresis_fit=False))
    else:
        rec = by_name(method)
        res = rec.calibrate_observed([rec.observe(run, settings, segmentation=seg)], settings)
    doc = res.passport
    p = load_passport(doc)
    model = p.compensation_model()
    K_t, U0_t = truth.constants_at(np.array([20.0, -40.0, 70.0]))
    K_m, U0_m = model.constants_at(np.array([20.0, -40.0, 70.0]))
    gain = np.abs(np.diagonal(K_t, axis1=1, axis2=2))[:, :, None]
    dK_ppm = np.abs(K_m - K_t) / gain * 1e6
    dU_uv = np.abs(U0_m - U0_t) * 1e6
    unc = doc.get("uncertainty") or {}
    sK = np.array(unc["coefficients"]["K"], dtype=float)
    sU = np.array(unc["coefficients"]["U0"], dtype=float)
    z = max(np.nanmax(np.abs(K_m[0] - K_t[0]) / sK), np.nanmax(np.abs(U0_m[0] - U0_t[0]) / sU))
    rows = res.rows
    return {
        "method": method if not legs_only else "ramp (legs)",
        "status": res.status,
        "vp_rows": len(rows),
        "vp_max_ug": max(abs(r.dg_method1_g) for r in rows) * 1e6 if rows else float("nan"),
        "vp_rms_ug": float(np.sqrt(np.mean([r.dg_method1_g**2 for r in rows]))) * 1e6 if rows else float("nan"),
        "dK0_ppm": float(dK_ppm[0].max()),
        "dU0_uv": float(dU_uv[0].max()),
        "sK0_ppm": float(np.nanmax(sK / gain[0])) * 1e6,
        "sU0_uv": float(np.nanmax(sU)) * 1e6,
        "z": float(z),
        "dK_ends_ppm": float(dK_ppm[1:].max()),
        "dU_ends_uv": float(dU_uv[1:].max()),
        "tau_s": p.rate_terms.lag_tau_s if p.rate_terms is not None else 0.0,
        "valid": tuple(doc["valid_temp_c"]),
        "passport": doc,
    }


def diagnose_text(run, passport: dict) -> str:
    from pipeline.diagnose.diagnosis import diagnose_run

    rep = diagnose_run(run, passport).report
    if rep["verdict"] == "consistent":
        return "consistent"
    out = []
    for f in rep["findings"]:
        params = f.get("parameters") or {}
        if "tau_s" in params:
            out.append(f"{f['effect']} tau {params['tau_s']:.0f} s")
        elif "h_v" in params:
            out.append(f"{f['effect']} h " + "/".join(f"{x * 1e6:+.0f}" for x in params["h_v"]) + " uV")
        else:
            out.append(f["effect"])
    return ", ".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--no-diagnose", action="store_true")
    ap.add_argument("--seeds", type=int, default=3, help="noise seeds per row (the VP errors are their mean)")
    args = ap.parse_args()
    t_start = time.perf_counter()
    settings = CalibrationSettings()
    progs = programs()
    hours = {k: v.timetable().duration_s / 3600.0 for k, v in progs.items()}
    truth = unit_for(SimConfig())
    print(
        "| program | case | chamber h | method (auto) | status | VP max dg ug | VP rms dg ug | K0 err ppm (sigma) "
        "| U0 err uV (sigma) | max err/sigma | -40/+70 C: K ppm, U0 uV | lag s | valid C | diagnose |"
    )
    print("|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|")
    for case, effects in CASES.items():
        for name, prog in progs.items():
            runs = [simulate(SimConfig(program=prog, effects=effects, seed=s)).run for s in range(args.seeds)]
            legs = name == "fast" and case.startswith("lag")
            for label, legs_only in [(name, False)] + ([(f"{name}, legs", True)] if legs else []):
                per_seed = [figures(r, truth, settings, legs_only) for r in runs]
                f = per_seed[0]
                vp_max = np.mean([g["vp_max_ug"] for g in per_seed])
                vp_rms = np.mean([g["vp_rms_ug"] for g in per_seed])
                statuses = "/".join(sorted({g["status"] for g in per_seed}))
                diag = "-" if args.no_diagnose else diagnose_text(runs[0], f["passport"])
                print(
                    f"| {label} | {case} | {hours[name]:.2f} | {f['method']} | {statuses} | "
                    f"{vp_max:.2f} ({f['vp_rows']}) | {vp_rms:.2f} | {f['dK0_ppm']:.2f} ({f['sK0_ppm']:.2f}) | "
                    f"{f['dU0_uv']:.3f} ({f['sU0_uv']:.3f}) | {f['z']:.1f} | "
                    f"{f['dK_ends_ppm']:.1f}, {f['dU_ends_uv']:.2f} | {f['tau_s']:.1f} | "
                    f"{f['valid'][0]:+.1f}..{f['valid'][1]:+.1f} | {diag} |",
                    flush=True,
                )
    print(
        f"\nchamber hours: fast {hours['fast']:.2f} h = {hours['fast'] / hours['standard']:.2f} x standard "
        f"{hours['standard']:.2f} h; stepped {hours['stepped']:.2f} h = "
        f"{hours['stepped'] / hours['standard']:.2f} x; {time.perf_counter() - t_start:.0f} s"
    )


if __name__ == "__main__":
    main()
