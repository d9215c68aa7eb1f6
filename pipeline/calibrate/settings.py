"""The settings of a calibration: everything that changes a passport (recorded in its provenance, hashed into its
identity), for every method."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from pipeline.segment import SegmentSettings
from pipeline.verify import Tolerances, grade_tolerances, resolve_tolerances


@dataclass(frozen=True)
class CalibrationSettings:
    """Everything that changes a passport. ``thermal_model``: auto | poly1 | poly2 | poly3 | piecewise
    (:data:`pipeline.thermal.THERMAL_MODELS`); ``constants_method``: auto | six_position | least_squares
    (:data:`pipeline.constants.CONSTANTS_METHODS`); ``cluster_tol_c`` (C): plateaus closer than this are one
    calibration temperature. ``grade``: the unit's grade (:data:`pipeline.verify.GRADES`), which sets the
    verification limits; None takes the run's ``unit_grade``, else navigation. ``tol_normal_g`` /
    ``tol_range_g`` (g): limits that replace the grade's at T0 / over the range (None: the grade's)."""

    thermal_model: str = "auto"
    constants_method: str = "auto"
    cluster_tol_c: float = 3.0
    temperature_referencing_passes: int = 2
    grade: str | None = None
    tol_normal_g: float | None = None
    tol_range_g: float | None = None
    segment: SegmentSettings = field(default_factory=SegmentSettings)

    def __post_init__(self):
        if self.grade is not None:
            grade_tolerances(self.grade)  # ValueError naming the grades

    def to_dict(self) -> dict:
        return asdict(self)

    def tolerances_for(self, meta) -> Tolerances:
        """The verification limits of a unit whose run metadata is ``meta`` (:class:`pipeline.run.RunMeta`, its
        ``unit_grade``; None: none), :func:`pipeline.verify.resolve_tolerances`."""
        return resolve_tolerances(
            self.grade,
            getattr(meta, "unit_grade", None),
            normal_g=self.tol_normal_g,
            operating_range_g=self.tol_range_g,
        )
