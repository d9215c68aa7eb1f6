"""``fixture_face_error``: each tilt face has its own small angular error; the true specific force in position P is
R(delta_P) a_nominal, delta_P a small rotation vector per position.

Shows in the horizontal channels of single positions and in the VP errors, constant in temperature. It acts on the
specific force (``acts_on == "specific_force"``): the simulator builds its orientations from
:meth:`FixtureFaceError.rotation_vectors_rad`, so it does not add ``delta_u_v`` again; ``delta_u_v`` is
``K(T) (R_P a - a)`` on the static samples, for a context whose ``a_g`` is nominal. Its fit terms are two small
rotations per position present, perpendicular to the position's vector (a rotation about it changes nothing).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.effects.base import Effect, Shown, SignalContext, Vec3, finite
from pipeline.positions import ALL_POSITIONS, POSITION_NAMES

#: rotation used to linearise the face error, rad (far below any real face error)
_FACE_EPS_RAD = 1e-6
#: a face error beyond this is not a fixture's machining error, deg
_LIMIT_DEG = 1.0


def perpendicular_basis(a: np.ndarray) -> np.ndarray:
    """Two unit vectors (2, 3) perpendicular to ``a`` (rotations about ``a`` leave a position's vector alone)."""
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)
    _, _, vt = np.linalg.svd(a[None, :])
    return vt[1:]


@dataclass(frozen=True)
class FixtureFaceError(Effect):
    """Each tilt face has its own small angular error: in position P the true a is R(delta_P) a_nominal.

    ``delta_rad`` gives the rotation vectors per position explicitly (positions not named have none); when it is
    None they are drawn from N(0, sigma_deg) per component with ``seed``.
    """

    id: ClassVar[str] = "fixture_face_error"
    order: ClassVar[int] = 7
    acts_on: ClassVar[str] = "specific_force"
    where: ClassVar[str] = "horizontal channels of single positions, VP errors; constant in temperature"
    sigma_deg: float = 0.01
    seed: int = 1
    delta_rad: dict[str, Vec3] | None = None

    def rotation_vectors_rad(self) -> dict[str, np.ndarray]:
        """delta_P (3,) in rad for every position."""
        if self.delta_rad is not None:
            unknown = set(self.delta_rad) - set(ALL_POSITIONS)
            if unknown:
                raise ValueError(f"fixture_face_error: unknown positions {sorted(unknown)}")
            return {p: np.asarray(self.delta_rad.get(p, (0.0, 0.0, 0.0)), dtype=float) for p in POSITION_NAMES}
        draws = np.random.default_rng(self.seed).normal(0.0, np.radians(self.sigma_deg), (len(POSITION_NAMES), 3))
        return dict(zip(POSITION_NAMES, draws))

    def position_vectors_g(self) -> dict[str, np.ndarray]:
        """The true specific force (g) of every position, R(delta_P) a_nominal."""
        return {
            p: Rotation.from_rotvec(d).apply(np.asarray(ALL_POSITIONS[p], dtype=float))
            for p, d in self.rotation_vectors_rad().items()
        }

    def delta_u_v(self, ctx: SignalContext) -> np.ndarray:
        rot = self.rotation_vectors_rad()
        table = np.array([rot[p] for p in POSITION_NAMES] + [np.zeros(3)])  # last row: moving / unknown
        idx = np.where(np.asarray(ctx.position_idx) >= 0, ctx.position_idx, len(POSITION_NAMES))
        a = np.asarray(ctx.a_g, dtype=float)
        k, _ = ctx.k_u0
        return np.einsum("nij,nj->ni", k, Rotation.from_rotvec(table[idx]).apply(a) - a)

    def params(self) -> dict[str, Any]:
        out = super().params()
        out["delta_rad"] = {p: v.tolist() for p, v in self.rotation_vectors_rad().items()}
        return out

    def stored_params(self) -> dict[str, Any]:
        """The fitted rotations are the parameters, not the random draw."""
        return {"delta_rad": self.params()["delta_rad"]}

    def validate(self) -> None:
        super().validate()
        self.rotation_vectors_rad()

    @classmethod
    def _convert(cls, name, default, current, axis, raw):
        if name == "delta_rad":
            return None if raw is None else {str(p): tuple(finite(v) for v in d) for p, d in raw.items()}
        return super()._convert(name, default, current, axis, raw)

    # ---- fit terms
    @classmethod
    def fit_columns(cls, ctx, value):
        present = sorted(set(int(i) for i in np.unique(ctx.position_idx) if i >= 0))
        labels, cols = [], []
        for i in present:
            name = POSITION_NAMES[i]
            for k, b in enumerate(perpendicular_basis(np.asarray(ALL_POSITIONS[name]))):
                eff = cls.make({"delta_rad": {name: list(_FACE_EPS_RAD * b)}})
                labels.append(f"{name}:{k}")
                cols.append(eff.delta_u_v(ctx) / _FACE_EPS_RAD)
        return labels, cols

    @classmethod
    def fit_parameters(cls, coef: np.ndarray, value: float | None, labels: list[str]) -> dict[str, Any]:
        delta: dict[str, np.ndarray] = {}
        for c, lab in zip(coef, labels):
            name, k = lab.split(":")
            b = perpendicular_basis(np.asarray(ALL_POSITIONS[name]))[int(k)]
            delta[name] = delta.get(name, np.zeros(3)) + float(c) * b
        return {"delta_rad": {p: [float(x) for x in v] for p, v in sorted(delta.items())}}

    @classmethod
    def implausible(cls, p):
        worst = max((np.linalg.norm(v) for v in p["delta_rad"].values()), default=0.0)
        limit = np.radians(_LIMIT_DEG)
        return f"face error {np.degrees(worst):.3g} deg is beyond {_LIMIT_DEG:g} deg" if worst > limit else None

    @classmethod
    def explain(cls, p: dict[str, Any], shown: Shown) -> str:
        worst = max(p["delta_rad"].items(), key=lambda kv: np.linalg.norm(kv[1]))
        return (
            f"The tilt fixture's faces carry their own small angular errors, up to "
            f"{np.degrees(np.linalg.norm(worst[1])) * 3600:.0f} arcsec (in {worst[0]}): they move the "
            f"horizontal channels of single positions by up to {shown.amount(shown.peak)}, the same at every "
            "temperature."
        )
