"""The settings of a calibration: everything that changes a passport (recorded in its provenance, hashed into its
identity), for every method."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from pipeline.segment import SegmentSettings
from pipeline.verify import Tolerances


@dataclass(frozen=True)
class CalibrationSettings:
    """Everything that changes a passport. ``thermal_model``: auto | poly1 | poly2 | poly3 | piecewise
    (:data:`pipeline.thermal.THERMAL_MODELS`); ``constants_method``: auto | six_position | least_squares
    (:data:`pipeline.constants.CONSTANTS_METHODS`); ``cluster_tol_c`` (C): plateaus closer than this are one
    calibration temperature."""

    thermal_model: str = "auto"
    constants_method: str = "auto"
    cluster_tol_c: float = 3.0
    temperature_referencing_passes: int = 2
    tolerances: Tolerances = field(default_factory=Tolerances)
    segment: SegmentSettings = field(default_factory=SegmentSettings)

    def to_dict(self) -> dict:
        return asdict(self)
