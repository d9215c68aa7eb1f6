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
