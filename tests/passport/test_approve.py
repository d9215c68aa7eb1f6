"""Approval records and the current passport (pipeline/passport/registry.py): an approval is a signed record of its
own (the version is not changed); the newest approved version is the unit's current passport, else the newest that
did not fail (a failed calibration is never current); verify checks approvals; a failed calibration cannot be
approved; a dry run's plan writes nothing."""

from __future__ import annotations

import json

import pytest

from pipeline.errors import RegistryError
from pipeline.passport.registry import Registry
from pipeline.passport.signing import verify_record
from tests.passport.test_registry import make_passport

UNIT = "AU-0001"


def _publish(reg: Registry, n: int, status: str = "pass"):
    doc = make_passport(UNIT, kxy=0.01 + n * 1e-4)
    doc["status"] = status
    return reg.publish(doc, inputs=[{"path": f"r{n}.mcap", "sha256": f"{n:064x}"}], settings={}, code_version="t")


@pytest.fixture
def reg(tmp_path):
    r = Registry(tmp_path / "reg")
    for n, status in enumerate(("pass", "pass", "fail"), start=1):
        _publish(r, n, status)
    return r


def test_current_is_newest_approved_else_newest_not_failed(reg):
    assert reg.current(UNIT) == 2  # nothing approved: the newest that did not fail (v3 failed)
    doc, st = reg.load_state(UNIT)
    assert doc["version"] == 2 and st.current and st.verification.verified
    before = reg.version_path(UNIT, 1).read_bytes()
    rec = reg.approve(UNIT, 1, "A. Metrologist")
    assert reg.version_path(UNIT, 1).read_bytes() == before  # approval does not change the version
    assert rec["version"] == 1 and rec["by"] == "A. Metrologist" and rec["schema"] == "thermocal.approval/1"
    assert verify_record(rec).ok
    assert reg.current(UNIT) == 1
    doc, st = reg.load_state(UNIT)
    assert doc["version"] == 1 and st.approved and st.version == 1
    reg.approve(UNIT, 2, "B. Checker")
    assert reg.current(UNIT) == 2
    assert reg.approve(UNIT, 2, "B. Checker") == reg.approvals(UNIT)[-1]  # idempotent: same record back
    log = {r["version"]: r for r in reg.log(UNIT)}
    assert [a["by"] for a in log[2]["approved"]] == ["B. Checker"] and log[2]["current"]
    assert log[3]["approved"] == [] and not log[3]["current"]
    assert reg.verify().ok


def test_a_unit_whose_every_version_failed_has_no_current_passport(tmp_path):
    r = Registry(tmp_path / "reg")
    _publish(r, 1, "fail")
    assert r.current(UNIT) is None and r.state(UNIT) is None
    with pytest.raises(RegistryError, match="no current passport") as info:
        r.load_state(UNIT)
    assert "\n" not in str(info.value)
    doc, st = r.load_state(UNIT, 1)  # named: it is used (and says it failed)
    assert doc["status"] == "fail" and not st.current and "failed its verification" in st.warning()


def test_failed_or_unknown_version_cannot_be_approved(reg):
    with pytest.raises(RegistryError, match="status fail"):
        reg.approve(UNIT, 3, "A. Metrologist")
    with pytest.raises(RegistryError, match="no version 9"):
        reg.approve(UNIT, 9, "A. Metrologist")
    with pytest.raises(RegistryError, match="--by"):
        reg.approve(UNIT, 1, "  ")
    assert not (reg.unit_dir(UNIT) / "approvals.jsonl").exists()


def test_verify_names_a_forged_or_altered_approval(reg):
    reg.approve(UNIT, 1, "A. Metrologist")
    path = reg.unit_dir(UNIT) / "approvals.jsonl"
    rec = json.loads(path.read_text().splitlines()[0])
    forged = dict(rec, version=2, sha256=reg.versions(UNIT)[1].sha256)  # moved to another version
    path.write_text(path.read_text() + json.dumps(forged) + "\n")
    report = reg.verify()
    assert not report.ok and any("approval of v2" in p and "altered" in p for p in report.problems)
    assert reg.current(UNIT) == 1  # the forged record does not count


def test_planned_writes_nothing(reg, tmp_path):
    doc = make_passport(UNIT, kxy=0.02)
    files = sorted(p.name for p in reg.unit_dir(UNIT).iterdir())
    assert reg.planned(doc, inputs=[{"path": "x", "sha256": "9" * 64}], settings={}) == (4, False)
    assert reg.planned(doc, inputs=[{"path": "r2.mcap", "sha256": f"{2:064x}"}], settings={}) == (2, True)
    assert sorted(p.name for p in reg.unit_dir(UNIT).iterdir()) == files
    assert Registry(tmp_path / "none").planned(doc, inputs=[], settings={}) == (1, False)
    assert not (tmp_path / "none").exists()
