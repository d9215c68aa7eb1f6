"""A wheel that works: build the wheel, install it (no dependencies) into a fresh virtual environment, and run
``thermocal simulate --format mcap``, ``inspect`` and ``calibrate`` from a folder outside the source tree. Offline:
the fresh environment sees the project environment's installed dependencies through a ``.pth`` file (a ``.pth``
file inside a directory added that way is not processed, so the editable install's finder stays out and
``pipeline`` must come from the wheel, which the test asserts)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

from pipeline.simulate.unit import UnitTruth

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


def _run(cmd: list, cwd: Path, env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{cmd}: exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The wheel built from a copy of the sources, installed into a fresh venv; yields (venv, work dir, env,
    site-packages), and stops the wheel's local Prefect server afterwards."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    src.mkdir()
    shutil.copy(REPO / "pyproject.toml", src)
    for pkg in ("pipeline", "flows", "schemas"):
        shutil.copytree(REPO / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV", "PIP_"))}
    env.update(PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PYTHONNOUSERSITE="1")
    _run(
        [sys.executable, "-m", "pip", "wheel", src, "--no-deps", "--no-build-isolation", "-w", root / "dist"],
        cwd=root,
        env=env,
    )
    (wheel,) = (root / "dist").glob("thermocal-*.whl")
    venv = root / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=root, env=env)
    py = venv / "bin" / "python"
    purelib = Path(
        _run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], root, env).stdout.strip()
    )
    (purelib / "project-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", wheel], cwd=root, env=env)
    work = root / "elsewhere"
    work.mkdir()
    env.update(
        PREFECT_HOME=str(root / "prefect-home"),
        PREFECT_SERVER_ANALYTICS_ENABLED="false",
        DO_NOT_TRACK="1",
        MPLBACKEND="Agg",
        THERMOCAL_KEY_DIR=str(root / "keys"),
        PATH=f"{venv / 'bin'}:{env.get('PATH', '')}",
    )
    yield venv, work, env, purelib
    # the wheel's own local Prefect server (started by its first calibrate) must not outlive the tests
    subprocess.run(
        [str(venv / "bin" / "thermocal"), "server", "stop"], cwd=work, env=env, capture_output=True, timeout=120
    )


def test_pipeline_comes_from_the_wheel(installed):
    venv, work, env, purelib = installed
    out = _run(
        [
            venv / "bin" / "python",
            "-c",
            "import pipeline, flows, sys; print(pipeline.__file__); print(flows.__file__); print(sys.prefix)",
        ],
        work,
        env,
    ).stdout.split()
    assert all(Path(p).is_relative_to(purelib) for p in out[:2]), out
    assert Path(out[2]) == venv


def test_the_wheel_carries_the_schemas_and_reads_them(installed):
    """The one schemas/ folder of the repository is the wheel's data package pipeline/io/schemas (every file,
    byte for byte), and the installed reader takes its schemas from there, not from a source tree."""
    venv, work, env, purelib = installed
    shipped = purelib / "pipeline" / "io" / "schemas"
    sources = sorted(p.name for p in (REPO / "schemas").iterdir() if p.is_file())
    assert {"thermocal.passport.json", "thermocal.proto", "thermocal.binpb", "thermocal.VoltageBlock.json"} <= set(
        sources
    )
    assert sorted(p.name for p in shipped.iterdir() if p.is_file()) == sources
    for name in sources:
        assert (shipped / name).read_bytes() == (REPO / "schemas" / name).read_bytes(), name
    used = _run(
        [venv / "bin" / "python", "-c", "from pipeline.io.codecs import SCHEMA_DIR; print(SCHEMA_DIR)"], work, env
    ).stdout.strip()
    assert Path(used) == shipped


def test_simulate_inspect_calibrate_from_another_folder(installed):
    """The console script of the wheel: a short 2 Hz MCAP run (schemas and the seed-000 unit from package data),
    its inspection, and a calibration whose passport holds the simulated unit's constants at T0 within 20 ppm of
    the gain and 20 micro-g."""
    venv, work, env, _ = installed
    thermocal = venv / "bin" / "thermocal"
    assert thermocal.exists()
    sim = json.loads(
        _run(
            [
                thermocal,
                "simulate",
                "--format",
                "mcap",
                "--out",
                "run.mcap",
                "--program",
                "short",
                "--rate-hz",
                "2",
                "--json",
            ],
            work,
            env,
        ).stdout
    )
    assert Path(work / "run.mcap").is_file() and sim["samples"] > 1000 and sim["unit"] == "AU-0001"
    # the run's channels carry the wheel's schema files as their schema data
    from mcap.reader import make_reader

    with open(work / "run.mcap", "rb") as fh:
        schemas = {s.name: s.data for s in make_reader(fh).get_summary().schemas.values()}
    assert schemas["thermocal.VoltageBlock"] == (REPO / "schemas" / "thermocal.VoltageBlock.json").read_bytes()
    info = _run([thermocal, "inspect", "run.mcap", "--json"], work, env).stdout
    assert '"AU-0001"' in info and f"{sim['samples']}" in info and "TP6" in json.dumps(json.loads(info))
    res = json.loads(_run([thermocal, "calibrate", "run.mcap", "--registry", "reg", "--json"], work, env).stdout)
    assert res["version"] == 1 and res["status"] == "pass" and res["method"] == "tilt_six_position"
    passport = work / res["passport"]  # as given: relative to the folder it ran in
    assert passport.resolve().is_relative_to((work / "reg").resolve())
    doc = json.loads(passport.read_text())
    unit = UnitTruth.from_dict(json.loads((work / "run.truth.json").read_text())["unit"])
    K0, U0 = (x[0] for x in unit.constants_at(np.array([doc["normal_temp_c"]])))
    gain = np.abs(np.diag(K0))
    assert np.abs(np.asarray(doc["coefficients"]["K"]) - K0).max() / gain.min() < 20e-6
    assert (np.abs(np.asarray(doc["coefficients"]["U0"]) - U0) / gain).max() < 20e-6
