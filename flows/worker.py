"""The warm worker of thermocal's local Prefect server (:mod:`flows.localserver`): started by the supervisor
(``python -m flows.worker FD``) with the job socket, it imports the command line, the flows (Prefect) and the
pipeline once, then waits for ``thermocal`` clients. For each client (its token checked) it forks a *job process*
that runs the command in-process with the client's arguments, working directory and environment (its Prefect
settings are the server's), relays stdout and stderr, sends the exit status and exits; the worker goes back to
waiting. A fork of the warmed process starts in milliseconds, so commands run back to back never wait for a worker
to warm up, and no warm-up competes with a running command for the CPU. The worker tells the supervisor on its
stdout when a job starts (``start PID``) and ends (``end PID``): the supervisor's idle timer. Nothing imports this
module.

Forking is safe here: when the worker forks, its only Python thread is the main one (the job's threads start in
the job process) and the native threads the imports started (polars' allocator and clean-up threads) are not in a
library call; polars' compute pool and Prefect's clients and event loops are first made in the job process.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import sys
import threading
import time
from typing import NoReturn

from .localserver import CLIENT_GONE_GRACE_S


class _Relay:
    """A text stream that sends what is written to the client (stdout or stderr) as JSON lines."""

    def __init__(self, conn: socket.socket, fd: int, tty: bool, lock: threading.Lock):
        self.conn, self.fd, self.tty, self.lock = conn, fd, tty, lock
        self.encoding = "utf-8"
        self.errors = "strict"

    def write(self, s: str) -> int:
        if isinstance(s, (bytes, bytearray)):
            s = bytes(s).decode("utf-8", "replace")
        if s:
            with self.lock, contextlib.suppress(OSError):
                self.conn.sendall(json.dumps({"fd": self.fd, "data": s}).encode() + b"\n")
        return len(s)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self.tty

    def writable(self) -> bool:
        return True

    @property
    def closed(self) -> bool:
        return False


def worker(listen_fd: int) -> int:
    """The warm worker: import what the commands need, then fork a job process per client (:func:`_serve`); in a
    job process, run its command (:func:`_run_job`) and exit with its status (:func:`_exit_job_process`)."""
    from pipeline.calibrate.fleet import prepare_worker

    from . import (  # noqa: F401
        calibrate,
        cli,
        fleet,
    )
    from .runtime import no_heartbeat

    prepare_worker()
    _import_flow_run_modules()
    no_heartbeat()
    job = _serve(socket.socket(fileno=listen_fd), os.environ.get("THERMOCAL_WORKER_TOKEN", ""))
    if job is None:  # the worker itself, stopped
        return 0
    code = _run_job(*job)
    _exit_job_process(code)


def _exit_job_process(code: int) -> NoReturn:
    """End a job process as the interpreter would, less its last step: threads' exit hooks (Prefect drains its
    event and log queues to the server there) and the joining of non-daemon threads, the ``atexit`` functions, the
    streams flushed; then ``os._exit``. The interpreter's own teardown (every module and object of the warm worker
    freed, in a forked copy of its memory) cost ~1 s of CPU after the command had answered. The two hooks are
    CPython's own (not a promised API): where either is missing, the process exits the ordinary way."""
    import atexit

    shutdown_threads = getattr(threading, "_shutdown", None)
    run_exit_functions = getattr(atexit, "_run_exitfuncs", None)
    if shutdown_threads is None or run_exit_functions is None:
        sys.exit(code)  # the interpreter's full teardown: slower, the same result
    shutdown_threads()  # what the interpreter calls at exit, before the atexit functions
    run_exit_functions()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _serve(listener: socket.socket, token: str):
    """Accept clients until SIGTERM; fork a job process for each one whose first line carries ``token``. Returns
    in a job process only, with its (connection, reader, request); in the worker, None when stopped. Job processes
    receive SIGTERM when the worker dies (Linux), and the worker terminates them when it is stopped."""
    import select

    from .localserver import die_with_parent

    me = os.getpid()
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(1))
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the supervisor's session: only SIGTERM stops the worker
    jobs: set[int] = set()

    def tell(line: str) -> None:
        with contextlib.suppress(OSError):
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    try:
        while not stopping:
            while jobs:  # reap the jobs that ended
                try:
                    pid, _ = os.waitpid(-1, os.WNOHANG)
                except ChildProcessError:
                    jobs.clear()
                    break
                if not pid:
                    break
                jobs.discard(pid)
                tell(f"end {pid}")
            if not select.select([listener], [], [], 0.2)[0]:
                continue
            try:
                conn, _ = listener.accept()
            except OSError:
                continue
            conn.settimeout(10)  # a client that does not send its request does not hold the worker up
            reader = conn.makefile("rb")
            try:
                req = json.loads(reader.readline() or b"{}")
            except (OSError, ValueError):
                req = {}
            if not token or req.get("token") != token:
                conn.close()  # not a thermocal client
                continue
            pid = os.fork()
            if pid == 0:  # the job process
                listener.close()
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
                signal.signal(signal.SIGINT, signal.default_int_handler)
                die_with_parent()
                if os.getppid() != me:  # the worker died before that
                    os._exit(1)
                os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # the supervisor reads the worker's stdout, not ours
                conn.settimeout(None)
                return conn, reader, req
            jobs.add(pid)
            tell(f"start {pid}")
            conn.close()
    finally:
        if os.getpid() == me:  # the worker (a job process returns through here too)
            for pid in jobs:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGTERM)
    return None


def _import_flow_run_modules() -> None:
    """What Prefect imports on a process's first flow run, imported now: its flow and task engines, the encoder of
    a flow run's parameters (FastAPI's), the run-graph tracker, anyio's asyncio backend (the API client's)."""
    import encodings.idna  # noqa: F401

    import anyio._backends._asyncio  # noqa: F401
    import fastapi.encoders  # noqa: F401
    import prefect.flow_engine
    import prefect.task_engine
    import prefect.utilities.visualization  # noqa: F401


def _run_job(conn: socket.socket, reader, req: dict) -> int:
    from . import cli

    keep = {k: os.environ[k] for k in ("PREFECT_API_URL", "PREFECT_HOME", "PREFECT_UI_API_URL") if k in os.environ}
    os.environ.update({k: v for k, v in req.get("env", {}).items() if not k.startswith("PREFECT_")})
    os.environ.update(keep)
    os.environ.pop("THERMOCAL_WORKER_TOKEN", None)
    with contextlib.suppress(OSError):
        os.chdir(req.get("cwd") or "/")
    if isinstance(req.get("umask"), int):
        os.umask(req["umask"])
    lock = threading.Lock()
    tty = req.get("tty", {})
    real_out, real_err = sys.stdout, sys.stderr
    sys.stdout = _Relay(conn, 1, bool(tty.get("stdout")), lock)
    sys.stderr = _Relay(conn, 2, bool(tty.get("stderr")), lock)

    done = threading.Event()

    def watch_client():
        """A Ctrl-C from the client interrupts the command; the client gone (killed) too, and then the worker
        leaves after a grace period whatever the command is doing."""
        with contextlib.suppress(OSError):
            for line in reader:
                with contextlib.suppress(ValueError):
                    if json.loads(line).get("signal") == "INT" and not done.is_set():
                        os.kill(os.getpid(), signal.SIGINT)
        if done.is_set():
            return
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(CLIENT_GONE_GRACE_S)
        os._exit(130)

    threading.Thread(target=watch_client, daemon=True, name="thermocal-client").start()
    sys.argv = ["thermocal", *req.get("argv", [])]
    try:
        cli.main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except KeyboardInterrupt:
        code = 130
    done.set()
    with lock, contextlib.suppress(OSError):
        conn.sendall(json.dumps({"exit": code}).encode() + b"\n")
        conn.shutdown(socket.SHUT_RDWR)
    sys.stdout, sys.stderr = real_out, real_err
    return code


if __name__ == "__main__":
    sys.exit(worker(int(sys.argv[1])))
