"""The local Prefect server thermocal starts for itself, and the warm worker that runs its flows.

Why: Prefect's embedded ("ephemeral") mode starts a private API server in every command (8-13 s here, 24 s on a
fresh home) and leaves it running when the command is killed; importing Prefect alone costs ~1 s. Instead, the first
``thermocal calibrate`` or ``fleet`` without ``PREFECT_API_URL`` starts one background server per Prefect home and
later commands reuse it:

- a *supervisor* (``python -m flows.localserver supervise``, detached from the terminal, its own session) holds a
  lock in the Prefect home (one per home), runs ``prefect server start`` on a free loopback port (the real server:
  API, UI, SQLite database under ``PREFECT_HOME``), and keeps one *warm worker* (:mod:`flows.worker`): a process
  that has imported Prefect, the flows and the pipeline once and waits on a loopback job port;
- the ``thermocal`` command sends its arguments, working directory, umask and environment to the worker, which
  forks a *job process* for it (milliseconds: the fork is already warm); the job process runs the command exactly
  as it would run in-process, with the flow and its task runs and artifacts recorded on the server, relays what it
  writes (stdout, stderr) and its exit status, and exits. Commands run back to back or at once each get their own
  job process, and no worker warms up while a command runs;
- lifecycle: the job process watches its client; when the client goes away (``kill -9``) it interrupts the flow and
  exits within seconds, and its own processes (the fleet's pool) follow it. Ctrl-C is passed on as an interrupt.
  The server, the supervisor and the worker (and any job process) exit when no command has run for
  ``THERMOCAL_SERVER_IDLE_S`` seconds (default 600), on ``thermocal server stop``, or when the supervisor itself is
  killed (Linux: parent-death signal).

The state file ``thermocal-server.json`` in the Prefect home (mode 0600) names the supervisor's pid, the API URL,
the job port and a random token the worker checks. ``thermocal server url`` prints the API URL for Prefect's own
CLI and UI. Where the home is: :func:`prefect_home`.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from pipeline.errors import ThermocalError

STATE = "thermocal-server.json"
LOCK = "thermocal-server.lock"
LOG = "thermocal-server.log"
#: seconds without a command after which the server exits (``THERMOCAL_SERVER_IDLE_S``)
DEFAULT_IDLE_S = 600.0
#: seconds a worker whose client went away gets to wind its flow down before it exits anyway
CLIENT_GONE_GRACE_S = 5.0
START_TIMEOUT_S = 180.0
_QUIET = {"PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1"}


# ------------------------------------------------------------------------------------------------------ where
def prefect_home() -> Path:
    """Where thermocal's Prefect state lives: ``PREFECT_HOME`` if set, else the per-user data folder
    (``$XDG_DATA_HOME/thermocal/prefect``, i.e. ``~/.local/share/thermocal/prefect`` on Linux;
    ``~/Library/Application Support/thermocal/prefect`` on macOS)."""
    env = os.environ.get("PREFECT_HOME")
    if env:
        return Path(env).expanduser()
    try:
        import platformdirs
    except ImportError:  # an environment installed before thermocal depended on it: the XDG default
        return Path(os.environ.get("XDG_DATA_HOME") or "~/.local/share").expanduser() / "thermocal" / "prefect"
    return Path(platformdirs.user_data_dir("thermocal", appauthor=False)) / "prefect"


def use_prefect_home() -> Path:
    """Set ``PREFECT_HOME`` for this process (and Prefect) to :func:`prefect_home`; returns it."""
    home = prefect_home()
    os.environ["PREFECT_HOME"] = str(home)
    return home


#: commands that run a Prefect flow: without PREFECT_API_URL they run on the local server's warm worker
FLOW_COMMANDS = ("calibrate", "fleet")


def runs_on_local_server(argv: list[str]) -> bool:
    """Whether the ``thermocal`` command ``argv`` (without the program name) runs on the local server's warm
    worker: a command that runs a flow (not its ``--help``) while :func:`uses_local_server`. Sets ``PREFECT_HOME``
    (:func:`use_prefect_home`) for such a command."""
    if not (argv[:1] and argv[0] in FLOW_COMMANDS and "--help" not in argv):
        return False
    use_prefect_home()
    return uses_local_server()


def uses_local_server() -> bool:
    """Whether flows run on thermocal's local server: no ``PREFECT_API_URL`` of the user's, and not switched off
    with ``THERMOCAL_PREFECT=ephemeral`` (Prefect's own per-process mode)."""
    return not os.environ.get("PREFECT_API_URL") and os.environ.get("THERMOCAL_PREFECT", "") != "ephemeral"


# ------------------------------------------------------------------------------------------------------ state
def read_state(home: Path | None = None) -> dict | None:
    """The running server's state (pid, api_url, job_port, token, code), or None if there is none alive."""
    home = home or prefect_home()
    try:
        st = json.loads((home / STATE).read_text())
    except (OSError, ValueError):
        return None
    return st if _alive(st.get("pid")) else None


def code_fingerprint() -> str:
    """The environment and the thermocal code a worker runs (``sys.prefix``, the code's folder and its newest
    modification time): a server started by another installation, or before the code changed, is replaced by
    :func:`ensure_server`."""
    import hashlib

    root = Path(__file__).resolve().parents[1]
    newest = max((f.stat().st_mtime_ns for d in ("flows", "pipeline") for f in (root / d).rglob("*.py")), default=0)
    return hashlib.sha256(f"{sys.prefix}|{root}|{newest}".encode()).hexdigest()[:16]


def _alive(pid) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie or a reused pid is not our supervisor
        with open(f"/proc/{pid}/stat") as f:
            if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                return False
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return b"flows.localserver" in f.read()
    except OSError:
        return True  # no /proc (not Linux): trust kill(0)


def ensure_server(home: Path | None = None, timeout_s: float = START_TIMEOUT_S) -> dict:
    """The running server's state, starting the server first if there is none (several seconds; the first time
    on a machine Prefect also creates its database)."""
    home = home or use_prefect_home()
    st = read_state(home)
    code = code_fingerprint()
    if st and st.get("code") == code:
        return st
    if st:  # another installation's or older code: replace it
        stop_server(home)
    home.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **_QUIET, "PREFECT_HOME": str(home)}
    env.pop("PREFECT_API_URL", None)
    with open(home / LOG, "ab") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "flows.localserver", "supervise", str(home)],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=log,
            start_new_session=True,
            close_fds=True,
            cwd=str(home),
        )
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st = read_state(home)
        if st and (st.get("code") == code or st.get("pid") == proc.pid):  # (the code may change meanwhile)
            return st
        if proc.poll() not in (None, 0):
            break
        time.sleep(0.05)
    raise ThermocalError(
        f"the local Prefect server did not start (its log: {home / LOG}); set PREFECT_API_URL to "
        "a running server or THERMOCAL_PREFECT=ephemeral"
    )


def stop_server(home: Path | None = None, timeout_s: float = 30.0) -> bool:
    """Stop the server of ``home`` (default: :func:`prefect_home`); False if none was running."""
    home = home or prefect_home()
    st = read_state(home)
    if not st:
        return False
    with contextlib.suppress(ProcessLookupError):
        os.kill(st["pid"], signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and _alive(st["pid"]):
        time.sleep(0.05)
    return True


# ------------------------------------------------------------------------------------------------------ client
def run_on_server(argv: list[str]) -> int:
    """Run the ``thermocal`` command ``argv`` on the local server's warm worker; relay its output; its exit
    status."""
    st = ensure_server()
    try:
        conn = socket.create_connection(("127.0.0.1", st["job_port"]), timeout=30)
    except OSError as e:
        raise ThermocalError(
            f"cannot reach the local Prefect server's worker ({e}); `thermocal server stop` and try again"
        ) from None
    conn.settimeout(None)
    umask = os.umask(0o022)
    os.umask(umask)
    request = {
        "token": st["token"],
        "argv": argv,
        "cwd": os.getcwd(),
        "env": dict(os.environ),
        "umask": umask,
        "tty": {"stdout": _isatty(sys.stdout), "stderr": _isatty(sys.stderr)},
    }
    conn.sendall(json.dumps(request).encode() + b"\n")
    reader = conn.makefile("rb")
    outs = {1: sys.stdout, 2: sys.stderr}
    interrupted = False
    while True:
        try:
            line = reader.readline()
        except KeyboardInterrupt:
            if interrupted:  # a second Ctrl-C: leave; the worker sees its client gone and stops
                return 130
            interrupted = True
            with contextlib.suppress(OSError):
                conn.sendall(b'{"signal": "INT"}\n')
            continue
        if not line:
            raise ThermocalError(
                f"the local Prefect server's worker ended without an answer (its log: {prefect_home() / LOG})"
            )
        msg = json.loads(line)
        if "exit" in msg:
            return int(msg["exit"])
        out = outs.get(msg.get("fd"))
        if out is not None:
            out.write(msg["data"])
            out.flush()


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


# ------------------------------------------------------------------------------------------------------ supervisor
def die_with_parent() -> None:
    """In a child (before exec, or after a fork): receive SIGTERM when the parent dies (Linux; elsewhere the idle
    timeout)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _health(url: str) -> bool:
    import urllib.request

    try:
        with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


def supervise(home: Path) -> int:
    """The supervisor's main loop (see the module doc)."""
    import fcntl

    home.mkdir(parents=True, exist_ok=True)
    lock = open(home / LOCK, "w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return 0  # another supervisor owns this home
    idle_s = float(os.environ.get("THERMOCAL_SERVER_IDLE_S", DEFAULT_IDLE_S))
    port = _free_port()
    api_url = f"http://127.0.0.1:{port}/api"
    env = {**os.environ, **_QUIET, "PREFECT_HOME": str(home), "PREFECT_UI_API_URL": api_url}
    env.pop("PREFECT_API_URL", None)
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "prefect",
            "server",
            "start",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--no-scheduler",
            "--no-late-runs",
        ],
        env=env,
        stdin=subprocess.DEVNULL,
        preexec_fn=die_with_parent,
    )
    stopping = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stopping.set())
    signal.signal(signal.SIGINT, lambda *_: stopping.set())
    listener = socket.create_server(("127.0.0.1", 0), backlog=64)
    token = secrets.token_hex(16)
    worker_env = {**env, "PREFECT_API_URL": api_url, "THERMOCAL_WORKER_TOKEN": token}

    def new_worker() -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [sys.executable, "-m", "flows.worker", str(listener.fileno())],
            env=worker_env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            pass_fds=(listener.fileno(),),
            preexec_fn=die_with_parent,
        )

    worker = new_worker()  # it warms up while the server starts
    jobs: set[str] = set()  # the worker's job processes running (it says "start PID" and "end PID")
    try:
        while not _health(api_url):
            if server.poll() is not None or stopping.is_set():
                print(f"thermocal server: prefect server exited ({server.returncode})", file=sys.stderr)
                return 1
            time.sleep(0.2)
        state = {
            "pid": os.getpid(),
            "api_url": api_url,
            "ui_url": api_url.removesuffix("/api"),
            "job_port": listener.getsockname()[1],
            "token": token,
            "idle_s": idle_s,
            "server_pid": server.pid,
            "home": str(home),
            "code": code_fingerprint(),
        }
        tmp = home / f".{STATE}.tmp"
        tmp.write_text(json.dumps(state))
        tmp.chmod(0o600)
        tmp.replace(home / STATE)
        last = time.monotonic()
        import select

        while not stopping.is_set():
            assert worker.stdout is not None  # new_worker starts it with stdout=PIPE
            if select.select([worker.stdout], [], [], 0.25)[0]:
                line = worker.stdout.readline()
                if line:
                    kind, _, pid = line.decode(errors="replace").strip().partition(" ")
                    if kind == "start":
                        jobs.add(pid)
                    else:
                        jobs.discard(pid)
                    last = time.monotonic()
                else:  # the worker died (a crash on import, or killed; its jobs follow it): start another, slowly
                    worker.wait()
                    worker.stdout.close()
                    jobs.clear()
                    time.sleep(1.0)
                    worker = new_worker()
            if jobs:
                last = time.monotonic()
            if server.poll() is not None:
                print(f"thermocal server: prefect server exited ({server.returncode})", file=sys.stderr)
                break
            if not jobs and time.monotonic() - last > idle_s:
                break
    finally:
        with contextlib.suppress(OSError):
            st = json.loads((home / STATE).read_text())
            if st.get("pid") == os.getpid():
                (home / STATE).unlink()
        listener.close()
        for p in (worker, server):  # the worker terminates its jobs
            if p.poll() is None:
                p.terminate()
        for p in (worker, server):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
    return 0


# ------------------------------------------------------------------------------------------------------ worker
def exit_with_parent(poll_s: float = 0.5) -> None:
    """Exit this process (at once) when its parent is gone: a thread that watches the parent pid. For the
    processes a worker starts itself (the fleet's pool), so that none outlives a killed command."""
    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="thermocal-parent-watch").start()


def pool_worker_init() -> None:
    """Initializer of the fleet's process pool: leave with the parent, then warm up
    (:func:`pipeline.calibrate.fleet.prepare_worker`)."""
    exit_with_parent()
    from pipeline.calibrate.fleet import prepare_worker

    prepare_worker()


def main(argv: list[str]) -> int:
    if argv[:1] == ["supervise"]:
        return supervise(Path(argv[1]))
    print("usage: python -m flows.localserver supervise HOME", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
