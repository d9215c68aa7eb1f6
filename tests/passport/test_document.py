"""The typed passport and its one loader: every method's passport loads as a :class:`Passport` with its format
version and method, the loader returns the right compensation model for each (thermal model; thermal model with
rate terms and lag; extended model), the JSON on disk is what the loader hands back, and a file that is not a
passport is a one-line error naming it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline import compensate
from pipeline.calibrate import scalar, tilt
from pipeline.calibrate.publish import publish
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.effects.model import ExtendedModel
from pipeline.errors import ThermocalError
from pipeline.model import gravity_module_error_g, output_v
from pipeline.passport.document import SCHEMA_ID, Passport, load_model, load_passport, read_passport
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.unit import UnitTruth
from pipeline.thermal import DifferentialModel, PolynomialModel, RateTerms


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """A short 2 Hz run calibrated by tilt and by scalar, published into a registry."""
    reg = tmp_path_factory.mktemp("reg")
    res = simulate(SimConfig(seed=5, program="short", rate_hz=2))
    out = {}
    for rec in (tilt, scalar):
        result = rec.calibrate([res.run])
        out[rec.METHOD] = publish(reg, result, input_paths=[], settings=CalibrationSettings(), figure=False)
    return out, UnitTruth.from_dict(res.truth["unit"])


def test_every_method_loads_typed_with_its_model(published):
    out, unit = published
    for method, result in out.items():
        p = load_passport(result["passport"])
        assert isinstance(p, Passport) and p.format == SCHEMA_ID and p.method == method
        assert p.unit == "AU-0001" and p.version == result["version"] and p.status == result["status"]
        on_disk = json.loads(open(result["passport"]).read())
        assert p.to_dict() == on_disk and read_passport(result["passport"]) == on_disk
        model = p.compensation_model()
        assert isinstance(model, PolynomialModel) and model is p.thermal_model
        np.testing.assert_array_equal(p.K, on_disk["coefficients"]["K"])
        # the model compensates the true unit's outputs at T0 to within 20 micro-g
        a = np.array([[0, 0, 1.0], [0.6, 0, 0.8], [0, -1.0, 0]])
        K, U0 = unit.constants_at(np.full(3, 20.0))
        dg = gravity_module_error_g(compensate.method1(model, output_v(K, U0, a), np.full(3, 20.0)))
        assert np.abs(dg).max() < 2e-5, (method, dg)
    assert out["tilt_six_position"]["version"] == 1 and out["scalar"]["version"] == 2


def test_rate_terms_and_extended_models_come_from_the_same_loader(published):
    """A passport with rate terms loads as a DifferentialModel whose constants move with the rate; one with an
    extended model as the ExtendedModel; load_model gives the base thermal model of either."""
    out, _ = published
    doc = json.loads(open(out["tilt_six_position"]["passport"]).read())
    rate = RateTerms(
        alpha_rate=np.full((1, 1, 3), 1e-5), beta_rate=np.zeros((1, 1, 3)), temp_smooth_s=301.0, lag_tau_s=12.0
    )
    diff_doc = {**doc, "method": "differential", "rate_terms": rate.to_dict()}
    model = load_passport(json.loads(json.dumps(diff_doc))).compensation_model()
    assert isinstance(model, DifferentialModel) and model.lag_tau_s == 12.0
    _, u0_still = model.constants_at(np.array([20.0]), np.array([0.0]))
    _, u0_ramp = model.constants_at(np.array([20.0]), np.array([2.0]))
    np.testing.assert_allclose(u0_ramp - u0_still, 2e-5, rtol=1e-12)
    base = load_model(diff_doc)
    assert isinstance(base, PolynomialModel) and base.order == load_model(doc).order

    ext = ExtendedModel(base=load_model(doc), effects=[])
    ext_doc = {**doc, "extended_model": ext.to_dict()}
    loaded = load_passport(ext_doc).compensation_model()
    assert isinstance(loaded, ExtendedModel)
    np.testing.assert_array_equal(loaded.base.K0, base.K0)


def test_not_a_passport_is_one_line_naming_the_file(tmp_path, published):
    out, _ = published
    doc = json.loads(open(out["scalar"]["passport"]).read())
    cases = {
        "other-schema.json": {**doc, "schema": "thermocal.passport/0"},
        "no-constants.json": {k: v for k, v in doc.items() if k != "coefficients"},
        "bad-K.json": {**doc, "coefficients": {"K": [[1, 2], [3, 4]], "U0": [0, 0, 0]}},
        "truncated.json": None,
    }
    for name, content in cases.items():
        path = tmp_path / name
        path.write_text(json.dumps(content) if content is not None else json.dumps(doc)[:100])
        with pytest.raises(ThermocalError) as err:
            load_passport(path)
        line = err.value.one_line()
        assert str(path) in line and "\n" not in line, line


def test_a_differential_passport_without_rate_terms_passes_the_content_check(published):
    """The differential method's validation may choose no rate terms (order 0, as for the CATS tag's sweep with its
    held-out blocks deleted): the passport calibrate writes passes the check every reader applies (was: apply,
    export and diagnose --registry refused it, 'rate_terms.order: 0 is outside 1..8'); 9 is still refused."""
    from pipeline.passport.verification import MAX_ORDER, check_content

    out, _ = published
    doc = json.loads(open(out["tilt_six_position"]["passport"]).read())
    none = RateTerms(alpha_rate=np.zeros((0, 1, 3)), beta_rate=np.zeros((0, 1, 3)), temp_smooth_s=301.0, lag_tau_s=0.0)
    diff_doc = json.loads(json.dumps({**doc, "method": "differential", "rate_terms": none.to_dict()}))
    assert diff_doc["rate_terms"]["order"] == 0
    check_content(diff_doc, "p.json")
    model = load_passport(diff_doc).compensation_model()
    assert isinstance(model, DifferentialModel)
    too_high = {**diff_doc, "rate_terms": {**diff_doc["rate_terms"], "order": MAX_ORDER + 1}}
    with pytest.raises(ThermocalError, match="rate_terms.order"):
        check_content(too_high, "p.json")
