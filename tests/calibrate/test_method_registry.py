"""One method interface (issue 27): ``inspect``, ``--method auto``, the command line's ``--method`` and the fleet
all read the registry (``pipeline.calibrate.methods``), so a fourth method defined in one module is seen by every
one of them with no other change; ``auto`` takes the most preferred method the recording supports, or one that
insists on it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate import methods
from pipeline.calibrate.fleet import ALREADY_PROCESSED, calibrate_group, plan_fleet
from pipeline.calibrate.method import Fitted, Method, Support
from pipeline.calibrate.observations import ObservedRun, observe_run, unit_of
from pipeline.calibrate.result import UnitFit
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import ThermocalError
from pipeline.inspect import describe_recording
from pipeline.io.runs import read_run, write_run
from pipeline.segment import segment_run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.thermal import PolynomialModel

REPO = Path(__file__).resolve().parents[2]


class Nominal(Method):
    """A fourth method, defined here only: the nominal gain on the diagonal of K and zero offsets, at T0, for a
    recording with four or more static poses; preferred above every built-in method."""

    name = "nominal"
    passport_method = "nominal_gain"

    def supports(self, recording):
        n = len(recording.poses)
        return Support(
            supported=n >= 4,
            why=f"{n} static poses",
            determines=("K diagonal from the nominal gain, U0 = 0",),
            preference=99.0,
        )

    def observe(self, run, settings=CalibrationSettings(), *, base_passport=None, segmentation=None):
        obs, warnings = observe_run(run, settings.segment, segmentation)
        return ObservedRun(meta=run.meta, source=run.source, observations=obs, warnings=warnings)

    def fit(self, observed, settings=CalibrationSettings(), *, base_passport=None):
        meta = observed[0].meta
        K = np.diag(np.full(3, meta.nominal_gain_v_per_g))
        model = PolynomialModel(K, np.zeros(3), meta.normal_temp_c, 0, np.zeros((0, 3)), np.zeros((0, 3, 3)))
        fit = UnitFit(unit_of(observed), meta.normal_temp_c, [], model, skipped=["nominal: not measured"])
        return Fitted(fit, passport_fields={"nominal": {"gain_v_per_g": meta.nominal_gain_v_per_g}})


@pytest.fixture
def nominal():
    method = methods.register(Nominal())
    yield method
    methods.unregister("nominal")


@pytest.fixture(scope="module")
def inbox(tmp_path_factory):
    """AU-0001's short program (2 Hz) in a folder of its own."""
    d = tmp_path_factory.mktemp("registry") / "inbox"
    write_run(simulate(SimConfig(seed=5, program="short", rate_hz=2)).run, d / "short.mcap", "mcap")
    return d


def test_built_in_methods_and_the_passport_schema():
    """The built-in methods by name, in order; the passport schema's ``method`` lists each one's passport method."""
    assert methods.names() == ("tilt", "scalar", "differential", "ramp")
    assert [m.name for m in methods.all_methods()] == list(methods.names())
    assert methods.passport_methods_with_base() == ("differential",)
    schema = json.loads((REPO / "schemas" / "thermocal.passport.json").read_text())
    assert set(schema["properties"]["method"]["enum"]) == {m.passport_method for m in methods.all_methods()}


def test_a_fourth_method_is_seen_by_inspect_auto_the_command_line_and_the_fleet(nominal, inbox, tmp_path):
    from flows.cli.app import check_method

    run = read_run(inbox / "short.mcap")
    seg = segment_run(run)
    assert methods.names() == ("tilt", "scalar", "differential", "ramp", "nominal")
    check_method("nominal")  # the command line's --method takes it
    with pytest.raises(
        ThermocalError, match=r"unknown method 'sweep' \(auto, tilt, scalar, differential, ramp, nominal\)"
    ):
        check_method("sweep")

    rec = describe_recording(run, seg)  # inspect lists it first (the most preferred) and auto takes it
    assert [m["method"] for m in rec["methods"]] == ["nominal", "tilt", "differential", "ramp", "scalar"]
    assert rec["methods"][0] == {
        "method": "nominal",
        "supported": True,
        "why": f"{rec['static']['poses']} static poses",
        "determines": ["K diagonal from the nominal gain, U0 = 0"],
    }
    assert rec["method_auto"] == "nominal"
    assert methods.auto_method(run, seg) == (
        "nominal",
        f"nominal (plateau program: {rec['static']['poses']} static poses)",
    )

    reg = tmp_path / "reg"  # the fleet: auto picks it, the passport is the shared tail's
    plan = plan_fleet(inbox, reg, CalibrationSettings(), "auto")
    (group,) = plan.groups
    outcome = calibrate_group(group.unit, group.runs, reg, figure=False, digests=group.digests, method="auto")
    assert not outcome.failed and outcome.result["method"] == "nominal_gain"
    doc = json.loads(Path(outcome.result["passport"]).read_text())
    gain = run.meta.nominal_gain_v_per_g
    assert doc["coefficients"]["K"] == np.diag([gain] * 3).tolist() and doc["coefficients"]["U0"] == [0.0] * 3
    assert doc["nominal"] == {"gain_v_per_g": gain} and doc["notes"] == ["nominal: not measured"]
    assert len(doc["verification"]) == len(outcome.result["verification"]) > 0
    # a unit made by it is done, for auto and for the method by name
    for method in ("auto", "nominal"):
        plan = plan_fleet(inbox, reg, CalibrationSettings(), method)
        assert not plan.groups and [s["why"] for s in plan.skipped] == [ALREADY_PROCESSED]


def test_unregistered_it_is_gone(inbox):
    run = read_run(inbox / "short.mcap")
    assert "nominal" not in methods.names()
    assert methods.auto_method(run, segment_run(run))[0] == "tilt"


def _support(supported: bool, preference: float, insists: str | None = None) -> Support:
    return Support(supported=supported, why="", preference=preference, insists=insists)


def test_auto_takes_the_first_supported_or_insisting_method():
    a, b, c = (methods.by_name(n) for n in methods.names()[:3])
    assert methods.auto_choice([(a, _support(False, 3)), (b, _support(True, 2)), (c, _support(True, 1))])[0] is b
    insisting = _support(False, 2, insists="the fixture log says so")
    assert methods.auto_choice([(a, _support(False, 3)), (b, insisting), (c, _support(True, 1))])[0] is b
    assert methods.auto_choice([(a, _support(False, 3)), (c, _support(False, 1))]) is None
