"""The warm worker of thermocal's local Prefect server (:mod:`flows.localserver`): started by the supervisor
(``python -m flows.worker FD``) with the job socket, it imports the command line, the flows (Prefect) and the
pipeline, takes one command from a ``thermocal`` client, runs it in-process with the client's arguments, working
directory and environment (its Prefect settings are the server's), relays stdout and stderr, sends the exit status
and exits. Nothing imports this module.
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
    """A warm worker: import what the commands need, take one job from the supervisor's socket, run it, exit."""
    from . import cli  # noqa: F401  (the command line and, below, the flows with Prefect and the pipeline)
    from . import calibrate, fleet  # noqa: F401
    from pipeline.calibrate.fleet import prepare_worker

    prepare_worker()
    _import_flow_run_modules()
    listener = socket.socket(fileno=listen_fd)
    token = os.environ.get("THERMOCAL_WORKER_TOKEN", "")
    while True:
        conn, _ = listener.accept()
        reader = conn.makefile("rb")
        try:
            req = json.loads(reader.readline() or b"{}")
        except ValueError:
            req = {}
        if req.get("token") == token and token:
            break
        conn.close()  # not a thermocal client: wait for the next
    listener.close()
    sys.stdout.write("taken\n")
    sys.stdout.flush()
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # the supervisor reads no more from this pipe
    return _run_job(conn, reader, req)


def _import_flow_run_modules() -> None:
    """What Prefect imports on a process's first flow run, imported now: its flow and task engines, the encoder of
    a flow run's parameters (FastAPI's), the run-graph tracker, anyio's asyncio backend (the API client's)."""
    import encodings.idna  # noqa: F401

    import anyio._backends._asyncio  # noqa: F401
    import fastapi.encoders  # noqa: F401
    import prefect.flow_engine  # noqa: F401
    import prefect.task_engine  # noqa: F401
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
