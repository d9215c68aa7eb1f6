"""The tampered-registry corpus (issue 15): every attack is named by ``passport verify`` (with ``--against`` an
earlier head statement for rollbacks and deletions), the next publish to a damaged unit is refused in one line,
and the refusal loses or alters nothing; calibrate and fleet refuse a forged chain end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipeline.errors import RegistryError
from pipeline.passport.canonical import content_sha256
from pipeline.passport.registry import Registry
from pipeline.passport.signing import sign_record, station_key
from tests.acceptance import tampered
from tests.acceptance.tampered import ATTACKS, UNITS, Attack, build_base, snapshot
from tests.conftest import run_main

pytestmark = pytest.mark.slow  # an end-to-end proof on long or many recordings

ATTACK_BY_NAME = {a.name: a for a in ATTACKS}


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return build_base(tmp_path_factory.mktemp("tampered"))


def attacked(base, tmp_path: Path, attack: Attack) -> Path:
    root, _ = base
    copy = tmp_path / "registry"
    shutil.copytree(root, copy)
    attack.apply(copy)
    return copy


def named(report, unit: str, version: int | None, fragment: str) -> bool:
    head = f"{unit} v{version}:" if version is not None else f"{unit}:"
    return any(p.startswith(head) and fragment in p for p in report.problems)


def test_clean_registry_verifies_with_and_without_its_head_statement(base):
    root, head = base
    reg = Registry(root)
    assert reg.verify().ok
    report = reg.verify(against=json.loads(head.read_bytes()))
    assert report.ok and not report.problems, report.problems


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda a: a.name)
def test_attack_is_named_and_refused_without_loss(base, tmp_path, attack):
    root = attacked(base, tmp_path, attack)
    reg = Registry(root)
    against = json.loads(base[1].read_bytes()) if attack.against else None
    report = reg.verify(against=against)
    assert not report.ok
    for unit, version, fragment in attack.names:
        assert named(report, unit, version, fragment), (attack.name, report.problems)
    assert all("\n" not in p for p in report.problems)
    if attack.refuses is None:
        return
    before = snapshot(root)
    with pytest.raises(RegistryError) as info:
        tampered.publish(reg, attack.refuses, 50)
    line = str(info.value)
    assert "\n" not in line and "refusing to append" in line or "is not this station's own signed version" in line
    assert attack.refuses in line
    assert snapshot(root) == before  # nothing lost, nothing altered, nothing adopted


def test_figures_attacks_tried_and_named(base, tmp_path_factory, capsys):
    """The figures of the closing note: every attack of the corpus is named, none is let through."""
    tried = named_count = 0
    for attack in ATTACKS:
        root = attacked(base, tmp_path_factory.mktemp(attack.name), attack)
        against = json.loads(base[1].read_bytes()) if attack.against else None
        report = Registry(root).verify(against=against)
        tried += 1
        named_count += all(named(report, u, v, f) for u, v, f in attack.names)
    with capsys.disabled():
        print(f"\ntampered registries: {tried} attacks tried, {named_count} named")
    assert named_count == tried == len(ATTACKS) >= 12


def test_rollback_is_invisible_without_a_head_statement(base, tmp_path):
    """What a head statement is for: a rollback leaves a consistent, shorter chain that verify alone accepts."""
    root = attacked(base, tmp_path, ATTACK_BY_NAME["rollback-newest"])
    assert Registry(root).verify().ok


def test_head_statement_tampering_is_named(base, tmp_path):
    root, head_file = base
    head = json.loads(head_file.read_bytes())
    edited = {**head, "units": {**head["units"], UNITS[0]: {**head["units"][UNITS[0]], "version": 2}}}
    report = Registry(root).verify(against=edited)
    assert any(p.startswith("head statement of") and "altered" in p for p in report.problems), report.problems
    rehashed = {k: v for k, v in edited.items() if k != "signature"}
    rehashed["content_sha256"] = content_sha256(rehashed)
    report = Registry(root).verify(against=sign_record(rehashed, station_key(tmp_path / "attacker")))
    assert any("which this station does not trust" in p for p in report.problems), report.problems


def test_cli_verify_head_and_against(base, tmp_path, monkeypatch, capsys):
    root, head = base
    code, out, _ = run_main(
        monkeypatch, capsys, "passport", "head", "--registry", str(root), "--out", str(tmp_path / "h.json")
    )
    assert code == 0 and json.loads(out)["units"] == json.loads(head.read_bytes())["units"]
    assert (tmp_path / "h.json").read_text() == out
    copy = attacked(base, tmp_path, ATTACK_BY_NAME["delete-unit-folder"])
    code, out, err = run_main(monkeypatch, capsys, "passport", "verify", "--registry", str(copy), "--json")
    assert code == 0, err  # the deletion is invisible to the registry alone...
    code, out, err = run_main(
        monkeypatch, capsys, "passport", "verify", "--registry", str(copy), "--against", str(head), "--json"
    )
    assert code == 1  # ...and named against the head statement
    problems = json.loads(out)["problems"]
    assert [p.split(":")[0] for p in problems] == [f"{UNITS[1]} v{v}" for v in (1, 2, 3)]
    forged = attacked(base, tmp_path / "f", ATTACK_BY_NAME["forged-version-unsigned"])
    code, out, err = run_main(monkeypatch, capsys, "passport", "head", "--registry", str(forged))
    assert code == 2 and out == ""  # no signed statement vouches for a forged version
    [line] = err.splitlines()
    assert "no head statement signed" in line and f"{UNITS[0]} v4" in line


def test_calibrate_and_fleet_refuse_a_forged_chain(tmp_path, monkeypatch, capsys):
    """End to end: a calibrated unit, a forged next version in its folder; calibrate exits 2 with one line and
    fleet lists the unit's run as failed with that reason; nothing in the registry changes."""
    from pipeline.io.runs import write_run
    from pipeline.simulate.chamber import SimConfig
    from pipeline.simulate.large import simulate_run

    run = simulate_run(SimConfig(program="short", rate_hz=2.0, seed=5, unit_serial="AU-0310")).run
    inbox = tmp_path / "inbox"
    path = write_run(run, inbox / "tp.mcap", "mcap")
    reg = tmp_path / "reg"
    code, out, err = run_main(monkeypatch, capsys, "calibrate", str(path), "--registry", str(reg), "--json")
    assert code == 0 and json.loads(out)["version"] == 1, err
    tampered.forged_unsigned(reg, "AU-0310")
    before = snapshot(reg)
    code, out, err = run_main(
        monkeypatch, capsys, "calibrate", str(path), "--registry", str(reg), "--thermal-model", "poly1"
    )
    assert code == 2 and out == ""
    [line] = [x for x in err.splitlines() if x.startswith("thermocal:")]
    assert "AU-0310 v2" in line and "not this station's own signed version" in line
    from flows.fleet import run_fleet
    from pipeline.calibrate.settings import CalibrationSettings

    # (with the same settings the fleet skips the run as already processed: nothing is appended either way)
    summary = run_fleet(str(inbox), str(reg), CalibrationSettings(thermal_model="poly1"), pool="thread", workers=1)
    [failed] = summary["failed"]
    assert failed["run"] == str(path.resolve()) and "AU-0310 v2" in failed["reason"] and not summary["done"]
    assert snapshot(reg) == before
