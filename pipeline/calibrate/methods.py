"""The registry of calibration methods (:class:`pipeline.calibrate.method.Method`): what ``inspect``,
``--method auto``, the command line's ``--method`` and the fleet all read.

- :data:`BUILTIN`: the methods by name, each the module that defines it (its ``CALIBRATION_METHOD``), imported on
  first use (their names cost nothing: the command line checks ``--method`` without importing any);
  :func:`register` adds one more (a method defined elsewhere, a test's);
- :func:`names`, :func:`by_name`, :func:`all_methods`: the methods in the order listed;
- :func:`judge`: every method's :class:`pipeline.calibrate.method.Support` of a recording, in the order ``--method
  auto`` prefers them, and :func:`auto_choice` the one it takes; :func:`auto_method` / :func:`resolve_auto` the
  ``--method auto`` steps on a unit's first run (the calibrate flow's and the fleet's);
- :func:`default_base_passport`, :func:`base_passport_of`: the passport a method that uses one
  (:attr:`~pipeline.calibrate.method.Method.uses_base_passport`) starts from by default.

Adding a method: a module with a :class:`~pipeline.calibrate.method.Method` subclass and its instance
``CALIBRATION_METHOD``, and its line in :data:`BUILTIN`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from pipeline.errors import CalibrationError, ThermocalError

if TYPE_CHECKING:
    from pipeline.calibrate.method import Method, Support
    from pipeline.calibrate.recording import Recording
    from pipeline.passport.document import Passport

#: the built-in methods by the name ``calibrate --method`` and ``fleet --method`` take: the module defining each
BUILTIN: dict[str, str] = {
    "tilt": "pipeline.calibrate.tilt",
    "scalar": "pipeline.calibrate.scalar",
    "differential": "pipeline.calibrate.differential",
    "ramp": "pipeline.calibrate.ramp",
}
_loaded: dict[str, Method] = {}  # the methods imported or registered so far, by name


def names() -> tuple[str, ...]:
    """Every method's name, built-in first, without importing any."""
    return (*BUILTIN, *(n for n in _loaded if n not in BUILTIN))


def register(method: Method) -> Method:
    """Add ``method`` to the registry (after the others; a method of a name already registered replaces it).
    Returns it."""
    _loaded[method.name] = method
    return method


def unregister(name: str) -> None:
    """Remove the method ``name`` added by :func:`register` (a built-in one is loaded again on its next use)."""
    _loaded.pop(name, None)


def by_name(name: str) -> Method:
    """The method ``name``; CalibrationError naming the known methods otherwise."""
    if name not in _loaded:
        if name not in BUILTIN:
            raise CalibrationError(f"unknown method {name!r} ({', '.join(names())})")
        method = importlib.import_module(BUILTIN[name]).CALIBRATION_METHOD
        if method.name != name:
            raise CalibrationError(f"{BUILTIN[name]} defines the method {method.name!r}, not {name!r}")
        _loaded[name] = method
    return _loaded[name]


def all_methods() -> list[Method]:
    """Every method, in the order of :func:`names`."""
    return [by_name(n) for n in names()]


def passport_methods_with_base() -> tuple[str, ...]:
    """The passports' ``method`` of the methods that start from a base passport (never a base themselves)."""
    return tuple(m.passport_method for m in all_methods() if m.uses_base_passport)


def judge(recording: Recording) -> list[tuple[Method, Support]]:
    """Every method's judgement of ``recording`` (:meth:`~pipeline.calibrate.method.Method.supports`), the one
    ``--method auto`` prefers first (highest :attr:`~pipeline.calibrate.method.Support.preference`; ties in the
    order of :func:`names`)."""
    judged = [(m, m.supports(recording)) for m in all_methods()]
    return sorted(judged, key=lambda ms: -ms[1].preference)


def auto_choice(judged: list[tuple[Method, Support]]) -> tuple[Method, Support] | None:
    """The method ``--method auto`` takes from :func:`judge`'s list: the first that the recording supports or that
    insists on it (:attr:`~pipeline.calibrate.method.Support.insists`); None when none does."""
    return next(((m, s) for m, s in judged if s.supported or s.insists), None)


def auto_method(run, seg) -> tuple[str, str]:
    """The method ``calibrate --method auto`` uses on ``run`` (segmented as ``seg``,
    :func:`pipeline.segment.segment_run`): :func:`auto_choice`, and a line saying which and why. CalibrationError
    naming the file when no method fits the recording."""
    from pipeline.calibrate.recording import KIND_WORDS, Recording

    recording = Recording.of(run, seg)
    judged = judge(recording)
    kind = KIND_WORDS.get(recording.program.kind, recording.program.kind)
    chosen = auto_choice(judged)
    if chosen is None:
        from pipeline.segment import short_holds

        why = "; ".join(f"{m.name}: {s.why}" for m, s in judged)
        from pipeline.calibrate.method import with_stuck_clauses

        short = short_holds(run, seg)
        raise with_stuck_clauses(
            CalibrationError(
                f"no calibration method fits this recording ({kind}; {why})" + (f"; {short}" if short else ""),
                path=run.source,
            ),
            run.warnings,
        )
    m, s = chosen
    return m.name, f"{m.name} ({kind}: {s.why})"


def resolve_auto(run, settings, base_passport: Passport | None = None, seg=None):
    """The ``--method auto`` steps on a unit's first run, for the calibrate flow and the fleet alike: segment
    ``run`` (``settings.segment``; ``seg``: its segmentation, when already made), choose the method it supports
    (:func:`auto_method`) and keep ``base_passport`` only when that method starts from one. Returns (the method's
    name, for :func:`by_name`; the base passport or None; the segmentation for the method's ``observe``; the line
    saying which method and why)."""
    from pipeline.segment import segment_run

    seg = seg if seg is not None else segment_run(run, settings.segment)
    method, why = auto_method(run, seg)
    return method, (base_passport if by_name(method).uses_base_passport else None), seg, why


def default_base_passport(registry, unit: str) -> tuple[Passport | None, str]:
    """(:func:`base_passport_of`, a line saying which version and its status), or (None, a line saying why none)
    when the unit has no passport to start from: the differential method then takes the constants at T0 from the
    orientations themselves."""
    from pipeline.passport.verification import MalformedPassport, UntrustedPassport

    try:
        doc, st = base_passport_of(registry, unit)
    except (UntrustedPassport, MalformedPassport):
        raise  # a base that does not verify is refused, not silently replaced by none
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
    its base's, so starting from it changes nothing but the identity), verified
    (:meth:`~pipeline.passport.registry.Registry.load_state`: one that does not verify is refused, UntrustedPassport).
    CalibrationError when the unit has none, or when that version failed its verification (approve a passing
    version or name one with --base-passport)."""
    from pipeline.passport.document import load_passport
    from pipeline.passport.registry import Registry
    from pipeline.passport.verification import MalformedPassport, UntrustedPassport

    reg = registry if isinstance(registry, Registry) else Registry(registry)
    try:
        doc, st = reg.load_state(unit, exclude_methods=passport_methods_with_base())
    except (CalibrationError, UntrustedPassport, MalformedPassport):
        raise
    except Exception as e:
        raise CalibrationError(
            f"no normal-temperature passport of {unit} to start from ({getattr(e, 'message', e)})"
        ) from None
    if st.status == "fail":
        raise CalibrationError(
            f"{st.text()} failed its verification: not a base for the "
            "differential method (approve a passing version, 'thermocal passport approve', or "
            "name one with --base-passport)"
        )
    return load_passport(doc), st
