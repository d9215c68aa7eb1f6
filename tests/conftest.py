"""Shared fixtures: seed 000 reference tables, the reference recordings of tests/data/, an isolated Prefect home."""

from __future__ import annotations

import atexit
import json
import os
import shutil
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
#: reference recordings made by others, each with its licence (tests/data/README.md)
DATA = REPO / "tests" / "data"

# Ctrl-C as at a terminal: a session started from a background shell inherits SIGINT ignored (then Python installs
# no KeyboardInterrupt handler, and every process the tests start ignores it too), which the tests that press Ctrl-C
# on a command, or on a worker's caller, cannot run under.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# Prefect: never the user's home, no telemetry (no network here); set before any test imports prefect.
os.environ.setdefault("PREFECT_HOME", str(Path(os.environ.get("TMPDIR", "/tmp")) / f"thermocal-prefect-{os.getpid()}"))
os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
os.environ["DO_NOT_TRACK"] = "1"
# Signing keys: never the user's key folder; one station key for the session, created on first use.
os.environ["THERMOCAL_KEY_DIR"] = tempfile.mkdtemp(prefix="thermocal-test-keys-")
atexit.register(shutil.rmtree, os.environ["THERMOCAL_KEY_DIR"], True)
# Verified-file cache (thermocal trends): never the user's, one for the session.
os.environ["THERMOCAL_CACHE_DIR"] = tempfile.mkdtemp(prefix="thermocal-test-cache-")
atexit.register(shutil.rmtree, os.environ["THERMOCAL_CACHE_DIR"], True)


@pytest.fixture(scope="session", autouse=True)
def _stop_local_prefect_server():
    """thermocal's local Prefect server for this session's PREFECT_HOME, if a test started it, is stopped at the
    end (it would exit by itself after its idle timeout)."""
    yield
    import sys

    if "prefect" in sys.modules:  # send this process's pending events and logs while the server is still up
        from prefect.events.worker import EventsWorker
        from prefect.logging.handlers import APILogWorker

        EventsWorker.drain_all(timeout=30)
        APILogWorker.drain_all(timeout=30)
    from flows.localserver import stop_server

    stop_server(Path(os.environ["PREFECT_HOME"]))


@pytest.fixture(scope="session")
def seed000():
    """The paper's Tables 1-3 (pipeline/simulate/data holds a copy of shared/reference/seed000_tables.json)."""
    return json.loads((REPO / "pipeline" / "simulate" / "data" / "seed000_tables.json").read_text())


@pytest.fixture(scope="session")
def seed000_constants(seed000):
    rows = seed000["table_1_2_constants"]
    T = np.array([r["temp_c"] for r in rows])
    K = np.array([r["K"] for r in rows])
    U0 = np.array([r["U0"] for r in rows])
    return T, K, U0


def data_path(*parts: str) -> Path:
    """A file or folder of tests/data/ (the repository carries them: a missing one is an error, not a skip)."""
    p = DATA.joinpath(*parts)
    assert p.exists(), f"reference data missing from the repository: {p}"
    return p


def run_piece(run, t0_ns: int, t1_ns: int, run_id: str, *, closed: str = "left", **changes):
    """The samples of every stream of ``run`` between ``t0_ns`` and ``t1_ns`` (ns since the epoch; ``closed`` as
    polars' ``is_between``: ``"left"`` keeps [t0, t1), ``"both"`` [t0, t1]) as a run of its own named ``run_id``, as
    a lab records part of a program in a separate file; ``changes`` replace further fields (``fixture=None``,
    ``source=...``)."""
    import dataclasses

    import polars as pl

    def cut(df):
        return None if df is None else df.filter(pl.col("t_ns").is_between(t0_ns, t1_ns, closed=closed))

    fields = {
        "meta": dataclasses.replace(run.meta, run_id=run_id),
        "voltmeter": cut(run.voltmeter),
        "au_temperature": cut(run.au_temperature),
        "chamber": cut(run.chamber),
        "fixture": cut(run.fixture),
    }
    return dataclasses.replace(run, **{**fields, **changes})


def run_in_child(fn, prepare, what: str) -> None:
    """Run ``fn`` in a forked child after ``prepare()`` (e.g. drop privileges, limit file sizes); the child reports
    through its exit code, so a failed assertion in it fails the test (its traceback is printed)."""
    import traceback

    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child reports through its exit code
        code = 0
        try:
            prepare()
            fn()
        except BaseException:
            traceback.print_exc()
            code = 1
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, f"{what} failed (traceback above)"


def run_main(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """The ``thermocal`` console entry point in this process: (exit code, stdout, stderr)."""
    import sys

    from flows.cli import main

    monkeypatch.setattr(sys, "argv", ["thermocal", *args])
    with pytest.raises(SystemExit) as info:
        main()
    out, err = capsys.readouterr()
    return info.value.code, out, err
