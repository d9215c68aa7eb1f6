"""The process of thermocal's local Prefect server (:mod:`flows.localserver` starts it and talks to it): Prefect's
API, and a job process per ``thermocal`` command, forked warm by multiprocessing's forkserver.

``python -m flows.jobserver PREFECT_HOME`` (:func:`serve`) serves Prefect's API and UI in its main thread (Prefect's
server app under uvicorn, as ``prefect server start`` runs it) and takes commands on a Unix socket in another
(:func:`_dispatch`). Its forkserver imports :data:`PRELOAD` once; each job process is a fork of it, so it starts
with the command line, the flows, Prefect and the pipeline imported. :func:`run_job` takes the command's standard
output and error (their file descriptors, sent over the socket), its arguments, working directory, umask and
environment, runs it as :func:`flows.cli.main` runs it in-process, and sends back the exit status. When it returns,
multiprocessing ends the process the way it ends every child: it waits for the non-daemon threads (Prefect sends its
queued events and logs to the server there), then exits without the interpreter's teardown. Importing this module
imports nothing heavy (the forkserver's preload does).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

from .localserver import DEFAULT_IDLE_S, LOCK, LOG, SOCKET, STATE, code_fingerprint

#: what the forkserver imports before it forks a job process: this module and the warm-up (:mod:`flows.warmup`)
PRELOAD = ["flows.jobserver", "flows.warmup"]
#: seconds a job whose command was killed gets to wind its flow down before it exits anyway
CLIENT_GONE_GRACE_S = 5.0


def nothing() -> None:
    """A job that does nothing (the server's first process: it starts the forkserver)."""


def run_job(conn: socket.socket) -> None:
    """Run the command a ``thermocal`` client sends over ``conn`` (:func:`flows.localserver.run_on_server`)."""
    from flows.cli.entry import run
    from flows.runtime import exit_guarded

    # Ctrl-C reaches the command only as the client forwards it (_watch_client): whatever SIGINT disposition the
    # server inherited from the command that started it (ignored, when that one ran in a background shell), the job
    # takes it as Python does at a terminal
    signal.signal(signal.SIGINT, signal.default_int_handler)
    _, fds, _, _ = socket.recv_fds(conn, 1, 2)
    for fd, target in zip(fds, (1, 2)):  # the command's own stdout and stderr
        os.dup2(fd, target)
        os.close(fd)
    reader = conn.makefile("rb")
    req = json.loads(reader.readline())
    kept = {k: os.environ[k] for k in ("PREFECT_API_URL", "PREFECT_HOME", "PREFECT_UI_API_URL")}
    os.environ.update({k: v for k, v in req["env"].items() if not k.startswith("PREFECT_")})
    os.environ.update(kept)
    with contextlib.suppress(OSError):
        os.chdir(req["cwd"])
    os.umask(req["umask"])
    sys.argv = ["thermocal", *req["argv"]]
    started, done = threading.Event(), threading.Event()

    def command() -> int:
        started.set()  # from here an interrupt is the command's (exit_guarded: "thermocal: aborted", 130)
        try:
            return run(server_checked=True)
        finally:
            done.set()

    threading.Thread(target=_watch_client, args=(reader, started, done), daemon=True, name="thermocal-client").start()
    try:
        exit_guarded(command)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except KeyboardInterrupt:  # Ctrl-C as the command ended
        code = 130
    with contextlib.suppress(OSError):
        conn.sendall(json.dumps({"exit": code}).encode() + b"\n")
        conn.shutdown(socket.SHUT_RDWR)


def _watch_client(reader, started: threading.Event, done: threading.Event) -> None:
    """Ctrl-C from the client (``INT``) interrupts the command; the client gone (killed) too, and then the job
    leaves after :data:`CLIENT_GONE_GRACE_S` whatever the command is doing."""

    main = threading.main_thread().ident
    assert main is not None  # the main thread has started

    def interrupt() -> None:
        started.wait()
        if not done.is_set():
            signal.pthread_kill(main, signal.SIGINT)

    with contextlib.suppress(OSError, ValueError):
        for line in reader:
            if line.strip() == b"INT":
                interrupt()
    if done.is_set():
        return
    interrupt()
    time.sleep(CLIENT_GONE_GRACE_S)
    os._exit(130)


# ------------------------------------------------------------------------------------------------------ server
def _socket_path(home: Path) -> Path:
    """The command socket: in the Prefect home, or in a private temporary folder where that path is too long for
    a Unix socket (~100 bytes)."""
    path = home / SOCKET
    return path if len(os.fsencode(path)) < 100 else Path(tempfile.mkdtemp(prefix="thermocal-")) / SOCKET


def _health(url: str) -> bool:
    import urllib.request

    try:
        with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


def serve(home: Path) -> int:
    """The server (see the module doc): Prefect's API in the main thread, commands started by
    :func:`_dispatch` in another."""
    import fcntl

    home.mkdir(parents=True, exist_ok=True)
    lock = open(home / LOCK, "w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return 0  # another server owns this home
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    api_url = f"http://127.0.0.1:{port}/api"
    os.environ.update(
        {
            "PREFECT_HOME": str(home),
            "PREFECT_API_URL": api_url,  # for the job processes
            "PREFECT_UI_API_URL": api_url,
            "PREFECT_SERVER_SERVICES_SCHEDULER_ENABLED": "false",
            "PREFECT_SERVER_SERVICES_LATE_RUNS_ENABLED": "false",
            "PREFECT_SERVER_LOGGING_LEVEL": "WARNING",
        }
    )
    path = _socket_path(home)
    path.unlink(missing_ok=True)  # a killed server's (the lock is ours)
    old = os.umask(0o077)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    os.umask(old)
    listener.listen(64)
    state = {
        "pid": os.getpid(),
        "api_url": api_url,
        "ui_url": api_url.removesuffix("/api"),
        "socket": str(path),
        "idle_s": float(os.environ.get("THERMOCAL_SERVER_IDLE_S", DEFAULT_IDLE_S)),
        "home": str(home),
        "log": str(home / LOG),
        "code": code_fingerprint(),
    }
    jobs: list = []
    seen = {"api_s": time.monotonic()}
    dispatcher = threading.Thread(
        target=_dispatch, args=(listener, state, jobs, seen), daemon=True, name="thermocal-jobs"
    )
    import uvicorn
    from prefect.server.api.server import create_app

    api = uvicorn.Server(
        uvicorn.Config(_ApiActivity(create_app(final=True), seen), host="127.0.0.1", port=port, log_level="warning")
    )
    for sig in (signal.SIGTERM, signal.SIGINT):  # uvicorn stops on them, then raises them again: ignored then
        signal.signal(sig, lambda *_: None)
    try:
        dispatcher.start()
        api.run()
    finally:
        with contextlib.suppress(OSError, ValueError):
            if json.loads((home / STATE).read_text()).get("pid") == os.getpid():
                (home / STATE).unlink()
        listener.close()
        path.unlink(missing_ok=True)
        if path.parent != home:  # the private temporary folder of a long home's socket
            path.parent.rmdir()
        for job in list(jobs):  # a stopped server interrupts its commands
            job.terminate()
        for job in list(jobs):
            job.join(10)
    return 0


class _ApiActivity:
    """Prefect's ASGI app, noting in ``seen["api_s"]`` (time.monotonic, seconds) when a request or a message on an
    open connection last reached it: a flow run in another process (the Python API, a notebook) uses the server
    without a ``thermocal`` command, and the server must not count that time as idle."""

    def __init__(self, app, seen: dict) -> None:
        self.app, self.seen = app, seen

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        self.seen["api_s"] = time.monotonic()

        async def noted():
            message = await receive()
            self.seen["api_s"] = time.monotonic()
            return message

        return await self.app(scope, noted, send)


def _dispatch(listener: socket.socket, state: dict, jobs: list, seen: dict) -> None:
    """Warm the forkserver up, publish the state file once the API answers, then start a job process per
    command; stop the server (SIGTERM to this process, as ``thermocal server stop``) after ``idle_s`` without a
    command and without a request to the API (``seen``, noted by :class:`_ApiActivity`), or when a job cannot be
    started (its reason in the log)."""
    import multiprocessing
    import traceback

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    try:
        warm = ctx.Process(target=nothing)  # starts the forkserver, which imports PRELOAD
        warm.start()
        warm.join()
        home = Path(state["home"])
        while not _health(state["api_url"]):
            time.sleep(0.1)
        tmp = home / f".{STATE}.tmp"
        tmp.write_text(json.dumps(state))
        tmp.chmod(0o600)
        tmp.replace(home / STATE)
        listener.settimeout(0.25)
        last = time.monotonic()
        while jobs or time.monotonic() - max(last, seen["api_s"]) < state["idle_s"]:
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                conn = None
            if conn is not None:
                with conn:
                    job = ctx.Process(target=run_job, args=(conn,), name="thermocal-job")
                    job.start()
                jobs.append(job)
            jobs[:] = [j for j in jobs if j.is_alive()]
            if jobs or conn is not None:
                last = time.monotonic()
    except Exception:
        if listener.fileno() != -1:  # (not the server's own shutdown, which closes the listener)
            traceback.print_exc()
    os.kill(os.getpid(), signal.SIGTERM)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m flows.jobserver PREFECT_HOME")
    sys.exit(serve(Path(sys.argv[1])))
