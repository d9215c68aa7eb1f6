"""No internal error on a malformed passport (issue 26 item 6): every command that reads one ends each passport of
the corpus (tests/acceptance/malformed_passports.py: singular K, deep nesting, order 10^6, wrong types, NaN) in one
line and exit 2, as a loose file with --unverified and as a signed version of a registry; the registry commands
(verify, log, show, diff) never crash on one."""

from __future__ import annotations

import pytest

from pipeline.errors import ThermocalError
from pipeline.io.runs import write_run
from pipeline.passport.registry import Registry
from pipeline.passport.verification import check_content
from pipeline.simulate.chamber import SimConfig, simulate
from tests.acceptance.malformed_passports import CORPUS, file_bytes, good_passport, malformed
from tests.conftest import run_main


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    run = simulate(SimConfig(program="short", rate_hz=0.5, seed=3, unit_serial="AU-0701")).run
    return write_run(run, tmp_path_factory.mktemp("run") / "r.mcap", "mcap")


def _one_line_exit_2(monkeypatch, capsys, *args, or_used: bool = False):
    code, out, err = run_main(monkeypatch, capsys, *args)
    if or_used and code == 0:
        return ""
    assert code == 2 and out == "", (args, code, out[:200], err)
    assert err.count("\n") == 1 and err.startswith("thermocal: error: "), (args, err)
    return err


@pytest.mark.parametrize("m", CORPUS, ids=lambda m: m.name)
def test_loose_malformed_passport_is_one_line(m, run_file, tmp_path, monkeypatch, capsys):
    bad = tmp_path / "bad.json"
    bad.write_bytes(file_bytes(m))
    monkeypatch.chdir(tmp_path)
    commands = [
        ("export", str(bad), "--format", "px4", "--unverified"),
        ("export", str(bad), "--format", "csv", "--unverified"),
        ("report", str(bad), "--out", "x.html", "--unverified"),
    ]
    if not m.usable:  # (a usable one would run them to the end: slow, and not the point here)
        commands += [
            ("apply", str(bad), str(run_file), "--out", "x.parquet", "--unverified"),
            ("diagnose", str(run_file), "--passport", str(bad), "--unverified", "--json"),
        ]
    for args in commands:
        err = _one_line_exit_2(monkeypatch, capsys, *args, or_used=m.usable)
        assert not err or str(bad) in err
    err = _one_line_exit_2(monkeypatch, capsys, "apply", str(bad), str(run_file), "--out", "y.parquet")
    assert str(bad) in err  # not signed: refused before anything else
    if not m.usable:
        assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json"]


@pytest.mark.parametrize("m", [m for m in CORPUS if m.raw is None], ids=lambda m: m.name)
def test_signed_malformed_version_in_a_registry(m, tmp_path, monkeypatch, capsys):
    reg = Registry(tmp_path / "reg")
    reg.publish(good_passport(), inputs=[{"path": "a", "sha256": "a" * 64}], settings={}, code_version="t")
    try:
        reg.publish(malformed(m), inputs=[{"path": "b", "sha256": "b" * 64}], settings={}, code_version="t")
    except (ThermocalError, RecursionError):
        pytest.skip("the registry does not write this content")
    try:
        check_content(reg.load("AU-0701", 2))
    except ThermocalError:
        pass
    else:
        pytest.skip("the registry rewrites the malformed field when it publishes")
    root = str(reg.root)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    for args in (
        ("export", "AU-0701", "2", "--registry", root, "--format", "ardupilot"),
        ("report", "AU-0701", "2", "--registry", root, "--out", "x.html"),
        ("passport", "show", "AU-0701", "2", "--registry", root),
        ("passport", "diff", "AU-0701", "1", "2", "--registry", root),
    ):
        err = _one_line_exit_2(monkeypatch, capsys, *args, or_used=m.usable)
        assert not err or "malformed passport" in err or "AU-0701" in err, err
    for args in (("passport", "log", "AU-0701", "--registry", root), ("passport", "verify", "--registry", root)):
        code, out, err = run_main(monkeypatch, capsys, *args)
        assert code in (0, 1) and "internal error" not in err, (args, err)


_SEGMENT = {
    "alpha": {"x": 1e-4, "y": 1e-4, "z": 1e-4},
    "beta": {"xx": 1e-5, "yy": 1e-5, "zz": 1e-5},
    "gamma": {k: 0.0 for k in ("xy", "xz", "yx", "yz", "zx", "zy")},
}
_K = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
_RATE = {
    "order": 1,
    "dt_order": 0,
    "temp_smooth_s": 60.0,
    "alpha_rate": {"x": [[1.0]], "y": [1.0], "z": [[1.0]]},
    "beta_rate": {"xx": [1.0], "yy": [1.0], "zz": [1.0]},
}


def _piecewise(**change) -> dict:
    model = {"kind": "piecewise_linear", "breakpoints_c": [-40.0, 20.0, 70.0], "segments": [_SEGMENT, _SEGMENT]}
    return {"thermal_model": {**model, **change}}


@pytest.mark.parametrize(
    ("change", "field_and_reason"),
    [
        (
            _piecewise(segments=[_SEGMENT, {**_SEGMENT, "alpha": {"x": 1e-4, "y": 1e-4, "z": "a"}}]),
            "thermal_model.segments[1].alpha.z: a string where a number belongs",
        ),
        (_piecewise(breakpoints_c=[-40.0, 70.0, 20.0]), "thermal_model.breakpoints_c: not increasing"),
        (_piecewise(segments=[_SEGMENT]), "thermal_model.segments: 1 segments for 3 breakpoints"),
        (
            {"rate_terms": {**_RATE, "beta_rate": {"xx": [1.0], "yy": [1.0], "zz": [["b"]]}}},
            "rate_terms.beta_rate.zz[0]: a list where a number belongs",
        ),
        (
            {"rate_terms": {**_RATE, "cross_axis_abs": {"xy": [1.0], "xz": [None]}}},
            "rate_terms.cross_axis_abs.xz[0]: null where a number belongs",
        ),
        (
            {
                "verification": [
                    {"temp_c": 20.0, "position": "+x"},
                    {"temp_c": 2.0, "position": "+y", "dg_method1_g": "x"},
                ]
            },
            "verification[1].dg_method1_g: a string where a number belongs",
        ),
        ({"coefficients": {"K": _K}}, "coefficients: field 'U0' is missing"),
        (
            {"uncertainty": {"coefficients": {"K": [[0.1, 0.1, 0.1], [0.1, 0.1, "s"], [0.1, 0.1, 0.1]]}}},
            "uncertainty.coefficients.K[1][2]: a string where a number belongs",
        ),
        (
            {"uncertainty": {"thermal_model": {"alpha": {"x": [0.1], "y": ["s"]}}}},
            "uncertainty.thermal_model.alpha.y[0]: a string where a number belongs",
        ),
        (
            {"provenance": {"inputs": [{"path": "a"}, {"path": "b", "sha256": 5}]}},
            "provenance.inputs[1].sha256: a number where a string belongs",
        ),
        (
            {"per_plateau": [{"temp_c": 20.0, "K": _K, "U0": [0.0, 0.0]}]},
            "per_plateau[0].U0: 2 entries, expected exactly 3",
        ),
        (
            {
                "thermal_model": {
                    "kind": "polynomial",
                    "order": 2,
                    "alpha": {"x": [1.0, 2.0], "y": [1.0], "z": [1.0, 2.0]},
                }
            },
            "thermal_model.alpha.y: 1 entries, expected exactly 2",
        ),
        (
            {"uncertainty": {"undetermined": {"K.xy": 3}}},
            "uncertainty.undetermined.K.xy: a number where a string belongs",
        ),
    ],
)
def test_a_malformed_field_is_named_by_its_whole_path(change, field_and_reason):
    """The path of a bad field deep in lists and objects (the checks build it only when a field fails)."""
    doc = {**good_passport(), **change}
    with pytest.raises(ThermocalError) as err:
        check_content(doc, "AU-0701 v1")
    assert str(err.value) == f"AU-0701 v1: malformed passport: {field_and_reason}"
