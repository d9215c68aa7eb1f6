"""What a calibration method is (:class:`Method`): what the recording must hold, what it determines, its per-run
step (``observe``) and its fit (``fit``); the verification, the plausibility judgement and the passport document
that follow every fit are one tail here (:meth:`Method.finish`).

A method is one module (``pipeline.calibrate.tilt``, ``.scalar``, ``.differential``) defining a subclass of
:class:`Method` and one instance of it, ``CALIBRATION_METHOD``; :mod:`pipeline.calibrate.methods` is the registry
that ``inspect``, ``--method auto``, the command line's ``--method`` and the fleet read.

The steps, for one unit:

1. ``supports(recording)`` (:class:`pipeline.calibrate.recording.Recording`: the temperature program, the static
   poses, the fixture log, the soaks whose test positions determine the 12 constants) -> :class:`Support`:
   whether this method can run on the recording, why, what it would determine, and how much ``--method auto``
   prefers it;
2. ``observe(run, settings, ...)`` per run -> :class:`pipeline.calibrate.observations.ObservedRun`;
3. ``fit(observed, settings, ...)`` -> :class:`Fitted`: the constants and thermal model
   (:class:`pipeline.calibrate.result.UnitFit`) and the method's own passport fields;
4. :meth:`Method.finish`: the VP verification (``verify_unit``), ``assess`` and ``build_passport``, the same for
   every method -> :class:`pipeline.calibrate.result.CalibrationResult`. ``calibrate_observed`` is 3 then 4,
   ``calibrate(runs)`` 2 then 3 then 4.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, ClassVar

from pipeline.calibrate.observations import (
    Observation,
    ObservedRun,
    plateau_summary,
    unit_of,
    verification_gap,
    verify_unit,
)
from pipeline.calibrate.result import CalibrationResult, UnitFit
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import CalibrationError
from pipeline.passport.document import Passport, build_passport, load_passport
from pipeline.plausibility import assess
from pipeline.run import PX4_DEVICE_ID_KEY
from pipeline.verify import VerificationRow

if TYPE_CHECKING:
    from pipeline.calibrate.recording import Recording
    from pipeline.run import Run


@dataclass(frozen=True)
class Support:
    """A method's judgement of a recording, before anything is fitted (:meth:`Method.supports`).

    ``supported``: the recording holds what the method needs; ``why``: one line saying what was found (or is
    missing); ``determines``: one line per group of constants it would determine, and what it leaves undetermined;
    ``preference``: how much ``--method auto`` prefers it on this recording (the methods are listed and tried
    highest first); ``insists``: when set, ``auto`` takes the method even where it is not supported (it then says
    exactly what is missing), and this says why (e.g. a tilt fixture's log)."""

    supported: bool
    why: str
    determines: tuple[str, ...] = ()
    preference: float = 0.0
    insists: str | None = None


@dataclass
class Fitted:
    """What a method's fit makes, before the tail every method shares (:meth:`Method.finish`): ``fit``, the constants
    and the thermal model the VP verification compensates with (``fit.skipped``: the fit's notes, also warnings);
    ``passport_fields``: the method's own fields of the passport (docs/contract.md: ``scalar``, ``differential``,
    ``rate_terms``...); ``settings_extra``: what the passport's identity depends on besides the settings and the
    method (:attr:`pipeline.calibrate.result.CalibrationResult.settings_extra`); ``observations``: the observations
    the tail verifies and summarises when the fit made its own (the ramp method's holds at the element temperature
    it fitted), None: the runs'. ``exact``: the static holds (run_id, t_start_ns) the fit reproduces by construction
    (as many equations as parameters: no redundancy), ``exact_why`` why: a VP row on one of them verifies nothing
    (its |dg| is 0 whatever the constants), so it does not count towards ``pass``."""

    fit: UnitFit
    passport_fields: dict[str, Any] = field(default_factory=dict)
    settings_extra: dict[str, Any] = field(default_factory=dict)
    observations: list[Observation] | None = None
    exact: frozenset[tuple[str, int]] = frozenset()
    exact_why: str = ""


class Method(ABC):
    """A calibration method. Subclasses set the class attributes and implement :meth:`supports`, :meth:`observe`
    and :meth:`fit`; the hooks :meth:`plateau_observations` and :meth:`verification_notes` have defaults."""

    #: the name ``calibrate --method`` and ``fleet --method`` take
    name: ClassVar[str]
    #: the passport's ``method`` field
    passport_method: ClassVar[str]
    #: the method starts from a normal-temperature passport when there is one (``base_passport``: named, or the
    #: unit's current passport in the registry, :func:`pipeline.calibrate.methods.default_base_passport`); a
    #: passport it made is never such a base itself
    uses_base_passport: ClassVar[bool] = False

    def __repr__(self) -> str:
        return f"<calibration method {self.name}>"

    @abstractmethod
    def supports(self, recording: Recording) -> Support:
        """Whether the recording (inspect's description of it) holds what this method needs, and what it would
        determine."""

    @abstractmethod
    def observe(
        self,
        run: Run,
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
        segmentation=None,
    ) -> ObservedRun:
        """The per-run step (what a fleet isolates: a run that cannot be observed is dropped). ``segmentation``:
        the run's, when already made with ``settings.segment`` (e.g. to choose the method). A method may take
        keyword options of its own after these (the differential method's settings)."""

    @abstractmethod
    def fit(
        self,
        observed: list[ObservedRun],
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | None = None,
    ) -> Fitted:
        """The constants and thermal model of one unit from its observed runs (a method may take keyword options of
        its own after these)."""

    def plateau_observations(self, observations: list[Observation]) -> list[Observation]:
        """The observations whose plateaus the passport's ``plateaus`` summary lists (default: all)."""
        return observations

    def recorded_temps_c(self, observed: list[ObservedRun], observations: list[Observation]) -> list[float]:
        """The AU temperatures (C) the recording held, for the plausibility check of T0 (default: the
        observations' temperatures)."""
        return [o.temp_c for o in observations]

    def verification_notes(
        self, observations: list[Observation], rows: list[VerificationRow], normal_temp_c: float
    ) -> list[str]:
        """Warnings about the verification itself, after the others (default: what the VP data leave unverified of
        the thermal model's range, :func:`pipeline.calibrate.observations.verification_gap`: the reason
        :func:`verify_unit` gives every method's ``pass`` up for ``unverified``)."""
        gap = verification_gap(observations, normal_temp_c) if rows else None
        return [gap] if gap else []

    def finish(self, observed: list[ObservedRun], fitted: Fitted, settings: CalibrationSettings) -> CalibrationResult:
        """The tail of every method: verify ``fitted.fit.model`` at every VP observation against the unit grade's
        limits (:meth:`CalibrationSettings.tolerances_for`), judge the constants'
        plausibility (:func:`pipeline.plausibility.assess`), and build the passport document with the method's
        fields. Warnings: the runs', the fit's notes, the implausibilities not already among the runs', then
        :meth:`verification_notes`."""
        unit_fit = fitted.fit
        meta = observed[0].meta
        observations = (
            fitted.observations if fitted.observations is not None else [o for r in observed for o in r.observations]
        )
        tolerances = settings.tolerances_for(meta)  # the unit's grade: --grade, else the run's unit_grade
        rows, status = verify_unit(unit_fit.model, observations, unit_fit.normal_temp_c, tolerances)
        status, void = _without_exact_rows(rows, status, fitted)
        if void:
            unit_fit = replace(unit_fit, skipped=[*unit_fit.skipped, void])
        run_warnings = [w for r in observed for w in r.warnings]
        temps_c = self.recorded_temps_c(observed, observations)
        status, implausible = assess(unit_fit, status, meta.nominal_gain_v_per_g, run_warnings, temps_c=temps_c)
        plateaus = plateau_summary(self.plateau_observations(observations))
        doc = build_passport(
            unit_fit,
            rows,
            status,
            g_local_mps2=meta.g_local_mps2,
            plateaus=plateaus,
            method=self.passport_method,
            tolerances=tolerances,
            extra={**fitted.passport_fields, **({"implausible": implausible} if implausible else {})},
        )
        return CalibrationResult(
            passport=doc,
            fit=unit_fit,
            rows=rows,
            status=status,
            plateaus=plateaus,
            warnings=run_warnings
            + list(unit_fit.skipped)
            + [p for p in implausible if p not in run_warnings]
            + self.verification_notes(observations, rows, unit_fit.normal_temp_c),
            settings_extra=dict(fitted.settings_extra),
            input_notes={
                r.source: {PX4_DEVICE_ID_KEY: r.meta.extra[PX4_DEVICE_ID_KEY]}
                for r in observed
                if r.source and r.meta.extra.get(PX4_DEVICE_ID_KEY)
            },
        )

    def calibrate_observed(
        self,
        observed: list[ObservedRun],
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | dict | None = None,
        **options,
    ) -> CalibrationResult:
        """:meth:`fit` then :meth:`finish`: the calibration of one unit from its observed runs (``base_passport``: a
        document is loaded once here, :func:`pipeline.passport.document.load_passport`)."""
        base = None if base_passport is None else load_passport(base_passport)
        try:
            fitted = self.fit(observed, settings, base_passport=base, **options)
        except CalibrationError as e:
            raise with_stuck_clauses(e, [w for r in observed for w in r.warnings]) from None
        return self.finish(observed, fitted, settings)

    def calibrate(
        self,
        runs,
        settings: CalibrationSettings = CalibrationSettings(),
        *,
        base_passport: Passport | dict | None = None,
        **options,
    ) -> CalibrationResult:
        """The calibration of one unit from its runs: :meth:`observe` each, then :meth:`calibrate_observed`
        (``options``: the method's own, passed to both; ``base_passport``: a document is loaded once here)."""
        runs = list(runs)
        unit_of(runs)
        base = None if base_passport is None else load_passport(base_passport)
        observed = [self.observe(r, settings, base_passport=base, **options) for r in runs]
        return self.calibrate_observed(observed, settings, base_passport=base, **options)


def with_stuck_clauses(e: CalibrationError, warnings: list[str]) -> CalibrationError:
    """``e`` with the channels left out as stuck or clipped (:func:`pipeline.io.checks.stuck_clauses`) named, when
    there are any: the refusal of a unit with too little left says why."""
    from pipeline.io.checks import stuck_clauses

    clauses = stuck_clauses(warnings)
    if not clauses:
        return e
    return CalibrationError(
        f"{e.message}; left out as stuck or clipped: {'; '.join(clauses)}", path=e.path, stream=e.stream, where=e.where
    )


def _without_exact_rows(rows: list[VerificationRow], status: str, fitted: Fitted) -> tuple[str, str | None]:
    """The status once the VP rows on holds the fit reproduces by construction (``fitted.exact``) no longer count,
    and the note saying so (None when there are none): a ``pass`` that rests on those rows alone is ``unverified``
    (a row elsewhere, e.g. at another temperature, still verifies; a ``fail`` stays one)."""
    exact = [r for r in rows if (r.run_id, r.t_start_ns) in fitted.exact]
    if not exact:
        return status, None
    rest = len(rows) - len(exact)
    if status == "pass" and not rest:
        status = "unverified"
    names = ", ".join(dict.fromkeys(r.position for r in exact))
    return status, (
        f"verification: the {len(exact)} VP row(s) at {names} are holds the fit reproduces exactly "
        f"({fitted.exact_why}): their |dg| is 0 by construction and verifies nothing; "
        + (f"the status rests on the other {rest} row(s)" if rest else "nothing is verified")
    )
