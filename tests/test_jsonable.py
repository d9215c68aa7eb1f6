"""One JSON coercion (pipeline.jsonable) for every JSON the project writes, and the run's one finite-thermosensor
view (Run.thermosensor)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pipeline.jsonable import json_default, to_jsonable
from pipeline.passport.canonical import canonical_json
from pipeline.run import Run, RunMeta, make_frame


@dataclass
class _Row:
    name: str
    u_v: np.ndarray
    span: tuple


def test_to_jsonable_and_json_default():
    value = {
        "rows": [_Row("TP1", np.array([0.5, -0.25, 1e-6]), (np.int64(3), np.float32(0.5)))],
        1: Path("/x/y.mcap"),
        "flag": np.bool_(True),
    }
    plain = to_jsonable(value)
    assert plain == {
        "rows": [{"name": "TP1", "u_v": [0.5, -0.25, 1e-6], "span": [3, 0.5]}],
        "1": "/x/y.mcap",
        "flag": True,
    }
    assert type(plain["rows"][0]["span"][0]) is int and type(plain["flag"]) is bool
    assert json.loads(json.dumps({"k": np.arange(3), "p": Path("a")}, default=json_default)) == {
        "k": [0, 1, 2],
        "p": "a",
    }
    assert (
        canonical_json({"K": np.eye(2)})
        == b'{\n  "K": [\n    [\n      1.0,\n      0.0\n    ],\n    [\n      0.0,\n      1.0\n    ]\n  ]\n}\n'
    )
    with pytest.raises(TypeError):
        json.dumps({"x": object()}, default=json_default)


def test_run_thermosensor_drops_non_finite_samples():
    run = Run(
        meta=RunMeta(unit_serial="AU-1", run_id="r"),
        voltmeter=make_frame("voltmeter", {"t_ns": [0], "ux": [0.0], "uy": [0.0], "uz": [0.0]}),
        au_temperature=make_frame("au_temperature", {"t_ns": [0, 10, 20, 30], "temp_c": [20.0, np.nan, 21.0, np.inf]}),
    )
    t_ns, temp_c = run.thermosensor()
    assert t_ns.tolist() == [0, 20] and temp_c.tolist() == [20.0, 21.0] and t_ns.dtype == np.int64
