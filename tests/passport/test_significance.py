"""passport diff marks the changes that exceed their combined uncertainty (pipeline/passport/significance.py):
two calibrations of one unit from two noise seeds differ by noise only (few marked); a real shift of a gain and an
offset is marked, in ppm of gain and micro-g; tiny float deltas are not."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from pipeline.calibrate import tilt
from pipeline.passport.document import build_passport
from pipeline.passport.registry import Registry
from pipeline.passport.significance import sigma_of, significant_changes
from pipeline.simulate.chamber import SimConfig, simulate


def _passport(seed: int) -> dict:
    res = simulate(SimConfig(seed=seed, program="short", rate_hz=1.0))
    obs, _ = tilt.observe_run(res.run)
    fit = tilt.fit_unit("AU-0001", obs, tilt.CalibrationSettings(), 20.0)
    return build_passport(fit, [], "unverified", g_local_mps2=9.80665, plateaus=[])


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    reg = Registry(tmp_path_factory.mktemp("reg"))
    a, b = _passport(41), _passport(42)
    shifted = copy.deepcopy(b)
    shifted["coefficients"]["U0"][0] += 5e-6  # about 9 micro-g on x
    shifted["coefficients"]["K"][1][1] *= 1 + 40e-6  # 40 ppm of the y gain
    shifted["coefficients"]["K"][2][0] += 1e-16  # a float-noise delta
    for n, doc in enumerate((a, b, shifted)):
        reg.publish(doc, inputs=[{"path": f"run{n}.mcap", "sha256": f"{n:064x}"}], settings={}, code_version="t")
    return reg


def test_noise_only_changes_are_rarely_significant(registry):
    d = registry.diff("AU-0001", 1, 2)
    entries = d["constants"] + d["thermal_model"]
    assert len(entries) == 12 + 24 and all(e["significant"] is not None for e in entries)
    assert sum(e["significant"] for e in entries) <= 5  # about 5 % expected at k = 2
    assert d["significance"]["coverage_factor"] == 2.0
    for e in d["constants"]:
        assert e["uncertainty"] > 0 and e["uncertainty_scaled"] > 0
        if e["name"].startswith("U0"):
            assert e["scaled_unit"] == "micro-g" and e["uncertainty_scaled"] < 3  # below a few micro-g


def test_real_shift_is_marked_in_engineering_units(registry):
    d = registry.diff("AU-0001", 2, 3)
    by_name = {e["name"]: e for e in d["constants"]}
    assert set(by_name) == {"U0.x", "K.yy", "K.zx"}
    assert by_name["U0.x"]["significant"] and by_name["K.yy"]["significant"]
    assert not by_name["K.zx"]["significant"]
    assert by_name["U0.x"]["delta_scaled"] == pytest.approx(5e-6 / 0.55 * 1e6, rel=0.02)  # micro-g
    assert by_name["K.yy"]["delta_scaled"] == pytest.approx(-40.0, rel=0.02)  # ppm (gain < 0)
    assert {e["name"] for e in significant_changes(d)} == {"U0.x", "K.yy"}


def test_sigma_lookup_and_missing_uncertainty(registry):
    doc = registry.load("AU-0001", 1)
    assert sigma_of(doc, "K.xy") == doc["uncertainty"]["coefficients"]["K"][0][1]
    assert sigma_of(doc, "alpha.z[2]") == doc["uncertainty"]["thermal_model"]["alpha"]["z"][1]
    assert sigma_of(doc, "gamma.zy[1]") == doc["uncertainty"]["thermal_model"]["gamma"]["zy"][0]
    assert sigma_of({}, "K.xy") is None and sigma_of(doc, "nonsense") is None
    assert np.isfinite(sigma_of(doc, "U0.y"))
