"""The local Prefect server thermocal starts for itself, and the warm processes that run its flows.

Why: Prefect's ephemeral mode starts a private API server in every command (8-13 s here, 24 s on a fresh home) and
leaves it running when the command is killed; importing Prefect alone costs ~1 s. Instead, the first ``thermocal
calibrate`` or ``fleet`` without ``PREFECT_API_URL`` starts one background server per Prefect home and later
commands reuse it. Everything rests on supported mechanisms (subprocess, multiprocessing's forkserver, Unix
sockets, Prefect's server app run by uvicorn as ``prefect server start`` runs it):

- the *server* (:mod:`flows.jobserver`, started by :func:`ensure_server`, detached from the terminal, its own
  session) holds a lock in the Prefect home (one server per home), serves Prefect's API and UI (SQLite database
  under ``PREFECT_HOME``) on a free loopback port, and listens for ``thermocal`` commands on a Unix socket (0600);
- it starts each command in a *job process* of multiprocessing's forkserver, which has imported the command line,
  the flows, Prefect and the pipeline once: a job starts in milliseconds, warm; commands back to back or at once
  each get their own, and no warm-up competes with a running command;
- the ``thermocal`` command sends its standard output and error (the file descriptors themselves), arguments,
  working directory, umask and environment; the job process runs the command as it would run in-process, writing
  straight to the command's terminal or pipe, with the flow, its task runs and artifacts recorded on the server,
  then sends back the exit status;
- lifecycle: when the command is killed (``kill -9``) its job process interrupts the flow and exits within
  seconds, its own processes (the fleet's pool) with it; Ctrl-C is passed on as an interrupt. The server (and with
  it the forkserver and any job process) exits when no command has run and nothing has used its API (a flow run by
  the Python API in another process) for ``THERMOCAL_SERVER_IDLE_S`` seconds (default 600), on ``thermocal server
  stop``, or when it is killed.

The state file ``thermocal-server.json`` in the Prefect home (mode 0600) names the server's pid, the API URL and
the socket. ``thermocal server url`` prints the API URL for Prefect's own CLI and UI. Where the home is:
:func:`prefect_home`.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from pipeline.errors import ThermocalError

STATE = "thermocal-server.json"
LOCK = "thermocal-server.lock"
LOG = "thermocal-server.log"
SOCKET = "thermocal-server.sock"
#: seconds without a command or an API request after which the server exits (``THERMOCAL_SERVER_IDLE_S``)
DEFAULT_IDLE_S = 600.0
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
    import platformdirs

    return Path(platformdirs.user_data_dir("thermocal", appauthor=False)) / "prefect"


def use_prefect_home() -> Path:
    """Set ``PREFECT_HOME`` for this process (and Prefect) to :func:`prefect_home`; returns it."""
    home = prefect_home()
    os.environ["PREFECT_HOME"] = str(home)
    return home


#: commands that run a Prefect flow: without PREFECT_API_URL they run on the local server
FLOW_COMMANDS = ("calibrate", "fleet")


def runs_on_local_server(argv: list[str]) -> bool:
    """Whether the ``thermocal`` command ``argv`` (without the program name) runs in a job process of the local
    server: a command that runs a flow (not its ``--help``) without ``PREFECT_API_URL``, whose stdout and stderr are
    files (the job writes to them; where a program has replaced them, e.g. a test capturing them, the flow runs in
    this process, recorded on the local server all the same: :func:`flows.runtime.flow_settings`)."""
    if not (argv[:1] and argv[0] in FLOW_COMMANDS and "--help" not in argv) or os.environ.get("PREFECT_API_URL"):
        return False
    try:
        sys.stdout.fileno(), sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        return False
    use_prefect_home()
    return True


# ------------------------------------------------------------------------------------------------------ state
def read_state(home: Path | None = None) -> dict | None:
    """The running server's state (pid, api_url, socket, code), or None if there is none alive."""
    home = home or prefect_home()
    try:
        st = json.loads((home / STATE).read_text())
    except (OSError, ValueError):
        return None
    return st if _alive(st.get("pid")) else None


def code_fingerprint() -> str:
    """The environment and the thermocal code a server runs (``sys.prefix``, the code's folder and its newest
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
    try:  # a zombie or a reused pid is not our server
        with open(f"/proc/{pid}/stat") as f:
            if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                return False
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return b"flows.jobserver" in f.read()
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
    say_starting(home, first=not (home / "prefect.db").exists())
    env = {**os.environ, **_QUIET, "PREFECT_HOME": str(home)}
    env.pop("PREFECT_API_URL", None)
    with open(home / LOG, "ab") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "flows.jobserver", str(home)],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=log,
            start_new_session=True,
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
        f"the local Prefect server did not start (its log: {home / LOG}); set PREFECT_API_URL to a running server"
    )


def say_starting(home: Path, *, first: bool, stream=None) -> bool:
    """One progress line on ``stream`` (default stderr) saying that the local server is starting and where, only
    when it is a terminal (a script's stderr stays empty: the one-line rule is for errors); True if printed."""
    stream = stream or sys.stderr
    try:
        if not stream.isatty():
            return False
    except (AttributeError, ValueError, OSError):  # no terminal behind it, or closed
        return False
    wait = "its database is created first: 10-30 s" if first else "a few seconds"
    print(f"thermocal: starting the local Prefect server in {home} ({wait}) ...", file=stream, flush=True)
    return True


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
    """Run the ``thermocal`` command ``argv`` in a job process of the local server, which writes to this process's
    stdout and stderr; its exit status. Ctrl-C is passed on; a second one leaves at once."""
    st = ensure_server()
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        conn.connect(st["socket"])
    except OSError as e:
        raise ThermocalError(
            f"cannot reach the local Prefect server ({e}); `thermocal server stop` and try again"
        ) from None
    umask = os.umask(0o022)
    os.umask(umask)
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    request = {"argv": argv, "cwd": os.getcwd(), "env": dict(os.environ), "umask": umask}
    socket.send_fds(conn, [b"\n"], [sys.stdout.fileno(), sys.stderr.fileno()])
    conn.sendall(json.dumps(request).encode() + b"\n")
    reader = conn.makefile("rb")
    interrupted = False
    while True:
        try:
            line = reader.readline()
        except KeyboardInterrupt:
            if interrupted:  # a second Ctrl-C: leave; the job process sees its client gone and stops
                return 130
            interrupted = True
            with contextlib.suppress(OSError):
                conn.sendall(b"INT\n")
            continue
        if not line:
            raise ThermocalError(f"the local Prefect server's job ended without an answer (its log: {st['log']})")
        return int(json.loads(line)["exit"])
