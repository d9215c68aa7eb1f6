"""The figures of a run with several units drawn in a second process (pipeline.calibrate.figure_worker): the same
PNG bytes as drawn inline, drawn inline when the worker cannot start, and no worker left alive after the caller ends,
fails or is interrupted."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate.figure_worker import FigureWorker
from pipeline.calibrate.figures import FigureJob, draw_figure
from pipeline.passport.document import SCHEMA_ID
from pipeline.thermal import fit_thermal_model
from pipeline.verify import VerificationRow


def alive(pid: int) -> bool:
    """The process ``pid`` exists and is not a zombie."""
    stat = Path(f"/proc/{pid}/stat")
    try:
        return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _jobs(folder: Path) -> list[FigureJob]:
    """A verification figure and a constants figure (a passport of five plateaus on a quadratic model)."""
    temps = np.array([-40.0, -10.0, 20.0, 45.0, 70.0])
    K0 = np.diag([0.55, 0.548, 0.548])
    K = np.array([K0 * (1 + 1e-5 * (t - 20) + 3e-8 * (t - 20) ** 2) for t in temps])
    U0 = np.array([[1e-3 + 2e-5 * (t - 20), 5e-4, 4e-4] for t in temps])
    model = fit_thermal_model(temps, K, U0, "poly2", 20.0, 3.0)
    passport = folder / "v0001.json"
    passport.write_text(
        json.dumps(
            {
                "schema": SCHEMA_ID,
                "coefficients": {"K": np.asarray(model.K0).tolist(), "U0": np.asarray(model.U00).tolist()},
                "normal_temp_c": 20.0,
                "thermal_model": model.to_dict(),
                "per_plateau": [{"temp_c": t, "K": k.tolist(), "U0": u.tolist()} for t, k, u in zip(temps, K, U0)],
            }
        )
    )
    rows = tuple(
        VerificationRow(
            temp_c=t,
            position=pos,
            run_id="r",
            t_start_ns=k,
            t_end_ns=k + 1,
            dg_uncompensated_g=(k + 1) * 1e-4,
            dg_method1_g=(k + 1) * 1e-6,
            dg_method2_g=(k + 2) * 1e-6,
            dg_method2_simplified_g=0.0,
            tolerance_g=1e-4,
            passed=True,
        )
        for k, (t, pos) in enumerate([(-10.0, "VP1"), (-10.0, "VP2"), (45.0, "VP1"), (45.0, "VP2")])
    )
    return [
        FigureJob(str(folder / "v0001.png"), "verification", "AU-0001 v1", rows=rows),
        FigureJob(str(folder / "v0001.constants.png"), "constants", "AU-0001 v1", passport=str(passport)),
    ]


def test_worker_draws_the_inline_figures_and_ends(tmp_path):
    (tmp_path / "worker").mkdir()
    (tmp_path / "inline").mkdir()
    inline = _jobs(tmp_path / "inline")
    for job in inline:
        draw_figure(job)
    with FigureWorker(processes=2) as draw:  # two: the jobs shared between them
        assert len(draw.pids) == 2 and all(alive(pid) for pid in draw.pids)
        for job in _jobs(tmp_path / "worker"):
            draw(job)
    assert not any(alive(pid) for pid in draw.pids)
    for job, ref in zip(draw.jobs, inline):
        assert Path(job.path).read_bytes() == Path(ref.path).read_bytes()
    assert sorted(p.name for p in (tmp_path / "worker").iterdir()) == ["v0001.constants.png", "v0001.json", "v0001.png"]
    result = {"figure": draw.jobs[0].path, "constants_figure": str(tmp_path / "gone.png")}
    assert draw.results([result]) == [{"figure": draw.jobs[0].path, "constants_figure": None}]


def test_figures_drawn_here_when_the_worker_cannot_start(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "executable", str(tmp_path / "no-python"))
    with FigureWorker() as draw:
        assert draw.pids == []
        for job in _jobs(tmp_path):
            draw(job)
    assert all(Path(job.path).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for job in draw.jobs)


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_no_worker_left_when_the_caller_fails_or_is_interrupted(tmp_path, error):
    with pytest.raises(error), FigureWorker() as draw:
        for job in _jobs(tmp_path):
            draw(job)
        raise error("stopped")
    assert len(draw.pids) == 1 and not any(alive(pid) for pid in draw.pids)


def test_no_worker_left_when_interrupted_while_the_caller_waits_for_the_figures(tmp_path):
    """Ctrl-C once every unit is calibrated, while the caller waits for the workers to draw what they were given:
    the workers are stopped with the caller, not left drawing (and writing figures) after the command ended."""
    main = threading.main_thread().ident
    assert main is not None
    folders = [tmp_path / str(k) for k in range(3)]
    # Ctrl-C as in a command's process (Python's own handler: KeyboardInterrupt), whatever an earlier test of this
    # session left installed (in the whole suite something did: the signal was taken and nothing raised)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt), FigureWorker() as draw:
            for folder in folders:
                folder.mkdir()
                for job in _jobs(folder):
                    draw(job)
            # the workers are still importing matplotlib: the interrupt lands in the wait at the block's end
            threading.Timer(0.3, signal.pthread_kill, (main, signal.SIGINT)).start()
    finally:
        signal.signal(signal.SIGINT, before)
    assert len(draw.pids) == 1 and not any(alive(pid) for pid in draw.pids)
    time.sleep(0.5)
    assert not [p for folder in folders for p in folder.glob("*.png")]


def test_no_worker_left_drawing_when_the_caller_is_killed(tmp_path):
    """A caller killed (no __exit__) with figures still in the workers' pipes: the workers leave with it."""
    caller = (
        "import os, sys\n"
        "from pathlib import Path\n"
        "from pipeline.calibrate.figure_worker import FigureWorker\n"
        "from tests.calibrate.test_figure_worker import _jobs\n"
        "draw = FigureWorker().__enter__()\n"
        "for k in range(3):\n"
        "    folder = Path(sys.argv[1]) / str(k)\n"
        "    folder.mkdir()\n"
        "    for job in _jobs(folder):\n"
        "        draw(job)\n"
        "print(*draw.pids, flush=True)\n"
        "os._exit(9)\n"
    )
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-c", caller, str(tmp_path)], capture_output=True, text=True, cwd=root)
    assert done.returncode == 9, done.stderr
    pids = [int(p) for p in done.stdout.split()]
    deadline = time.monotonic() + 30.0
    while any(alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(pids) == 1 and not any(alive(pid) for pid in pids)
    assert not list(tmp_path.glob("*/*.png"))  # the 6 figures given were not drawn after the caller was gone


def test_worker_imports_the_plotting_code_only():
    """A worker starts beside the caller's segmentation, on the same cores: its module and a job's type import
    neither polars, the segmenter nor Prefect (they were ~0.3 CPU s of its start)."""
    code = (
        "import sys, pipeline.calibrate.figure_worker, pipeline.calibrate.figures\n"
        "print(sorted(m for m in ('polars', 'pipeline.segment', 'prefect', 'scipy') if m in sys.modules))"
    )
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
