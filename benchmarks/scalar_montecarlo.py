"""Monte-Carlo study of scalar calibration (seed 004, section 3), first-order solution against the nonlinear fit.

The paper's simulation: normalised outputs of a triad in random static orientations,

    B = D0 + (I + diag(D1) + M) a + noise,   |a| = 1,

calibrated by the first-order connection equation (eq. 11); "calibration error" is the relative error of the
estimated error coefficients D0_i, D1_i, psi_ij. Its conclusions (docs/physics.md): worthwhile for noise up to
1e-4 m/s^2 (1 sigma) -- about 10 % error there; offset and scale errors up to 1 % give errors up to 5 %;
misalignment terms of 0.005-0.01 degrade it to 10-20 %.

Reference unit: the paper's AK-6 values (Table 1 text): D0 = 2e-4 (all axes), D1 = (2e-4, 4e-4, 4e-4),
misalignments a_xz = 8e-4, a_xy = -2e-3, a_yz = -2e-4, a_yx = 2e-4, a_zy = 2e-4, a_zx = -2e-3 (the subscripts are
garbled in the text; this is our reading), entering B as in the paper's eq. 4. Program: 24 random orientations,
one averaged reading each, g = 9.81 m/s^2.

Printed per sweep point (median over the trials):
- ``paper``: max over the 9 coefficients of |estimate - truth| / |truth|, truth = the paper's D0, D1 and
  psi_xy = a_xz - a_yz, psi_xz = a_zy - a_xy, psi_yz = a_yx - a_zx (first-order definitions);
- ``ident``: the same against the identifiable truth: D0 and the lower-triangular K of the same K K^T (|a| data
  determine nothing else; D1 and psi differ from it in second order);
- ``p95``: the 95th percentile of ``ident`` over the trials (the paper's curves are RMS values; it notes that
  the maximum is about twice that);
- ``|dg| ug``: max gravity-module error |a_hat| - 1 over 200 fresh orientations, micro-g, noise-free readings.

Run: ``.venv/bin/python benchmarks/scalar_montecarlo.py`` (about half a minute).
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.calibrate.scalar import lower_gauge, scalar_first_order, scalar_nonlinear
from pipeline.model import gravity_module_error_g, specific_force_g
from pipeline.positions import ALL_POSITIONS

G_MPS2 = 9.81
M_POSITIONS = 24
AK6_D0 = np.array([2e-4, 2e-4, 2e-4])
AK6_D1 = np.array([2e-4, 4e-4, 4e-4])
AK6_MIS = {"xz": 8e-4, "xy": -2e-3, "yz": -2e-4, "yx": 2e-4, "zy": 2e-4, "zx": -2e-3}


def misalignment_matrix(mis: dict[str, float]) -> np.ndarray:
    """M of eq. 4: Bx += a_xz ay - a_xy az, By += -a_yz ax + a_yx az, Bz += a_zy ax - a_zx ay."""
    M = np.zeros((3, 3))
    M[0, 1], M[0, 2] = mis["xz"], -mis["xy"]
    M[1, 0], M[1, 2] = -mis["yz"], mis["yx"]
    M[2, 0], M[2, 1] = mis["zy"], -mis["zx"]
    return M


def random_directions(rng: np.random.Generator, m: int) -> np.ndarray:
    a = rng.normal(size=(m, 3))
    return a / np.linalg.norm(a, axis=1)[:, None]


def coefficients(d0, kn) -> np.ndarray:
    """The 9 coefficients (D0, D1, psi) of a normalised K (paper's first-order definitions)."""
    d1 = np.diag(kn) - 1.0
    psi = np.array([kn[0, 1] + kn[1, 0], kn[0, 2] + kn[2, 0], kn[1, 2] + kn[2, 1]])
    return np.concatenate([d0, d1, psi])


def one_trial(rng, d0, d1, M, noise_g, test_a, program):
    kn = np.eye(3) + np.diag(d1) + M
    a = random_directions(rng, M_POSITIONS) if program is None else program
    B = d0 + a @ kn.T + rng.normal(0.0, noise_g, a.shape)
    truth_paper = coefficients(d0, kn)
    truth_ident = coefficients(d0, lower_gauge(kn))
    out = {}
    for name, fn in (("first", scalar_first_order), ("nonlin", scalar_nonlinear)):
        f = fn(B, np.ones(3), np.zeros(3))
        est = np.concatenate([f.d0, f.d1, f.psi])  # lower gauge: psi below the diagonal, zeros above
        with np.errstate(divide="ignore", invalid="ignore"):
            rel_p = np.abs(est - truth_paper) / np.abs(truth_paper)
            rel_i = np.abs(est - truth_ident) / np.abs(truth_ident)
        dg = gravity_module_error_g(specific_force_g(f.K, f.U0, d0 + test_a @ kn.T))
        out[name] = (np.nanmax(rel_p[np.isfinite(rel_p)]), np.nanmax(rel_i[np.isfinite(rel_i)]), np.max(np.abs(dg)))
    return out


def sweep(label: str, points, make, trials: int, seed: int = 1, program: np.ndarray | None = None) -> None:
    """Median errors per value; ``program`` (m, 3) fixed orientations, None: M_POSITIONS random ones per trial."""
    rng = np.random.default_rng(seed)
    test_a = random_directions(rng, 200)
    print(f"\n{label}")
    print(
        f"{'value':>10} | {'first order: paper':>18} {'ident':>7} {'p95':>6} {'|dg| ug':>8} | "
        f"{'nonlinear: paper':>16} {'ident':>7} {'p95':>6} {'|dg| ug':>8}"
    )
    for v in points:
        d0, d1, M, noise_g = make(v)
        res = [one_trial(rng, d0, d1, M, noise_g, test_a, program) for _ in range(trials)]
        row = []
        for name in ("first", "nonlin"):
            arr = np.array([r[name] for r in res])
            med = np.median(arr, axis=0)
            p95 = np.percentile(arr[:, 1], 95)
            row.append(f"{med[0] * 100:17.1f}% {med[1] * 100:6.1f}% {p95 * 100:5.1f}% {med[2] * 1e6:8.2f}")
        print(f"{v:10.2g} | {row[0]} | {row[1]}")


def main() -> None:
    t = time.perf_counter()
    M_ak6 = misalignment_matrix(AK6_MIS)
    print("scalar calibration Monte Carlo: random orientations, medians over trials")
    noise = [1e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3]
    sweep(
        f"1) noise, m/s^2 (1 sigma per reading), AK-6 errors, {M_POSITIONS} positions",
        noise,
        lambda s: (AK6_D0, AK6_D1, M_ak6, s / G_MPS2),
        trials=300,
    )
    sweep(
        "1') the same with the 12 positions TP1..TP6 + VP1..VP6 (the standard program at +20 C)",
        noise,
        lambda s: (AK6_D0, AK6_D1, M_ak6, s / G_MPS2),
        trials=300,
        program=np.array(list(ALL_POSITIONS.values())),
    )
    sweep(
        "2) offset and scale errors D0_i = D1_i = value, AK-6 misalignments, no noise",
        [1e-4, 1e-3, 3e-3, 1e-2, 2e-2, 5e-2],
        lambda s: (np.full(3, s), np.full(3, s), M_ak6, 0.0),
        trials=40,
    )
    sweep(
        "3a) one misalignment a_xz = value (others AK-6), no noise",
        [1e-3, 2.5e-3, 5e-3, 1e-2, 2e-2],
        lambda s: (AK6_D0, AK6_D1, misalignment_matrix({**AK6_MIS, "xz": s}), 0.0),
        trials=40,
    )
    sweep(
        "3b) all six misalignments = +-value together (signs of AK-6), no noise",
        [1e-3, 2.5e-3, 5e-3, 1e-2, 2e-2],
        lambda s: (AK6_D0, AK6_D1, misalignment_matrix({k: s * np.sign(v) for k, v in AK6_MIS.items()}), 0.0),
        trials=40,
    )
    print(f"\n(took {time.perf_counter() - t:.1f} s)")


if __name__ == "__main__":
    main()
