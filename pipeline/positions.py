"""Positions of the tilt fixture: specific force along the AU axes, in g (docs/physics.md)."""

from __future__ import annotations

import numpy as np

_S = 1.0 / np.sqrt(2.0)

#: Test positions TP1..TP6 (calibration): a = (ax, ay, az) in g.
TEST_POSITIONS: dict[str, tuple[float, float, float]] = {
    "TP1": (0.0, 0.0, 1.0),
    "TP2": (0.0, -1.0, 0.0),
    "TP3": (0.0, 0.0, -1.0),
    "TP4": (0.0, 1.0, 0.0),
    "TP5": (-1.0, 0.0, 0.0),
    "TP6": (1.0, 0.0, 0.0),
}

#: Verification positions VP1..VP6: a in g, |a| = 1.
VERIFICATION_POSITIONS: dict[str, tuple[float, float, float]] = {
    "VP1": (_S, 0.0, _S),
    "VP2": (0.0, _S, _S),
    "VP3": (_S, _S, 0.0),
    "VP4": (-_S, 0.0, _S),
    "VP5": (0.0, -_S, _S),
    "VP6": (_S, -_S, 0.0),
}

ALL_POSITIONS: dict[str, tuple[float, float, float]] = {**TEST_POSITIONS, **VERIFICATION_POSITIONS}
POSITION_NAMES: tuple[str, ...] = tuple(ALL_POSITIONS)
MOVING = "MOVING"
AXES = ("x", "y", "z")


def gravity_vector_g(position: str) -> np.ndarray:
    """Specific force along the AU axes in ``position`` (TP1..TP6, VP1..VP6), in g, shape (3,)."""
    try:
        return np.asarray(ALL_POSITIONS[position], dtype=float)
    except KeyError:
        raise ValueError(f"unknown position {position!r}") from None


def is_test_position(position: str) -> bool:
    return position in TEST_POSITIONS


def is_verification_position(position: str) -> bool:
    return position in VERIFICATION_POSITIONS


def nearest_position(direction_g: np.ndarray) -> tuple[str, float]:
    """The position whose nominal vector is closest in angle to ``direction_g`` (any length).

    Returns the name and the angle to it in degrees.
    """
    d = np.asarray(direction_g, dtype=float)
    d = d / np.linalg.norm(d)
    names = list(ALL_POSITIONS)
    vecs = np.array([ALL_POSITIONS[n] for n in names])
    cos = np.clip(vecs @ d, -1.0, 1.0)
    i = int(np.argmax(cos))
    return names[i], float(np.degrees(np.arccos(cos[i])))
