"""Plain JSON values from the library's results: one coercion for every JSON the project writes (passports and
registry records, ``--json`` output, ground truth, summaries). Dataclasses become objects, tuples lists, numpy
arrays and scalars Python numbers, paths strings."""

from __future__ import annotations

import dataclasses
from os import PathLike, fspath
from typing import Any

import numpy as np


def to_jsonable(value: Any) -> Any:
    """``value`` with every dataclass, dict key, tuple, numpy value and path made plain JSON (recursively)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    if isinstance(value, PathLike):
        return fspath(value)
    return value


def json_default(obj: Any) -> Any:
    """``default=`` for :func:`json.dumps`: what :func:`to_jsonable` makes of a value JSON cannot take as it is;
    TypeError for anything else."""
    plain = to_jsonable(obj)
    if plain is obj:
        raise TypeError(f"{type(obj).__name__} is not JSON serialisable")
    return plain
