"""The passport registry: hash chain, idempotent publish, tamper detection, concurrency, write failures, diff."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import RegistryError
from pipeline.passport.registry import Registry, canonical_json, content_sha256, identity_key, sha256_file
from tests.conftest import run_in_child

UNIT = "AU-0001"
INPUTS = [{"path": "runs/a.mcap", "sha256": "a" * 64}, {"path": "runs/b.mcap", "sha256": "b" * 64}]


def make_passport(
    unit: str = UNIT, *, kxy: float = 0.0123, u0z: float = 0.0031, alpha_x2: float = 2.0e-7, status: str = "pass"
) -> dict:
    """A small passport as docs/contract.md describes it (values of seed 000's magnitudes)."""
    return {
        "schema": "thermocal.passport/1",
        "unit": unit,
        "normal_temp_c": 20.0,
        "g_local_mps2": 9.80665,
        "status": status,
        "coefficients": {
            "K": [[-0.55, kxy, -0.004], [0.002, -0.56, 0.016], [-0.001, 0.003, -0.54]],
            "U0": [0.0021, -0.0017, u0z],
        },
        "per_plateau": [
            {
                "temp_c": 20.0,
                "K": [[-0.55, kxy, -0.004], [0.002, -0.56, 0.016], [-0.001, 0.003, -0.54]],
                "U0": [0.0021, -0.0017, u0z],
                "positions": ["TP1", "TP2", "TP3", "TP4", "TP5", "TP6"],
            }
        ],
        "thermal_model": {
            "kind": "polynomial",
            "order": 2,
            "alpha": {"x": [1.1e-4, alpha_x2], "y": [-0.9e-4, 1e-7], "z": [1.2e-4, -3e-7]},
            "beta": {"xx": [1.5e-5, 1e-8], "yy": [2.5e-5, 0.0], "zz": [4.5e-5, -2e-8]},
            "gamma": {k: [1e-4, 1e-6] for k in ("xy", "xz", "yx", "yz", "zx", "zy")},
        },
        "verification": [
            {
                "temp_c": -10.0,
                "position": "VP1",
                "dg_uncompensated_g": 1.2e-3,
                "dg_method1_g": 2.1e-5,
                "dg_method2_g": 2.4e-5,
            }
        ],
        "provenance": {"host": "chamber-3"},
    }


def publish(reg: Registry, settings: dict | None = None, inputs=INPUTS, **kw):
    return reg.publish(
        make_passport(**kw), inputs=inputs, settings=settings or {"thermal_model": "poly2"}, code_version="0.1.0"
    )


def tamper(path: Path, old: bytes, new: bytes) -> None:
    """Change bytes of a (read-only) version file in place, as someone with write access could."""
    data = path.read_bytes()
    assert old in data
    os.chmod(path, 0o644)
    path.write_bytes(data.replace(old, new, 1))


def problems_naming(report, unit: str, version: int) -> list[str]:
    return [p for p in report.problems if p.startswith(f"{unit} v{version}:")]


# ---------------------------------------------------------------------------------------------------------------


def test_publish_chain_and_canonical_file(tmp_path):
    reg = Registry(tmp_path / "reg")
    r1 = publish(reg)
    r2 = publish(reg, settings={"thermal_model": "poly3"})
    assert (r1.version, r1.created, r2.version, r2.created) == (1, True, 2, True)
    assert r1.path == tmp_path / "reg" / "units" / UNIT / "v0001.json"
    assert r1.sha256 == sha256_file(r1.path) and r2.sha256 == sha256_file(r2.path)

    p1, p2 = reg.load(UNIT, 1), reg.load(UNIT)
    assert p1["version"] == 1 and p1["parent_sha256"] is None
    assert p2["version"] == 2 and p2["parent_sha256"] == sha256_file(r1.path)
    # canonical bytes: re-serialising the loaded document gives the file exactly; the self-hash holds
    assert canonical_json(p2) == r2.path.read_bytes()
    assert p2["content_sha256"] == content_sha256(p2)
    prov = p2["provenance"]
    assert prov["inputs"] == INPUTS and prov["settings"] == {"thermal_model": "poly3"}
    assert prov["code_version"] == "0.1.0" and prov["host"] == "chamber-3"
    assert prov["identity"] == identity_key(INPUTS, {"thermal_model": "poly3"})
    assert stat.S_IMODE(r1.path.stat().st_mode) == 0o444
    assert reg.units() == [UNIT]
    assert [(i.version, i.sha256, i.status) for i in reg.versions(UNIT)] == [
        (1, r1.sha256, "pass"),
        (2, r2.sha256, "pass"),
    ]
    rows = reg.log(UNIT)
    assert [r["version"] for r in rows] == [1, 2] and rows[1]["inputs"] == ["runs/a.mcap", "runs/b.mcap"]
    assert rows[0]["created_utc"] <= rows[1]["created_utc"]
    assert reg.verify().ok


def test_same_inputs_and_settings_give_the_existing_version(tmp_path):
    reg = Registry(tmp_path)
    first = publish(reg, settings={"thermal_model": "poly2", "min_soak_s": 600})
    # same input files (other order, other paths) and same settings (other key order): nothing new
    again = publish(
        reg,
        settings={"min_soak_s": 600, "thermal_model": "poly2"},
        inputs=[{"path": "/elsewhere/b.mcap", "sha256": "b" * 64}, {"path": "/elsewhere/a.mcap", "sha256": "a" * 64}],
    )
    assert again.created is False and (again.version, again.sha256, again.path) == (1, first.sha256, first.path)
    assert sorted(p.name for p in (tmp_path / "units" / UNIT).glob("v*.json")) == ["v0001.json"]
    assert len(reg.log(UNIT)) == 1
    # other settings, or other inputs: a new version each
    assert publish(reg, settings={"thermal_model": "poly3", "min_soak_s": 600}).version == 2
    assert publish(reg, settings={"thermal_model": "poly2", "min_soak_s": 600}, inputs=INPUTS[:1]).version == 3
    # back to the first settings: the first version is reported, not a copy of it
    back = publish(reg, settings={"thermal_model": "poly2", "min_soak_s": 600})
    assert (back.version, back.created) == (1, False)
    assert reg.find(UNIT, identity_key(INPUTS, {"thermal_model": "poly3", "min_soak_s": 600})).version == 2
    assert reg.verify().ok


def test_numpy_values_are_stored_as_plain_json(tmp_path):
    reg = Registry(tmp_path)
    p = make_passport()
    p["coefficients"]["K"] = np.array(p["coefficients"]["K"])
    p["normal_temp_c"] = np.float64(20.0)
    r = reg.publish(p, inputs=INPUTS, settings={"order": np.int64(2)}, code_version="x")
    assert reg.load(UNIT)["coefficients"]["K"][0][1] == 0.0123
    assert reg.load(UNIT)["provenance"]["settings"] == {"order": 2}
    bad = make_passport()
    bad["status_score"] = float("nan")
    with pytest.raises(RegistryError, match="not valid JSON"):
        reg.publish(bad, inputs=INPUTS, settings={"x": 1}, code_version="x")
    assert reg.versions(UNIT)[-1].version == r.version == 1


@pytest.mark.parametrize("serial", ["../evil", "a/b", "", "..", ".hidden", "x..y", "a\\b", None, "A" * 101])
def test_unit_serials_that_are_not_safe_names_are_refused(tmp_path, serial):
    reg = Registry(tmp_path / "reg")
    with pytest.raises(RegistryError, match="unit serial"):
        publish(reg, unit=serial)
    assert not (tmp_path / "reg").exists() and not (tmp_path / "evil").exists()


def test_unknown_unit_or_version_is_a_registry_error(tmp_path):
    reg = Registry(tmp_path)
    with pytest.raises(RegistryError, match="unknown unit"):
        reg.load("AU-0404")
    publish(reg)
    with pytest.raises(RegistryError, match="no version 7"):
        reg.load(UNIT, 7)
    with pytest.raises(RegistryError, match="no registry here"):
        Registry(tmp_path / "nope").verify()


# --- integrity --------------------------------------------------------------------------------------------------


def three_versions(tmp_path) -> Registry:
    reg = Registry(tmp_path)
    for order in (1, 2, 3):
        publish(reg, settings={"order": order}, kxy=0.012 + order * 1e-4)
    publish(reg, unit="AU-0002")
    assert reg.verify().ok
    return reg


def test_tampered_middle_version_is_named(tmp_path):
    reg = three_versions(tmp_path)
    tamper(reg.version_path(UNIT, 2), b"0.0122", b"0.0123")  # one digit of K.xy
    report = reg.verify()
    assert not report.ok
    assert problems_naming(report, UNIT, 2)
    # every problem is attributed to the altered version, not to its neighbours or the other unit
    assert all(p.startswith(f"{UNIT} v2:") for p in report.problems), report.problems
    assert any("v3's parent_sha256" in p for p in report.problems)


@pytest.mark.parametrize("recompute_self_hash", [False, True])
def test_tampered_newest_version_is_named(tmp_path, recompute_self_hash):
    reg = three_versions(tmp_path)
    path = reg.version_path(UNIT, 3)
    tamper(path, b'"pass"', b'"fail"')
    if recompute_self_hash:  # a careful forger fixes the stored self-hash too: the log still catches it
        doc = json.loads(path.read_bytes())
        doc["content_sha256"] = content_sha256(doc)
        path.write_bytes(canonical_json(doc))
    report = reg.verify()
    assert not report.ok and problems_naming(report, UNIT, 3)
    assert all(p.startswith(f"{UNIT} v3:") for p in report.problems), report.problems
    assert any("log.jsonl" in p for p in report.problems)
    # the chain is not extended from an altered head
    with pytest.raises(RegistryError, match="v3: file was altered"):
        publish(reg, settings={"order": 4})


def test_deleted_version_is_named(tmp_path):
    reg = three_versions(tmp_path)
    reg.version_path(UNIT, 2).unlink()
    report = reg.verify()
    assert not report.ok and problems_naming(report, UNIT, 2)
    assert any("deleted" in p for p in problems_naming(report, UNIT, 2))
    with pytest.raises(RegistryError, match="v2: version file missing"):
        publish(reg, settings={"order": 4})
    # deleting the newest is caught by the log
    reg.version_path("AU-0002", 1).unlink()
    assert problems_naming(reg.verify(), "AU-0002", 1)


def test_unparsable_version_is_named(tmp_path):
    reg = three_versions(tmp_path)
    path = reg.version_path(UNIT, 1)
    os.chmod(path, 0o644)
    path.write_bytes(path.read_bytes()[:100])
    report = reg.verify()
    assert any("unparsable JSON" in p for p in problems_naming(report, UNIT, 1))
    assert reg.versions(UNIT)[0].status == "unreadable"
    with pytest.raises(RegistryError, match="not valid JSON"):
        reg.load(UNIT, 1)


def test_interrupted_writer_leftovers_are_notes_and_are_cleaned(tmp_path):
    reg = three_versions(tmp_path)
    udir = tmp_path / "units" / UNIT
    # killed before the link: a temp file; killed after the link, before the log row was complete
    (udir / ".tmp-v0004-99999-deadbeef.json").write_bytes(b'{"unit": "AU-0001", "vers')
    log = udir / "log.jsonl"
    lines = log.read_bytes().splitlines(keepends=True)
    log.write_bytes(b"".join(lines[:2]) + lines[2][:30])
    report = reg.verify()
    assert report.ok, report.problems
    assert any("leftover temp file" in n for n in report.notes)
    assert any("v3: not yet in log.jsonl" in n for n in report.notes)
    assert any("unterminated" in n for n in report.notes)
    # the next publish cleans up, records v3 and extends the chain from it
    r4 = publish(reg, settings={"order": 4})
    assert r4.version == 4 and reg.load(UNIT, 4)["parent_sha256"] == sha256_file(reg.version_path(UNIT, 3))
    assert not list(udir.glob(".tmp-*"))
    rows = [json.loads(x) for x in log.read_text().splitlines()]
    assert [r["version"] for r in rows] == [1, 2, 3, 4] and rows[2].get("recovered") is True
    report = reg.verify()
    assert report.ok and not report.notes, report


# --- concurrency --------------------------------------------------------------------------------------------------

WRITER = textwrap.dedent("""
    import sys
    from pipeline.passport.registry import Registry
    root, tag, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    reg = Registry(root)
    for i in range(n):
        p = {"schema": "thermocal.passport/1", "unit": "AU-0001", "status": "pass",
             "coefficients": {"K": [[-0.55, 0, 0], [0, -0.55, 0], [0, 0, -0.55]], "U0": [0.001 * i, 0, 0]}}
        r = reg.publish(p, inputs=[{"path": f"{tag}.mcap", "sha256": tag * 64}], settings={"i": i},
                        code_version="test")
        assert r.created
""")


def test_two_processes_publishing_at_once_keep_a_valid_chain(tmp_path):
    n = 20
    procs = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), tag, str(n)], stderr=subprocess.PIPE, text=True)
        for tag in ("a", "b")
    ]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    reg = Registry(tmp_path)
    infos = reg.versions(UNIT)
    assert [i.version for i in infos] == list(range(1, 2 * n + 1))
    for prev, cur in zip(infos, infos[1:]):
        assert reg.load(UNIT, cur.version)["parent_sha256"] == prev.sha256
    # both writers' publications are all there (each identity exactly once)
    tags = [reg.load(UNIT, i.version)["provenance"]["inputs"][0]["path"] for i in infos]
    assert sorted(tags) == ["a.mcap"] * n + ["b.mcap"] * n
    report = reg.verify()
    assert report.ok and not report.notes, report


# --- write failures -----------------------------------------------------------------------------------------------


def test_unit_folder_blocked_by_a_file_is_a_clean_error(tmp_path):
    # really fails, even as root: the unit's folder is a file
    (tmp_path / "units").mkdir()
    (tmp_path / "units" / UNIT).write_text("not a folder")
    with pytest.raises(RegistryError) as exc:
        publish(Registry(tmp_path))
    msg = str(exc.value)
    assert "\n" not in msg and str(tmp_path / "units" / UNIT) in msg
    assert sorted(p.name for p in (tmp_path / "units").iterdir()) == [UNIT]
    # a registry root that is a file
    (tmp_path / "file").write_text("x")
    with pytest.raises(RegistryError, match="not a directory"):
        publish(Registry(tmp_path / "file"))


def run_unprivileged(fn) -> None:
    """Run ``fn`` as an ordinary user: as is, or (as root, who writes through chmod) in a child that drops to nobody."""
    if os.geteuid() != 0:
        fn()
        return

    def drop_to_nobody():
        os.setgid(65534)
        os.setuid(65534)

    run_in_child(fn, drop_to_nobody, "the unprivileged check")


def test_read_only_registry_is_a_clean_error(monkeypatch):
    base = Path(tempfile.mkdtemp(prefix="thermocal-ro-", dir="/tmp" if Path("/tmp").is_dir() else None))
    os.chmod(base, 0o777)  # reachable by the unprivileged child
    monkeypatch.setenv("THERMOCAL_KEY_DIR", str(base / "keys"))  # a station key the unprivileged user owns

    def check():
        reg = Registry(base / "reg")
        publish(reg)
        udir = base / "reg" / "units" / UNIT
        os.chmod(udir, 0o555)
        with pytest.raises(RegistryError, match="permission denied") as exc:
            publish(reg, settings={"other": 1})
        assert str(udir) in str(exc.value) and "\n" not in str(exc.value)
        assert sorted(p.name for p in udir.iterdir()) == [".lock", "log.jsonl", "v0001.json"]
        report = reg.verify()  # reading needs no write access
        assert report.ok and not report.notes
        os.chmod(base / "reg" / "units", 0o555)
        with pytest.raises(RegistryError, match="permission denied"):
            publish(reg, unit="AU-0002")
        os.chmod(base / "reg" / "units", 0o755)
        os.chmod(udir, 0o755)

    try:
        run_unprivileged(check)
    finally:
        shutil.rmtree(base)


FULL_DISK = textwrap.dedent("""
    import resource, signal, sys
    from pipeline.errors import RegistryError
    from pipeline.passport.registry import Registry
    root, limit, pad = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)          # write() then fails with EFBIG, as on a full disk
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    p = {"schema": "thermocal.passport/1", "unit": "AU-0001", "note": "x" * pad}
    try:
        Registry(root).publish(p, inputs=[], settings={"late": 1}, code_version="test")
    except RegistryError as exc:
        print(exc)
        sys.exit(3)
""")


@pytest.mark.parametrize("where", ["version file", "log row"])
def test_a_failed_write_leaves_nothing_partial(tmp_path, where):
    reg = Registry(tmp_path)
    for i in range(8):
        publish(reg, settings={"i": i})
    udir = tmp_path / "units" / UNIT
    log_bytes = (udir / "log.jsonl").read_bytes()
    if where == "version file":  # a big passport on a small quota: the version file write fails
        limit, pad = 4096, 20_000
    else:  # a small passport fits, the log (already bigger than the quota) cannot grow: the version is taken back
        limit, pad = len(log_bytes), 0
    proc = subprocess.run(
        [sys.executable, "-c", FULL_DISK, str(tmp_path), str(limit), str(pad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 3, proc.stderr
    assert "file too large" in proc.stdout and len(proc.stdout.strip().splitlines()) == 1
    assert sorted(p.name for p in udir.iterdir()) == [".lock", "log.jsonl"] + [f"v{i:04d}.json" for i in range(1, 9)]
    assert (udir / "log.jsonl").read_bytes() == log_bytes
    report = reg.verify()
    assert report.ok and not report.notes, report
    assert publish(reg, settings={"late": 1}).version == 9


# --- diff ---------------------------------------------------------------------------------------------------------


def test_diff_reports_changed_constants_in_physical_units(tmp_path):
    reg = Registry(tmp_path)
    publish(reg, settings={"thermal_model": "poly2"})
    # K.xy +1.1e-5 V/g, U0.z +5.4e-6 V, alpha_x order 2 +1e-7 V/C^2, status pass -> fail, new settings and inputs
    publish(
        reg,
        settings={"thermal_model": "poly2", "min_soak_s": 900},
        inputs=INPUTS[:1] + [{"path": "runs/c.mcap", "sha256": "c" * 64}],
        kxy=0.0123 + 1.1e-5,
        u0z=0.0031 + 5.4e-6,
        alpha_x2=3.0e-7,
        status="fail",
    )
    d = reg.diff(UNIT, 1, 2)
    by_name = {e["name"]: e for e in d["constants"]}
    assert set(by_name) == {"K.xy", "U0.z"}
    assert by_name["K.xy"]["delta"] == pytest.approx(1.1e-5, rel=1e-9)
    assert by_name["K.xy"]["delta_scaled"] == pytest.approx(20.0, rel=1e-6)  # 1.1e-5 / 0.55 = 20 ppm of Kxx
    assert by_name["K.xy"]["scaled_unit"] == "ppm of gain" and by_name["K.xy"]["old"] == 0.0123
    assert by_name["U0.z"]["delta_scaled"] == pytest.approx(10.0, rel=1e-6)  # 5.4e-6 V / 0.54 V/g = 10 micro-g
    assert by_name["U0.z"]["unit"] == "V" and by_name["U0.z"]["scaled_unit"] == "micro-g"
    [alpha] = d["thermal_model"]
    assert alpha["name"] == "alpha.x[2]" and alpha["unit"] == "V/C^2"
    assert alpha["delta"] == pytest.approx(1e-7) and alpha["delta_scaled"] == pytest.approx(1e-7 / 0.55 * 1e6)
    assert {f["name"]: (f["old"], f["new"]) for f in d["fields"]} == {"status": ("pass", "fail")}
    assert d["settings"] == [{"name": "min_soak_s", "old": None, "new": 900}]
    assert d["inputs"] == {
        "added": [{"path": "runs/c.mcap", "sha256": "c" * 64}],
        "removed": [{"path": "runs/b.mcap", "sha256": "b" * 64}],
    }
    # a version compared with itself has no difference
    same = reg.diff(UNIT, 2, 2)
    assert not (same["constants"] or same["thermal_model"] or same["fields"] or same["settings"])


def test_diff_of_piecewise_models_and_of_a_model_change(tmp_path):
    reg = Registry(tmp_path)

    def seg(a, b):
        return {
            "alpha": {"x": a, "y": 0.0, "z": 0.0},
            "beta": {"xx": b, "yy": 0.0, "zz": 0.0},
            "gamma": dict.fromkeys(("xy", "xz", "yx", "yz", "zx", "zy"), 0.0),
        }

    def pw(a2):
        return {
            "kind": "piecewise_linear",
            "breakpoints_c": [-40.0, 20.0, 70.0],
            "segments": [
                {"t_lo_c": -40.0, "t_hi_c": 20.0, **seg(1e-4, 2e-5)},
                {"t_lo_c": 20.0, "t_hi_c": 70.0, **seg(a2, 2e-5)},
            ],
        }

    for i, model in enumerate([pw(1.1e-4), pw(1.3e-4)]):
        p = make_passport()
        p["thermal_model"] = model
        reg.publish(p, inputs=INPUTS, settings={"i": i}, code_version="0.1.0")
    d = reg.diff(UNIT, 1, 2)
    [e] = d["thermal_model"]
    assert e["name"] == "segments[1].alpha.x" and e["unit"] == "V/C"
    assert e["delta"] == pytest.approx(2e-5) and e["delta_scaled"] == pytest.approx(2e-5 / 0.55 * 1e6)
    # polynomial (v3) against piecewise (v2): the kind change is reported, not element-wise nonsense
    reg.publish(make_passport(), inputs=INPUTS, settings={"i": 2}, code_version="0.2.0")
    d = reg.diff(UNIT, 2, 3)
    names = {f["name"] for f in d["fields"]}
    assert {
        "thermal_model.kind",
        "thermal_model.order",
        "thermal_model.breakpoints_c",
        "provenance.code_version",
    } <= names
    assert d["thermal_model"] == []
