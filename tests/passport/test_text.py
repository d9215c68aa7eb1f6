"""What a person reads (issue 16, item 6): calibrate's summary, passport log / show / diff, on a real registry."""

from __future__ import annotations

import json
import re

from flows.cli.calibrate import calibrate_text
from pipeline.passport.registry import Registry
from pipeline.passport.text import diff_lines, verification_lines
from tests.conftest import run_main


def test_calibrate_summary_is_a_table_per_temperature(calibrated_registry):
    res = calibrated_registry["results"][0]
    doc = json.loads(open(res["passport"]).read())
    text = calibrate_text({**res, "constants_figure": "c.png"})
    lines = text.splitlines()
    assert len(lines) < 30, text
    # one row per visit of a verification temperature, with its limit in micro-g
    rows = [ln for ln in lines if re.match(r"^\s+[+-]\d+\.\d C", ln)]
    temps = sorted({round(v["temp_c"]) for v in doc["verification"]})
    assert len(rows) >= len(temps) and all(("1000" in r or "300" in r) for r in rows), text
    m1_by_temp: dict[int, float] = {}  # the "after m1" column: the largest |dg| of the visit, in micro-g
    for r in rows:
        m = re.search(r"(\d+\.\d)\s+(\d+\.\d)\s+(\d+\.\d)\s+(\d+)\s+(pass|FAIL)", r)
        assert m, r
        t = round(float(r.split()[0]))
        m1_by_temp[t] = max(m1_by_temp.get(t, 0.0), float(m.group(2)))
    for t in temps:
        worst = max(abs(v["dg_method1_g"]) for v in doc["verification"] if round(v["temp_c"]) == t) * 1e6
        assert abs(m1_by_temp[t] - worst) < 0.051, (t, m1_by_temp, worst)
    assert f"figure, VP errors: {res['figure']}" in text and "figure, constants: c.png" in text
    assert "constants at T0 = +20.0 C" in text and "+-" in text and "ppm" in text and "ug" in text


def test_calibrate_summary_names_the_method_once(calibrated_registry):
    """``--method auto``: one method line, the passport's method with why auto picked it (it was printed twice:
    ``method: tilt (...)`` above ``method tilt_six_position; ...``)."""
    res = calibrated_registry["results"][0]
    doc = json.loads(open(res["passport"]).read())
    why = "plateaus with the six tilt positions: the 12 constants at each temperature"
    text = calibrate_text({**res, "method": "tilt", "method_auto": f"tilt ({why})"})
    said = [ln for ln in text.splitlines() if ln.lstrip().startswith("method")]
    assert said == [
        f"  method {doc['method']} (picked by --method auto: {why}); thermal model "
        + said[0].split("; thermal model ", 1)[1]
    ], text
    plain = calibrate_text({k: v for k, v in res.items() if k != "method_auto"})
    assert [ln for ln in plain.splitlines() if ln.lstrip().startswith("method")] == [
        said[0].replace(f" (picked by --method auto: {why})", "")
    ]


def test_failing_rows_are_marked():
    rows = [
        {
            "temp_c": -10.0,
            "position": f"VP{k}",
            "run_id": "r",
            "t_start_ns": k,
            "dg_uncompensated_g": 5e-3,
            "dg_method1_g": (1.4e-3 if k == 2 else 2e-6),
            "dg_method2_g": 1e-5,
            "tolerance_g": 1e-3,
            "passed": k != 2,
        }
        for k in range(1, 7)
    ]
    lines = verification_lines({"verification": rows})
    row = next(ln for ln in lines if "-10.0 C" in ln)
    assert "FAIL" in row and "5000.0" in row and "1400.0" in row and "1000" in row
    assert any("FAIL VP2" in ln and "1400.0 > 1000" in ln for ln in lines)
    assert not any("FAIL VP1" in ln for ln in lines)


def test_passport_log_show_and_diff(monkeypatch, capsys, calibrated_registry):
    reg, unit = str(calibrated_registry["registry"]), calibrated_registry["unit"]
    code, out, err = run_main(monkeypatch, capsys, "passport", "log", unit, "--registry", reg)
    assert code == 0 and err == ""
    v1, v2 = [ln for ln in out.splitlines() if re.match(r"^ [ *] v\d", ln)]
    assert "tilt_six_position" in v1 and "poly" in v1 and "ug" in v1
    assert "piecewise" in v2
    docs = [Registry(reg).load(unit, v) for v in (1, 2)]
    for line, doc in zip((v1, v2), docs):
        assert doc["status"] in line
        worst = max(abs(r["dg_method1_g"]) for r in doc["verification"]) * 1e6
        assert f"{worst:.1f}ug" in line
    code, out, _ = run_main(monkeypatch, capsys, "passport", "show", unit, "1", "--registry", reg)
    assert code == 0 and not out.lstrip().startswith("{") and len(out.splitlines()) < 40
    for what in (
        "passport v1",
        "method: tilt_six_position",
        "thermal model: polynomial",
        "approval:",
        "constants at T0",
        "verification at the VP positions",
        "inputs (sha256)",
        docs[0]["provenance"]["inputs"][0]["sha256"][:16],
        "v0001.png",
    ):
        assert what in out, what
    code, out, _ = run_main(monkeypatch, capsys, "passport", "show", unit, "1", "--registry", reg, "--json")
    assert json.loads(out) == docs[0]
    code, out, _ = run_main(monkeypatch, capsys, "passport", "diff", unit, "1", "2", "--registry", reg)
    assert code == 0
    assert "thermal_model.kind: polynomial -> piecewise_linear" in out
    assert "thermal models of different forms" in out
    assert "e-1" not in out  # no 16-digit numbers: tiny deltas are counted, not listed
    assert "within their uncertainty" in out or "constants and thermal coefficients: unchanged" in out


def test_diff_prints_significant_changes_in_engineering_units():
    d = {
        "unit": "U",
        "v1": 1,
        "v2": 2,
        "fields": [],
        "settings": [],
        "inputs": {},
        "significance": {"coverage_factor": 2.0},
        "constants": [
            {
                "name": "K.xx",
                "unit": "V/g",
                "delta": 5.5e-5,
                "delta_scaled": 100.0,
                "scaled_unit": "ppm of gain",
                "uncertainty": 1.1e-6,
                "uncertainty_scaled": 2.0,
                "significant": True,
            },
            {
                "name": "U0.y",
                "unit": "V",
                "delta": 1e-16,
                "delta_scaled": 1.8e-10,
                "scaled_unit": "micro-g",
                "uncertainty": 1e-7,
                "uncertainty_scaled": 0.18,
                "significant": False,
            },
        ],
        "thermal_model": [
            {
                "name": "alpha.x[1]",
                "unit": "V/C^1",
                "delta": 1e-6,
                "delta_scaled": 1.8,
                "scaled_unit": "micro-g/C^1",
                "uncertainty": 1e-8,
                "uncertainty_scaled": 0.018,
                "significant": True,
            }
        ],
    }
    text = "\n".join(diff_lines(d))
    assert re.search(r"K\.xx\s+\+100 ppm of gain \(\+-2, 50\.0 sigma\)\s+SIGNIFICANT", text), text
    assert "U0.y" not in text and "1 more within their uncertainty" in text
    assert "alpha.x[1]" in text and "micro-g/C^1" in text
    assert "U0.y" in "\n".join(diff_lines(d, show_all=True))


def test_output_unit_recorded_and_inferred_for_older_passports(calibrated_registry):
    """A volt passport says V/g and V; one written before ``output_unit`` was recorded gets the unit its gains
    say: gains of about 9.8 per g (a logger recording m/s^2) print as (m/s^2)/g, never V/g."""
    from pipeline.passport.document import output_unit_of
    from pipeline.passport.text import constants_lines

    doc = json.loads(open(calibrated_registry["results"][0]["passport"]).read())
    assert doc["output_unit"] == "V" and output_unit_of(doc) == "V"
    assert "K_ix (V/g)" in "\n".join(constants_lines(doc))
    old = {k: v for k, v in doc.items() if k != "output_unit"}
    assert output_unit_of(old) == "V"
    scale = -9.80665 / 0.55
    mps2 = {
        **old,
        "coefficients": {
            "K": [[k * scale for k in row] for row in doc["coefficients"]["K"]],
            "U0": [u * scale for u in doc["coefficients"]["U0"]],
        },
    }
    assert output_unit_of(mps2) == "m/s^2"
    text = "\n".join(constants_lines(mps2))
    assert "K_ix ((m/s^2)/g)" in text and "U0_i (m/s^2)" in text and "V/g" not in text


def test_one_plateau_and_a_zero_read_as_words_and_plus_zero(calibrated_registry):
    """calibrate's summary of a one-temperature calibration says '1 plateau', and a constant fixed at zero (the
    scalar method's gauge stores -0.0) reads +0.00000000, in the text and the certificate alike."""
    from pipeline.passport.report import certificate_html
    from pipeline.passport.text import calibrate_lines

    res = calibrated_registry["results"][0]
    doc = json.loads(open(res["passport"]).read())
    K = [list(row) for row in doc["coefficients"]["K"]]
    K[0][1] = -0.0
    doc = {**doc, "coefficients": {**doc["coefficients"], "K": K}}
    text = "\n".join(calibrate_lines({**res, "plateaus": res["plateaus"][:1]}, doc))
    assert "  1 plateau: " in text and "-0.00000000" not in text and "+0.00000000" in text
    page = certificate_html(doc, figures={})
    assert "-0.00000000" not in page and "+0.00000000" in page


def test_diff_prints_a_rate_term_in_the_recordings_unit_per_rate():
    """A rate term of a passport in m/s^2 is printed per (C/min)^n/C^k with its unit bracketed, as the thermal
    coefficients are: (m/s^2)/(C/min)^1/C^0, not m/s^2/(C/min)^1/C^0."""
    from pipeline.passport.diff import diff_passports

    def doc(value):
        return {
            "unit": "AU-0001",
            "output_unit": "m/s^2",
            "rate_terms": {"order": 1, "dt_order": 0, "alpha_rate": {"x": [[value]]}},
        }

    d = diff_passports(doc(1.0), doc(3.0), unit="AU-0001", v1=1, v2=2)
    (entry,) = d["rate_terms"]
    assert entry["unit"] == "(m/s^2)/(C/min)^1/C^0" and entry["delta"] == 2.0
    text = "\n".join(diff_lines(d))
    assert "rate_terms.alpha_rate.x[1][0] +2 (m/s^2)/(C/min)^1/C^0" in " ".join(text.split()), text
    assert "m/s^2/(C/min)" not in text
