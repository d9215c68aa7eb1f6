"""The one result type of every calibration method (:class:`CalibrationResult`), and the fitted constants it
holds (:class:`UnitFit`, :class:`PlateauConstants`).

A recipe (``pipeline.calibrate.tilt``, ``.scalar``, ``.differential``) is a pure ``calibrate(runs, settings, ...)
-> CalibrationResult``; ``pipeline.calibrate.publish.publish`` is the one path that writes a result into the
registry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.passport.document import Passport
from pipeline.thermal import ThermalModel
from pipeline.uncertainty import ThermalSigma
from pipeline.verify import VerificationRow


@dataclass(frozen=True)
class PlateauConstants:
    """The 12 constants at one calibration plateau: K (3, 3) V/g, U0 (3,) V at ``temp_c`` (C), the positions used,
    the method (``six_position``, ``least_squares``, ``scalar_nonlinear``...) and the output residual RMS (V)."""

    run_id: str
    plateau: int
    temp_c: float
    K: np.ndarray  # (3, 3) V/g
    U0: np.ndarray  # (3,) V
    positions: tuple[str, ...]
    method: str
    residual_rms_v: float
    K_sigma: np.ndarray | None = None  # (3, 3) V/g, standard uncertainty of K (None: not estimated)
    U0_sigma: np.ndarray | None = None  # (3,) V

    def to_dict(self) -> dict:
        return {
            "temp_c": round(self.temp_c, 4),
            "run_id": self.run_id,
            "plateau": self.plateau,
            "K": self.K.tolist(),
            "U0": self.U0.tolist(),
            "positions": list(self.positions),
            "method": self.method,
            "residual_rms_v": self.residual_rms_v,
        }


@dataclass
class UnitFit:
    """A unit's fitted constants: per plateau, and the thermal model K(T), U0(T) about ``normal_temp_c`` (C)."""

    unit: str
    normal_temp_c: float
    per_plateau: list[PlateauConstants]
    model: ThermalModel
    skipped: list[str]  # one line per plateau that could not be used, and why (notes of the passport)
    uncertainty: ThermalSigma | None = None  # of K0, U00 and the thermal model's coefficients
    valid_temp_c: tuple[float, float] | None = None  # the calibration temperatures the data covered (C)
    excess_scatter_v: np.ndarray | None = None  # (3,) V, segment scatter beyond the measured noise (pooled)


@dataclass
class CalibrationResult:
    """A calibration by any method, ready to publish.

    ``passport``: the passport document (docs/contract.md) without the registry's fields (version, parent, creation
    time, provenance); ``fit``: the constants it was built from; ``rows``/``status``: the VP verification;
    ``plateaus``: the plateau summary of ``calibrate --json``; ``warnings``: the runs' and the fit's warnings, one
    line each; ``settings_extra``: what the passport's identity depends on besides the calibration settings and the
    method (the differential method: its base passport)."""

    passport: dict
    fit: UnitFit
    rows: list[VerificationRow]
    status: str
    plateaus: list[dict]
    warnings: list[str] = field(default_factory=list)
    settings_extra: dict = field(default_factory=dict)
    #: per input run (its ``source``), what its metadata adds to its provenance record (``px4_accel_device_id``)
    input_notes: dict[str, dict] = field(default_factory=dict)

    @property
    def unit(self) -> str:
        return self.fit.unit

    @property
    def method(self) -> str:
        """The passport's ``method``: ``tilt_six_position``, ``scalar`` or ``differential``."""
        return self.passport["method"]


def base_reference(base_passport: Passport) -> dict:
    """What a passport's identity records of the base passport its method started from (the differential method;
    :attr:`CalibrationResult.settings_extra`)."""
    return {"base_passport_sha256": base_passport.content_sha256 or base_passport.unit}
