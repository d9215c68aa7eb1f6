"""The calibration methods by name: one recipe module per method, each with the same interface.

A recipe module (``tilt``, ``scalar``, ``differential``) has ``METHOD`` (the passport's ``method``),
``observe(run, settings, *, base_passport=None, segmentation=None) -> ObservedRun`` (the per-run step: what a
fleet isolates; ``segmentation``: the run's, when already made, e.g. by :func:`auto_method`'s caller),
``calibrate_observed(observed, settings, *, base_passport=None) -> CalibrationResult`` and
``calibrate(runs, settings, *, base_passport=None) -> CalibrationResult`` (the two in a row).
"""

from __future__ import annotations

from types import ModuleType

from pipeline.calibrate import differential, scalar, tilt
from pipeline.errors import CalibrationError, ThermocalError

#: recipe module by the name ``calibrate --method`` and ``fleet --method`` take
RECIPES: dict[str, ModuleType] = {"tilt": tilt, "scalar": scalar, "differential": differential}
#: the method names, the default first
METHODS: tuple[str, ...] = tuple(RECIPES)
#: methods that start from a normal-temperature passport (``base_passport``)
NEEDS_BASE_PASSPORT: tuple[str, ...] = ("differential",)


def recipe(method: str) -> ModuleType:
    """The recipe module of ``method``; CalibrationError naming the known methods otherwise."""
    try:
        return RECIPES[method]
    except KeyError:
        raise CalibrationError(f"unknown method {method!r} ({', '.join(METHODS)})") from None


def auto_method(run, seg) -> tuple[str, str]:
    """The method ``calibrate --method auto`` uses on ``run`` (segmented as ``seg``,
    :func:`pipeline.segment.segment_run`): the one inspect says the recording supports
    (:func:`pipeline.inspect.describe_recording`), and a line saying which and why. CalibrationError naming the
    file when no method fits the recording."""
    from pipeline.inspect import KIND_WORDS, describe_recording

    rec = describe_recording(run, seg)
    chosen = rec["method_auto"]
    kind = KIND_WORDS.get(rec["temperature"]["kind"], rec["temperature"]["kind"])
    if chosen is None:
        why = "; ".join(f"{m['method']}: {m['why']}" for m in rec["methods"])
        raise CalibrationError(f"no calibration method fits this recording ({kind}; {why})", path=run.source)
    m = next(m for m in rec["methods"] if m["method"] == chosen)
    return chosen, f"{chosen} ({kind}: {m['why']})"


def resolve_auto(run, settings, base_passport: dict | None = None):
    """The ``--method auto`` steps on a unit's first run, for the calibrate flow and the fleet alike: segment
    ``run`` (``settings.segment``), choose the method it supports (:func:`auto_method`) and keep ``base_passport``
    only when that method starts from one. Returns (the method's name, for :func:`recipe`; the base passport or
    None; the segmentation for the recipe's ``observe``; the line saying which method and why)."""
    from pipeline.segment import segment_run

    seg = segment_run(run, settings.segment)
    method, why = auto_method(run, seg)
    return method, (base_passport if method in NEEDS_BASE_PASSPORT else None), seg, why


def default_base_passport(registry, unit: str) -> tuple[dict | None, str]:
    """(:func:`base_passport_of`, a line saying which version and its status), or (None, a line saying why none)
    when the unit has no passport to start from: the differential method then takes the constants at T0 from the
    orientations themselves."""
    try:
        doc, st = base_passport_of(registry, unit)
    except ThermocalError as e:
        return None, (
            f"differential base: none ({e.message}); the constants at T0 are taken from the orientations themselves"
        )
    return doc, f"differential base: {st.text()}"


def base_passport_of(registry, unit: str):
    """The passport a differential calibration of ``unit`` starts from by default, and its
    :class:`pipeline.passport.registry.VersionState`: the unit's current passport in ``registry`` (a folder or a
    :class:`pipeline.passport.registry.Registry`; the one rule, :meth:`~pipeline.passport.registry.Registry.current`)
    among the versions not made by the differential method itself (a differential passport's constants at T0 are
    its base's, so starting from it changes nothing but the identity). CalibrationError when the unit has none, or
    when that version failed its verification (approve a passing version or name one with --base-passport)."""
    from pipeline.passport.registry import Registry

    reg = registry if isinstance(registry, Registry) else Registry(registry)
    try:
        st = reg.state(unit, exclude_methods=NEEDS_BASE_PASSPORT)
    except CalibrationError:
        raise
    except Exception as e:
        raise CalibrationError(
            f"no normal-temperature passport of {unit} to start from ({getattr(e, 'message', e)})"
        ) from None
    if st is None:
        raise CalibrationError(
            f"no normal-temperature passport of {unit} to start from (no version, or only differential ones)"
        )
    if st.status == "fail":
        raise CalibrationError(
            f"{st.text()} failed its verification: not a base for the "
            "differential method (approve a passing version, 'thermocal passport approve', or "
            "name one with --base-passport)"
        )
    return reg.load(unit, st.version), st
