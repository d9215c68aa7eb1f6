"""The effect catalogue by id: every :class:`~pipeline.effects.base.Effect` defined in a module of this package, in
the order of docs/physics.md's table, and the CLI syntax ``ID[:k=v,...]``.

Effects outside the catalogue (disturbances the simulator can add to test that ``diagnose`` does not force a
catalogue name onto them) live in :mod:`pipeline.simulate.disturbances`, not here.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path
from typing import Any

from pipeline.effects.base import Effect

_NOT_EFFECTS = ("base", "catalogue", "model")


def _discover() -> dict[str, type[Effect]]:
    classes: list[type[Effect]] = []
    for info in pkgutil.iter_modules([str(Path(__file__).parent)]):
        if info.name in _NOT_EFFECTS:
            continue
        module = importlib.import_module(f"pipeline.effects.{info.name}")
        classes += [
            c
            for c in vars(module).values()
            if isinstance(c, type) and issubclass(c, Effect) and c.id and c.__module__ == module.__name__
        ]
    classes.sort(key=lambda c: (c.order, c.id))
    return {c.id: c for c in classes}


#: id -> effect class, in the catalogue's order
EFFECTS: dict[str, type[Effect]] = _discover()


def effect_class(effect_id: str) -> type[Effect]:
    """The class of catalogue effect ``effect_id`` (ValueError naming the ids when unknown)."""
    try:
        return EFFECTS[effect_id]
    except KeyError:
        raise ValueError(f"unknown effect {effect_id!r}; expected one of {', '.join(EFFECTS)}") from None


def make_effect(effect_id: str, params: dict[str, Any] | None = None) -> Effect:
    """The effect ``effect_id`` with ``params`` over its defaults (:meth:`Effect.make`)."""
    return effect_class(effect_id).make(params)


def parse_effect_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Parse the CLI syntax ``ID[:k=v,...]`` into (id, all parameters with defaults filled in).

    ``thermal_hysteresis:h_v=2e-5`` sets all three axes, ``thermal_hysteresis:h_v_y=2e-5`` only y.
    """
    effect_id, overrides = parse_spec(spec)
    effect = make_effect(effect_id, overrides)
    return effect.id, effect.params()


def parse_spec(spec: str) -> tuple[str, dict[str, float]]:
    """``ID[:k=v,...]`` as (id, the numbers given), without checking them against any catalogue."""
    text = spec.strip()
    effect_id, colon, rest = text.partition(":")
    effect_id = effect_id.strip()
    overrides: dict[str, float] = {}
    if rest.strip():
        for item in rest.split(","):
            key, eq, value = item.partition("=")
            if not eq or not key.strip() or not value.strip():
                raise ValueError(f"bad effect parameter {item.strip()!r} in {spec!r}: expected name=value")
            try:
                overrides[key.strip()] = float(value)
            except ValueError:
                raise ValueError(f"effect {effect_id!r}: {key.strip()!r} is not a number: {value.strip()!r}") from None
    elif colon:
        raise ValueError(f"effect spec {spec!r} has ':' but no parameters")
    return effect_id, overrides


__all__ = ["EFFECTS", "effect_class", "make_effect", "parse_effect_spec", "parse_spec"]
