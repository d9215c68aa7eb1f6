"""The figures of a run with several units drawn in another process while the next unit is calibrated
(:class:`FigureWorker`): a unit's two figures were ~1.5 CPU s, several times the unit's choose, observe, fit and
write once the run is segmented (~0.12 CPU s in a warm worker since they are drawn in layers with their tick labels
pasted, :class:`pipeline.plots._Layers`), so on two cores they are drawn beside the calibration. A worker is ``python -m
pipeline.calibrate.figure_worker``: it imports the plotting code only (no Prefect, no caller's main module), reads
:class:`pipeline.calibrate.figures.FigureJob` pickles on its standard input and draws each
(:func:`pipeline.calibrate.figures.draw_figure`) until the input ends, so it ends with its caller (a caller
interrupted or killed closes the pipe)."""

from __future__ import annotations

import contextlib
import os
import pickle
import subprocess
import sys
import threading
import time
from pathlib import Path

from pipeline.calibrate.figures import FigureJob, draw_figure, drop_missing_figures

#: How long a closing caller waits for the workers to finish the figures they were given (s), before it stops them.
_FINISH_S = 600.0
#: The relative cost of a figure of each kind (CPU), to share them out between the workers.
_COST = {"verification": 1, "constants": 3}


class FigureWorker:
    """publish's ``draw`` (:func:`pipeline.calibrate.publish.publish`): each :class:`FigureJob` sent to one of
    ``processes`` worker processes (the least loaded by :data:`_COST`). One by default: a unit's two figures
    (~0.12 CPU s warm) take less than its calibration in the caller, so one worker keeps up, and a second costs its
    start (~1.9 CPU s) and its own first figures for no shorter run. Used as a context manager: on a normal exit,
    waits for the workers, then draws here any figure they did not make (none could start, or one failed), so the
    figures are those :func:`publish` draws inline; on an exception (Ctrl-C too), stops them at once (a figure not
    drawn is drawn at the unit's next publish). ``pids``: the workers' (empty when none could start)."""

    def __init__(self, processes: int = 1) -> None:
        self.processes = processes
        self.jobs: list[FigureJob] = []
        self.pids: list[int] = []
        self._procs: list[subprocess.Popen] = []
        self._sent: list[int] = []

    def __enter__(self) -> FigureWorker:
        root = Path(__file__).resolve().parents[2]  # the folder holding ``pipeline``: imported from there
        for _ in range(self.processes):
            with contextlib.suppress(OSError):
                self._procs.append(
                    subprocess.Popen(
                        [sys.executable, "-m", __name__, str(os.getpid())],  # its caller, to leave with
                        stdin=subprocess.PIPE,
                        stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,  # a figure is a convenience: one not drawn is drawn here after
                        cwd=root,
                    )
                )
        self.pids = [proc.pid for proc in self._procs]
        self._sent = [0] * len(self._procs)
        return self

    def __call__(self, job: FigureJob) -> None:
        self.jobs.append(job)
        while self._procs:
            k = self._sent.index(min(self._sent))
            pipe = self._procs[k].stdin
            assert pipe is not None  # opened with stdin=PIPE
            try:
                pickle.dump(job, pipe)
                pipe.flush()
            except (OSError, ValueError):  # that worker ended: the others take the job (else drawn here at the end)
                _stop([self._procs.pop(k)], 0.0)
                del self._sent[k]
                continue
            self._sent[k] += _COST.get(job.kind, 1)
            return

    def __exit__(self, kind, value, tb) -> None:
        procs, self._procs = self._procs, []
        _stop(procs, _FINISH_S if kind is None else 0.0)
        if kind is None:
            for job in self.jobs:
                if not os.path.exists(job.path):
                    draw_figure(job)

    def results(self, results: list[dict]) -> list[dict]:
        """publish's results, after the exit: without a figure path whose figure was not made."""
        return [drop_missing_figures(r) for r in results]


def _stop(procs: list[subprocess.Popen], wait_s: float) -> None:
    """Close the workers' input and wait up to ``wait_s`` for them to draw what they were given and end; then stop
    them (a figure being drawn is left under its temporary name, which the registry removes later); stopped at once
    when the wait is interrupted."""
    for proc in procs:
        with contextlib.suppress(OSError, ValueError):
            proc.stdin.close()  # type: ignore[union-attr]
    deadline = time.monotonic() + wait_s
    try:
        for proc in procs:
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    except BaseException:  # Ctrl-C while waiting for the figures: the workers stopped too, not left drawing
        for proc in procs:
            with contextlib.suppress(OSError):
                proc.kill()
            proc.wait()
        raise


def main() -> None:
    """The worker: draws the jobs read on standard input until it ends, or until its caller is gone (killed: the
    jobs still in the pipe are not drawn after it)."""
    caller = int(sys.argv[1]) if len(sys.argv) > 1 else os.getppid()  # gone already: leaves at once

    def leave_with_caller() -> None:
        while os.getppid() == caller:
            time.sleep(0.2)
        os._exit(1)

    threading.Thread(target=leave_with_caller, daemon=True, name="thermocal-caller-watch").start()
    # imported and warmed up while the caller segments its runs, not at the first figure (pipeline.plots imports
    # lazily)
    from matplotlib import figure, ticker  # noqa: F401
    from matplotlib.backends import backend_agg  # noqa: F401

    import pipeline.plots

    pipeline.plots.warm_up()

    source = sys.stdin.buffer
    while True:
        try:
            job = pickle.load(source)
        except EOFError:
            return
        draw_figure(job)


if __name__ == "__main__":
    main()
