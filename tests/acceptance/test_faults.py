"""Faults (issue 7) through the calibration's write path, ``pipeline.calibrate.publish.publish``: a calibration
killed (SIGKILL) at random moments leaves a registry that ``passport verify`` accepts and loses or alters no earlier
version, nor leaves a partial figure; two processes calibrating the same unit at once both finish; a full disk or a
read-only registry gives a one-line error and writes nothing partial.

tests/test_registry.py covers the registry's own publish under the same faults; here the whole calibration write
(passport, registry, figure) is hit, and the disk is really full or read-only where this machine lets us mount a
tmpfs (as root), else it falls back to a file-size limit and an unprivileged user.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest

from pipeline.calibrate import tilt
from pipeline.calibrate.publish import publish as publish_result
from pipeline.calibrate.settings import CalibrationSettings
from pipeline.errors import RegistryError
from pipeline.io.runs import write_run
from pipeline.passport.registry import Registry, sha256_file
from tests.acceptance.badcorpus import valid
from tests.conftest import run_in_child

pytestmark = pytest.mark.slow  # processes killed, disks filled, two writers at once

UNIT = "BAD-00"
THERMOCAL = str(Path(sys.executable).parent / "thermocal")
PNG_END = b"IEND\xaeB`\x82"
KILLS = 16


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    """The valid run on disk (MCAP and Parquet) and its calibration, pickled for child processes."""
    d = tmp_path_factory.mktemp("faults")
    run = valid().run
    paths = [write_run(run, d / "run.mcap"), write_run(run, d / "run_parquet", "parquet")]
    result = tilt.calibrate([run])
    assert result.unit == UNIT
    state = d / "calibration.pickle"
    state.write_bytes(pickle.dumps((result, str(paths[0]))))
    return {"state": state, "paths": paths, "result": result}


def publish(calibration, registry: Path, k: int = 0, input_path: Path | None = None, **kw) -> dict:
    """The calibration's write step; ``k`` varies the settings, so each k is a new version."""
    c = calibration
    return publish_result(
        registry,
        c["result"],
        input_paths=[str(input_path or c["paths"][0])],
        settings=CalibrationSettings(cluster_tol_c=3.0 + k * 1e-3),
        **kw,
    )


def snapshot(registry: Path) -> dict[str, str]:
    """sha256 of every file in the unit's folder (versions, log, figures)."""
    udir = registry / "units" / UNIT
    return {p.name: sha256_file(p) for p in sorted(udir.iterdir()) if p.is_file()} if udir.is_dir() else {}


def assert_registry_sound(registry: Path, before: dict[str, str]) -> dict[str, str]:
    """verify finds no problem, no earlier version or figure is lost or altered, every figure is a whole PNG."""
    report = Registry(registry).verify()
    assert report.ok, report.problems
    now = snapshot(registry)
    for name, digest in before.items():
        if name.startswith("v"):
            assert now.get(name) == digest, f"{name} lost or altered"
    udir = registry / "units" / UNIT
    for png in udir.glob("v*.png"):
        assert png.read_bytes().endswith(PNG_END), f"partial figure {png.name}"
    return now


# --- kill -9 ------------------------------------------------------------------------------------------------------

ZYGOTE = textwrap.dedent("""
    import os, pickle, signal, sys
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.calibrate.publish import publish
    from pipeline.plots import plot_verification
    result, run_path = pickle.loads(open(sys.argv[1], "rb").read())
    registry = sys.argv[2]
    plot_verification(result.rows, sys.argv[3])            # warm up matplotlib before forking
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)   # killed children are reaped at once
    print("ready", flush=True)
    for line in sys.stdin:
        k = int(line)
        pid = os.fork()
        if pid == 0:                                # a calibration writing versions until it is killed
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            try:
                while True:
                    publish(registry, result, input_paths=[run_path],
                            settings=CalibrationSettings(cluster_tol_c=3.0 + k * 1e-3), figure=k % 3 != 0)
                    k += 1000
            finally:
                import traceback
                traceback.print_exc()
                os._exit(1)
        print(pid, flush=True)
""")


def _wait_gone(pid: int, timeout_s: float = 30.0) -> None:
    t_end = time.monotonic() + timeout_s
    while Path(f"/proc/{pid}").exists():
        assert time.monotonic() < t_end, f"process {pid} survived SIGKILL"
        time.sleep(0.01)


def test_calibration_killed_at_random_moments(calibration, tmp_path):
    """SIGKILL a process writing calibrations after a random delay, again and again: after every kill the registry
    verifies, no earlier version or figure changed; at the end a calibration goes through and leaves no note."""
    registry = tmp_path / "reg"
    publish(calibration, registry, k=-1)  # a version that must survive everything
    before = assert_registry_sound(registry, {})
    rng = random.Random(7)
    zygote = subprocess.Popen(
        [sys.executable, "-c", ZYGOTE, str(calibration["state"]), str(registry), str(tmp_path / "warm.png")],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert zygote.stdout.readline().strip() == "ready"
        for k in range(KILLS):
            zygote.stdin.write(f"{k}\n")
            zygote.stdin.flush()
            pid = int(zygote.stdout.readline())
            time.sleep(rng.uniform(0.0, 0.6))
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pytest.fail("the calibration process ended by itself (its traceback is on stderr)")
            _wait_gone(pid)
            before = assert_registry_sound(registry, before)
    finally:
        zygote.stdin.close()
        zygote.wait(timeout=60)
    versions = Registry(registry).versions(UNIT)
    assert len(versions) >= 2, "no kill landed after a publish: the loop did not exercise the write path"
    result = publish(calibration, registry, k=10_000)
    assert result["version"] == versions[-1].version + 1 and Path(result["figure"]).exists()
    report = Registry(registry).verify()
    assert report.ok and not report.notes, report
    assert_registry_sound(registry, before)
    leftovers = [p.name for p in (registry / "units" / UNIT).iterdir() if p.name.startswith(".tmp-")]
    assert leftovers == []
    proc = subprocess.run(
        [THERMOCAL, "passport", "verify", "--registry", str(registry), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0 and json.loads(proc.stdout)["ok"] is True, proc.stderr


# --- two calibrations at once -------------------------------------------------------------------------------------

CALIBRATE = textwrap.dedent("""
    import json, sys
    from pipeline.calibrate import tilt
    from pipeline.calibrate.publish import publish
    from pipeline.calibrate.settings import CalibrationSettings
    from pipeline.io.runs import read_run
    path, registry = sys.argv[1], sys.argv[2]
    print("ready", flush=True)
    sys.stdin.readline()                             # both start together
    result = publish(registry, tilt.calibrate([read_run(path)]), input_paths=[path], settings=CalibrationSettings())
    print(json.dumps({k: result[k] for k in ("version", "passport_sha256", "created", "figure")}))
""")


def _calibrate_at_once(paths: list[Path], registry: Path) -> list[dict]:
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", CALIBRATE, str(p), str(registry)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for p in paths
    ]
    for p in procs:
        assert p.stdout.readline().strip() == "ready", p.stderr.read()
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    results = []
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
        results.append(json.loads(out))
    return results


def test_two_processes_calibrating_the_same_unit_at_once(calibration, tmp_path):
    """Two runs of one unit calibrated at the same moment by two processes: two versions, chained; the same run
    twice: one version, which the second process finds."""
    registry = tmp_path / "reg"
    results = _calibrate_at_once(calibration["paths"], registry)
    assert sorted(r["version"] for r in results) == [1, 2] and all(r["created"] for r in results)
    versions = Registry(registry).versions(UNIT)
    assert [v.sha256 for v in versions] == [r["passport_sha256"] for r in sorted(results, key=lambda r: r["version"])]
    assert Registry(registry).load(UNIT, 2)["parent_sha256"] == versions[0].sha256
    report = Registry(registry).verify()
    assert report.ok and not report.notes, report
    assert all(Path(r["figure"]).read_bytes().endswith(PNG_END) for r in results)

    same = _calibrate_at_once([calibration["paths"][0]] * 2, tmp_path / "reg2")
    assert [r["version"] for r in same] == [1, 1] and sorted(r["created"] for r in same) == [False, True]
    assert same[0]["passport_sha256"] == same[1]["passport_sha256"]
    assert len(Registry(tmp_path / "reg2").versions(UNIT)) == 1


def test_two_calibrate_commands_at_once(calibration, tmp_path):
    """Two ``thermocal calibrate`` console scripts (two Prefect flows sharing one Prefect home) on the same unit at
    the same time: both exit 0, two chained versions."""
    registry = tmp_path / "reg"
    procs = [
        subprocess.Popen(
            [THERMOCAL, "calibrate", str(p), "--registry", str(registry), "--json"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for p in calibration["paths"]
    ]
    results = []
    for p in procs:
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
        results.append(json.loads(out))
    assert sorted(r["version"] for r in results) == [1, 2]
    report = Registry(registry).verify()
    assert report.ok and not report.notes, report


# --- full disk, read-only registry ---------------------------------------------------------------------------------


class MountRefused(Exception):
    pass


@contextlib.contextmanager
def mounted(target: Path, *args: str, remount: str | None = None):
    """``mount *args target`` (then ``mount -o remount target``) for the duration; MountRefused if not permitted."""
    target.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", *args, str(target)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise MountRefused(proc.stderr.strip() or "mount failed")
    if remount:
        proc = subprocess.run(["mount", "-o", remount, str(target)], capture_output=True, text=True)
        if proc.returncode != 0:
            subprocess.run(["umount", "-l", str(target)], capture_output=True)
            raise MountRefused(proc.stderr.strip() or "remount failed")
    try:
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], capture_output=True)


def _fill(folder: Path, leave_bytes: int) -> Path:
    """Fill the file system of ``folder`` but about ``leave_bytes``."""
    filler = folder / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        with contextlib.suppress(OSError):
            while os.write(fd, bytes(65536)):
                pass
    finally:
        os.close(fd)
    size = filler.stat().st_size
    os.truncate(filler, max(0, size - leave_bytes))
    return filler


def _unchanged(registry: Path, before: dict[str, str]) -> None:
    assert snapshot(registry) == before, "the failed calibration changed the unit's folder"
    report = Registry(registry).verify()
    assert report.ok and not report.notes, report


def _fsize_child(fn) -> None:
    """Run ``fn`` in a forked child whose file writes stop at 16 KiB (EFBIG, as on a full disk)."""
    import resource

    def limit_file_size():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (16384, 16384))

    run_in_child(fn, limit_file_size, "the check in the child")


def test_full_disk_gives_a_clear_error_and_writes_nothing(calibration, tmp_path):
    """The registry on a full file system: one-line error naming the passport, the unit's folder unchanged; with
    room for the passport but not the figure: the version is complete, no figure, no partial file."""
    try:
        with mounted(tmp_path / "small", "-t", "tmpfs", "-o", "size=1m", "tmpfs") as disk:
            registry = disk / "reg"
            publish(calibration, registry, k=0)
            before = snapshot(registry)
            filler = _fill(disk, 0)
            with pytest.raises(RegistryError) as info:
                publish(calibration, registry, k=1)
            text = str(info.value)
            assert "\n" not in text and "no space left on device (disk full)" in text, text
            assert text.startswith(str(registry / "units" / UNIT / "v0002.json")), text
            _unchanged(registry, before)
            filler.unlink()
            filler = _fill(disk, 40_000)  # the passport (~21 kB) and its log row fit, the figure (~60 kB) does not
            result = publish(calibration, registry, k=2)
            assert result["version"] == 2 and result["figure"] is None
            names = sorted(p.name for p in (registry / "units" / UNIT).iterdir())
            assert names == [".lock", "log.jsonl", "v0001.json", "v0001.png", "v0002.json"]
            report = Registry(registry).verify()
            assert report.ok and not report.notes, report
            filler.unlink()
            assert publish(calibration, registry, k=3)["version"] == 3
            return
    except MountRefused as exc:
        print(f"tmpfs not mountable here ({exc}); using a file-size limit")
    registry = tmp_path / "reg"
    publish(calibration, registry, k=0, figure=False)
    before = snapshot(registry)

    def check():
        with pytest.raises(RegistryError, match="file too large") as info:
            publish(calibration, registry, k=1)
        assert "\n" not in str(info.value)

    _fsize_child(check)
    _unchanged(registry, before)


def test_read_only_registry_gives_a_clear_error(calibration, tmp_path):
    """A registry mounted read-only (else: a user without write permission): one line, nothing written."""
    base = Path(tempfile.mkdtemp(prefix="thermocal-ro-", dir="/tmp" if Path("/tmp").is_dir() else None))
    os.chmod(base, 0o777)  # reachable by an unprivileged child
    run_copy = base / "run.mcap"
    run_copy.write_bytes(Path(calibration["paths"][0]).read_bytes())
    registry = base / "reg"
    publish(calibration, registry, k=0, input_path=run_copy)
    before = snapshot(registry)
    try:
        try:
            with mounted(base / "ro", "--bind", str(registry), remount="remount,bind,ro") as ro:
                with pytest.raises(RegistryError) as info:
                    publish(calibration, ro, k=1, input_path=run_copy)
                text = str(info.value)
                assert "\n" not in text and "read-only file system" in text and text.startswith(str(ro)), text
                report = Registry(ro).verify()
                assert report.ok and not report.notes, report
        except MountRefused as exc:
            print(f"read-only bind mount not possible here ({exc}); a user without write permission instead")
            from tests.passport.test_registry import run_unprivileged

            def check():
                with pytest.raises(RegistryError, match="permission denied") as info:
                    publish(calibration, registry, k=1, input_path=run_copy)
                assert "\n" not in str(info.value)

            os.chmod(registry / "units" / UNIT, 0o555)
            try:
                run_unprivileged(check)
            finally:
                os.chmod(registry / "units" / UNIT, 0o755)
        _unchanged(registry, before)
    finally:
        shutil.rmtree(base, ignore_errors=True)
