"""The tampered-registry corpus (issue 15): every attack is named by ``passport verify`` (with ``--against`` an
earlier head statement for rollbacks and deletions), the next publish to a damaged unit is refused in one line,
and the refusal loses or alters nothing; calibrate and fleet refuse a forged chain end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipeline.errors import RegistryError, ThermocalError
from pipeline.passport.canonical import content_sha256
from pipeline.passport.registry import Registry
from pipeline.passport.signing import sign_record, station_key
from pipeline.passport.verification import UntrustedPassport
from tests.acceptance import tampered
from tests.acceptance.tampered import ATTACKS, UNITS, VERSIONS, Attack, build_base, snapshot
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


@pytest.mark.parametrize("attack", [a for a in ATTACKS if a.refuses], ids=lambda a: a.name)
def test_attacked_unit_is_not_used_by_any_consumer(base, tmp_path, attack):
    """Issue 26: the one path every consumer reads a registry's passport by (Registry.load_state: export, report,
    diagnose --registry, the differential base) refuses the attacked unit's current passport in one line; with
    ``unverified`` it is used and its state says so; the other unit is untouched and verified."""
    root = attacked(base, tmp_path, attack)
    reg = Registry(root)
    with pytest.raises(UntrustedPassport) as info:
        reg.load_state(attack.refuses)
    line = info.value.one_line()
    assert "\n" not in line and "is not used" in line and "--unverified" in line, line
    try:
        doc, st = reg.load_state(attack.refuses, unverified=True)
    except ThermocalError as exc:  # the forged bytes are not a record at all: never used
        assert "not a passport record" in exc.one_line()
    else:
        assert not st.verification.verified and "UNVERIFIED" in st.text() and st.as_dict()["verification"]["problem"]
    other = next(u for u in UNITS if u != attack.refuses)
    doc, st = reg.load_state(other)
    assert st.verification.verified and doc["unit"] == other
    histories, problems = reg.verified_versions(attack.refuses)
    assert problems and len(histories) < VERSIONS + 1


CONSUMED = ("thermal-x10-newest-stale-hashes", "forged-version-unsigned", "duplicate-keys-prepended")


@pytest.mark.parametrize("name", CONSUMED)
def test_commands_refuse_an_altered_passport_in_one_line(base, tmp_path, monkeypatch, capsys, name):
    """Issue 26 item 1, end to end: export, report, apply and diagnose refuse the attacked unit's passport (exit 2,
    one line, nothing written); with --unverified the readable ones are used and every output says UNVERIFIED."""
    root = attacked(base, tmp_path, ATTACK_BY_NAME[name])
    unit = UNITS[0]
    newest = max((root / "units" / unit).glob("v[0-9]*.json"))
    run = Path(__file__).resolve().parents[2] / "sample_data" / "standard_short.mcap"
    monkeypatch.chdir(tmp_path)
    commands = {
        "export": ("export", unit, "--registry", str(root), "--format", "px4", "--out", "x.params"),
        "report": ("report", unit, "--registry", str(root), "--out", "x.html"),
        "apply": ("apply", str(newest), str(run), "--out", "x.parquet"),
        "diagnose": ("diagnose", str(run), "--passport", str(newest), "--json"),
    }
    before = snapshot(root)
    for what, args in commands.items():
        code, out, err = run_main(monkeypatch, capsys, *args)
        assert (code, out) == (2, ""), (what, code, err)
        [line] = err.splitlines()
        assert line.startswith("thermocal: error: ") and unit in line and "--unverified" in line, (what, line)
    assert not any(Path(f).exists() for f in ("x.params", "x.html", "x.parquet")) and snapshot(root) == before
    if name == "duplicate-keys-prepended":  # which of the two readings? none: not used even --unverified
        code, out, err = run_main(monkeypatch, capsys, *commands["export"], "--unverified")
        assert code == 2 and "not a passport record" in err and not Path("x.params").exists()
        return
    for extra in ((), ("--json",)):  # the audit view shows it, and says on stderr that it does not verify
        code, out, err = run_main(monkeypatch, capsys, "passport", "show", unit, "--registry", str(root), *extra)
        [line] = err.splitlines()
        assert code == 0 and line.startswith(f"thermocal: warning: {unit} v") and "DOES NOT VERIFY" in line, err
    code, out, err = run_main(monkeypatch, capsys, *commands["export"], "--unverified", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["passport_used"]["verification"]["verified"] is False
    assert "UNVERIFIED" in Path("x.params").read_text() and "UNVERIFIED" in err
    # the hash the header names is the one the file claims, said so (it named it as the passport's own)
    stored = str(json.loads(newest.read_text())["content_sha256"])[:16]
    assert (
        f"passport v{newest.stem[1:].lstrip('0')} (content_sha256 as stored, unverified {stored})"
        in Path("x.params").read_text()
    )
    code, out, err = run_main(monkeypatch, capsys, *commands["report"], "--unverified")
    assert code == 0 and "UNVERIFIED" in out and "UNVERIFIED" in Path("x.html").read_text(), err
    code, out, err = run_main(monkeypatch, capsys, *commands["apply"], "--unverified", "--json")
    assert code == 0 and json.loads(out)["passport"]["verification"]["verified"] is False, err
    import polars as pl

    assert "UNVERIFIED" in pl.read_parquet_metadata("x.parquet")["thermocal.passport_verification"]
    assert snapshot(root) == before


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
