"""thermocal's local Prefect server (flows/localserver.py) with real processes: commands record their flow runs,
task runs and artifacts on it and Prefect's own CLI lists them (the pinned versions); a killed or interrupted
command leaves no process behind; the server exits by itself when idle, and its processes with it when killed;
progress lines on a terminal only; a failing command prints one line. Every wait is bounded."""

from __future__ import annotations

import json
import os
import pty
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from flows.localserver import ensure_server, read_state, stop_server
from pipeline.io.runs import write_run
from pipeline.simulate.chamber import SimConfig, simulate

pytestmark = pytest.mark.slow  # a real Prefect server and its workers

BIN = Path(sys.executable).parent
THERMOCAL = str(BIN / "thermocal")


def _children(pid: int) -> dict[int, list[int]]:
    """ppid -> child pids of every process (from /proc)."""
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if fields[0] != "Z":
                kids.setdefault(int(fields[1]), []).append(int(d))
    return kids


def _descendants(pid: int) -> set[int]:
    kids, out, todo = _children(pid), set(), [pid]
    while todo:
        for c in kids.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _alive(pids) -> set[int]:
    return {p for p in pids if _cmdline(p) and _state(p) != "Z"}


def _state(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "X"


def _wait(what: str, check, timeout_s: float):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.05)
    pytest.fail(f"{what}: not within {timeout_s} s")


def _without_key_notice(stderr: str) -> str:
    """stderr without the one-time notice of the session's first passport (its station signing key created)."""
    return "".join(ln for ln in stderr.splitlines(keepends=True) if "created this station's signing key" not in ln)


def _workers(server: int) -> list[int]:
    """The server's warm process (one): multiprocessing's forkserver, which forks the job processes."""
    return sorted(p for p in _children(server).get(server, []) if "multiprocessing.forkserver" in _cmdline(p))


def _jobs(server: int) -> list[int]:
    """The job processes the forkserver forked (one per command running)."""
    kids = _children(server)
    return sorted(j for w in _workers(server) for j in kids.get(w, []))


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("runs")
    res = simulate(SimConfig(unit_serial="AU-0401", unit_seed=401, program="short", rate_hz=2.0))
    return write_run(res.run, d / "AU-0401.mcap", "mcap")


@pytest.fixture(scope="module")
def standard_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("runs")
    res = simulate(SimConfig(unit_serial="AU-0402", unit_seed=402, program="standard", rate_hz=10.0))
    return write_run(res.run, d / "AU-0402.mcap", "mcap")


def test_commands_recorded_and_listed_by_prefects_cli(short_run, tmp_path):
    """`thermocal calibrate` without PREFECT_API_URL runs on the local server (started here on first use); its flow
    run, its task runs (ingest, observe, fit, write) and its artifact are on that server, and `prefect flow-run
    ls`, `task-run ls`, `artifact ls` and `deployment ls` (the nightly deployment registered against it) list them
    with the pinned prefect/fastapi/pydantic (fastapi >= 0.151 made the server answer 422 to these commands)."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    out = subprocess.run(
        [THERMOCAL, "calibrate", str(short_run), "--registry", str(tmp_path / "reg"), "--json"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["unit"] == "AU-0401" and _without_key_notice(out.stderr) == ""
    st = read_state(Path(os.environ["PREFECT_HOME"]))
    assert st and st["api_url"].startswith("http://127.0.0.1:")
    assert ensure_server()["pid"] == st["pid"]  # the same installation (another interpreter name): reused
    url = subprocess.run([THERMOCAL, "server", "url"], capture_output=True, text=True, env=env, timeout=60)
    assert url.stdout.strip() == st["api_url"]
    api = st["api_url"]
    (fr,) = [
        f
        for f in httpx.post(f"{api}/flow_runs/filter", json={"limit": 200}, timeout=30).json()
        if f["parameters"].get("registry") == str(tmp_path / "reg")
    ]
    assert fr["state"]["type"] == "COMPLETED"

    def tasks():
        trs = httpx.post(f"{api}/task_runs/filter", timeout=30, json={"flow_runs": {"id": {"any_": [fr["id"]]}}}).json()
        names = {t["name"].rsplit("-", 1)[0] for t in trs if t["state"]["type"] == "COMPLETED"}
        return names if names >= {"ingest", "observe", "fit", "write"} else None

    _wait("task runs recorded (ingest, observe, fit, write)", tasks, 60)
    # the nightly deployment registered on the same server (as `thermocal serve` does, without serving it)
    reg = subprocess.run(
        [
            sys.executable,
            "-c",
            "from flows.serve import nightly_deployment as d; "
            f"d({str(tmp_path / 'inbox')!r}, {str(tmp_path / 'reg')!r}, name='i17').apply()",
        ],
        capture_output=True,
        text=True,
        env={**env, "PREFECT_API_URL": api},
        timeout=120,
    )
    assert reg.returncode == 0, reg.stderr
    penv = {**env, "PREFECT_API_URL": api, "COLUMNS": "250"}
    listed = {}
    for what in ("flow-run", "task-run", "artifact", "deployment"):
        p = subprocess.run([str(BIN / "prefect"), what, "ls"], capture_output=True, text=True, env=penv, timeout=120)
        assert p.returncode == 0, f"prefect {what} ls: {p.stdout[-2000:]}{p.stderr[-2000:]}"
        listed[what] = p.stdout
    assert fr["id"] in listed["flow-run"] and "thermocal-calibrate" in listed["flow-run"]
    assert "fit-" in listed["task-run"] and "write-" in listed["task-run"]
    assert "calibration-au-0401" in listed["artifact"]
    assert "thermocal-fleet/i17" in listed["deployment"]
    assert httpx.get(st["ui_url"] + "/", timeout=30).status_code == 200  # the UI is served too


def test_killed_fleet_leaves_no_process(tmp_path):
    """kill -9 of `thermocal fleet` while its process pool calibrates: the job process that ran it and the pool's
    processes are gone within seconds; the server and its warm forkserver stay for the next commands."""
    inbox = tmp_path / "inbox"
    for k in range(4):
        res = simulate(SimConfig(unit_serial=f"AU-05{k:02d}", unit_seed=500 + k, program="standard", rate_hz=4.0))
        write_run(res.run, inbox / f"AU-05{k:02d}.mcap", "mcap")
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    st = ensure_server()
    sup = st["pid"]
    warm = _wait("the warm forkserver", lambda: _workers(sup), 60)
    cli = subprocess.Popen(
        [
            THERMOCAL,
            "fleet",
            str(inbox),
            "--registry",
            str(tmp_path / "reg"),
            "--pool",
            "process",
            "--workers",
            "2",
            "--json",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:

        def pool_running():
            for job in _jobs(sup):
                kids = _descendants(job)
                if len([p for p in kids if "multiprocessing" in _cmdline(p)]) >= 2:
                    return job, kids
            return None

        busy, kids = _wait("the fleet's process pool running", pool_running, 120)
        cli.kill()
        cli.wait(timeout=10)
        _wait("the killed command's job process and pool gone", lambda: not _alive({busy, *kids}), 15)
        assert _workers(sup) == warm and not _jobs(sup)  # the forkserver, waiting for the next commands
        assert read_state(Path(os.environ["PREFECT_HOME"]))["pid"] == sup
    finally:
        if cli.poll() is None:
            cli.kill()


def test_ctrl_c_stops_cleanly(standard_run, tmp_path):
    """SIGINT (Ctrl-C) to `thermocal calibrate` while it runs in a job process of the local server: exit 130, one
    line on stderr, the job process gone, the forkserver still there."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    st = ensure_server()
    sup = st["pid"]
    warm = _wait("the warm forkserver", lambda: _workers(sup), 60)
    cli = subprocess.Popen(
        [THERMOCAL, "calibrate", str(standard_run), "--registry", str(tmp_path / "reg")],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    (job,) = _wait("the command running in a job process", lambda: _jobs(sup), 60)
    cli.send_signal(signal.SIGINT)
    out, err = cli.communicate(timeout=60)
    assert cli.returncode == 130, err
    assert err.strip().splitlines() == ["thermocal: aborted"] and out == ""
    _wait("the interrupted command's job process gone", lambda: not _alive({job}), 15)
    assert _workers(sup) == warm


def test_commands_back_to_back_and_at_once_each_get_a_job_process(short_run, tmp_path):
    """Three calibrates started at once, then one more: each runs in a job process of its own forked by the one
    forkserver (no process is warmed up for them), each is recorded (versions 1 of three registries, one flow run
    each), and no job process is left."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    st = ensure_server()
    sup = st["pid"]
    warm = _wait("the warm forkserver", lambda: _workers(sup), 60)
    regs = [tmp_path / f"reg{k}" for k in range(3)]
    procs = [
        subprocess.Popen(
            [THERMOCAL, "calibrate", str(short_run), "--registry", str(r), "--json"],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for r in regs
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], [e for _, e in outs]
    assert [json.loads(o)["version"] for o, _ in outs] == [1, 1, 1]
    again = subprocess.run(
        [THERMOCAL, "calibrate", str(short_run), "--registry", str(regs[0]), "--json"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert again.returncode == 0 and json.loads(again.stdout)["created"] is False
    flow_runs = httpx.post(f"{st['api_url']}/flow_runs/filter", json={"limit": 200}, timeout=30).json()
    mine = [f for f in flow_runs if f["parameters"].get("registry") in {str(r) for r in regs}]
    assert len(mine) == 4 and {f["state"]["type"] for f in mine} == {"COMPLETED"}
    assert _workers(sup) == warm
    _wait("no job process left", lambda: not _jobs(sup), 30)


def test_server_exits_when_idle_and_its_processes_when_it_is_killed(tmp_path):
    """The server killed (-9): its warm forkserver follows within seconds. Started again with a 2 s idle timeout (in a
    Prefect home too long for a Unix socket's path: the socket goes to a private temporary folder), it stays up
    while its API is used without a command (a flow run by the Python API), then exits by itself, with everything it
    started, and removes its state file, socket and that folder. Starting on a fresh home with stderr on a terminal
    says so in one line there (stdout: the URL alone); not on a terminal, nothing on stderr."""
    home = tmp_path / "home"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env["PREFECT_HOME"] = str(home)
    code, out, lines = _terminal_stderr([THERMOCAL, "server", "start"], env)
    assert code == 0 and out.startswith("http://127.0.0.1:") and len(out.splitlines()) == 1
    assert lines == [
        f"thermocal: starting the local Prefect server in {home} (its database is created first: 10-30 s) ..."
    ]
    st = read_state(home)
    warm = _wait("the warm forkserver", lambda: _workers(st["pid"]), 60)
    family = _descendants(st["pid"])
    assert warm[0] in family
    os.kill(st["pid"], signal.SIGKILL)
    _wait("the warm processes of a killed server gone", lambda: not _alive(family), 15)

    home = tmp_path / ("long-" * 20)
    env.update(THERMOCAL_SERVER_IDLE_S="2", PREFECT_HOME=str(home))
    again = subprocess.run([THERMOCAL, "server", "start"], env=env, check=True, capture_output=True, timeout=240)
    assert again.stderr == b""
    st = read_state(home)
    assert home not in Path(st["socket"]).parents and Path(st["socket"]).exists()
    family = _descendants(st["pid"]) | {st["pid"]}
    # a flow run by the Python API in another process uses the API without a command: not idle meanwhile
    busy_until = time.monotonic() + 6.0
    while time.monotonic() < busy_until:
        assert httpx.get(st["api_url"] + "/health", timeout=30).status_code == 200
        time.sleep(0.5)
    assert _alive({st["pid"]}), "the server exited while its API was in use"
    _wait("an idle server gone by itself", lambda: not _alive(family), 60)
    assert not (home / "thermocal-server.json").exists() and read_state(home) is None
    assert not Path(st["socket"]).parent.exists()
    assert stop_server(home) is False


def _terminal_stderr(cmd: list[str], env: dict) -> tuple[int, str, list[str]]:
    """Run ``cmd`` with stderr on a pseudo-terminal, stdout on a pipe: exit status, stdout, the stderr lines."""
    master, slave = pty.openpty()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=slave)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:
            break
        if not data:
            break
        chunks.append(data)
    out = proc.communicate(timeout=300)[0]
    os.close(master)
    return proc.returncode, out.decode(), [ln for ln in b"".join(chunks).decode().splitlines() if ln.strip()]


def _with_terminal_stderr(cmd: list[str], env: dict) -> tuple[int, str, list[str]]:
    """Run ``cmd`` with stderr on a pseudo-terminal, stdout on a pipe: exit status, stdout, the progress steps
    (the lines of the session's first command aside: the local server starting, the station's key created)."""
    code, out, lines = _terminal_stderr(cmd, env)
    first = ("thermocal: starting the local Prefect server", "thermocal: created this station's signing key")
    lines = [ln for ln in lines if not ln.startswith(first)]
    assert all(ln.startswith(f"thermocal: {cmd[1]}: ") for ln in lines), lines
    return code, out, [ln.split(": ")[2].split()[0] for ln in lines]


def test_progress_on_a_terminal_json_alone_on_stdout(short_run, tmp_path):
    """calibrate and diagnose with stderr on a terminal: progress lines (ingest, choose the method, observe, fit,
    write) there, stdout (a pipe, --json) the JSON alone; with stderr not a terminal, nothing on stderr."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    code, out, steps = _with_terminal_stderr(
        [THERMOCAL, "calibrate", str(short_run), "--registry", str(tmp_path / "reg"), "--json"], env
    )
    assert code == 0 and json.loads(out)["unit"] == "AU-0401"
    assert steps == ["ingest", "choose", "observe", "fit", "write", "done"]
    code, out, steps = _with_terminal_stderr(
        [
            THERMOCAL,
            "diagnose",
            str(short_run),
            "--json",
            "--png",
            str(tmp_path / "d.png"),
            "--out-passport",
            str(tmp_path / "d.json"),
        ],
        env,
    )
    assert code == 0 and json.loads(out)["unit"] == "AU-0401"
    assert steps == ["ingest", "segment,", "write"]
    quiet = subprocess.run(
        [THERMOCAL, "calibrate", str(short_run), "--registry", str(tmp_path / "reg"), "--json"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert quiet.returncode == 0 and quiet.stderr == "" and json.loads(quiet.stdout)["version"] == 1
    quiet = subprocess.run(
        [THERMOCAL, "calibrate", str(short_run), "--registry", str(tmp_path / "reg"), "--json"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert quiet.returncode == 0 and quiet.stderr == "" and json.loads(quiet.stdout)["version"] == 1


def test_failing_command_prints_one_line(short_run, tmp_path):
    """A calibrate that fails inside its flow (the registry is a file): exit 2 and the one-line reason, no Prefect
    noise (tracebacks, event flushing) on stderr."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    (tmp_path / "reg").write_text("not a folder")
    out = subprocess.run(
        [THERMOCAL, "calibrate", str(short_run), "--registry", str(tmp_path / "reg")],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 2 and out.stdout == ""
    err = _without_key_notice(out.stderr)
    assert len(err.splitlines()) == 1 and err.startswith("thermocal: error: "), out.stderr
    assert str(tmp_path / "reg") in out.stderr


def test_calibrate_into_a_closed_pipe_ends_quietly_and_writes_its_passport(short_run, tmp_path):
    """`thermocal calibrate RUN | head -3` (its output written by a job process of the local server): the reader
    gone ends the output quietly (exit 0, nothing on stderr but the key notice) and the passport is written all the
    same."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    r, w = os.pipe()
    os.close(r)
    try:
        p = subprocess.run(
            [THERMOCAL, "calibrate", str(short_run), "--registry", str(tmp_path / "reg")],
            stdout=w,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            timeout=300,
        )
    finally:
        os.close(w)
    assert p.returncode == 0 and _without_key_notice(p.stderr) == "", (p.returncode, p.stderr)
    assert (tmp_path / "reg" / "units" / "AU-0401" / "v0001.json").is_file()
    assert (tmp_path / "reg" / "units" / "AU-0401" / "v0001.png").is_file()
