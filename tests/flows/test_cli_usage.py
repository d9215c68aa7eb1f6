"""The command line as a person meets it (issue 16, item 8): usage errors exit 2 with one line on stderr,
``--version``, a plain-words help text for every option and argument (no Python type tags), times in UTC."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import typer

from flows.cli import app
from pipeline.inspect import format_summary, utc_text
from tests.conftest import run_main

THERMOCAL = str(Path(sys.executable).parent / "thermocal")


@pytest.mark.parametrize(
    "args, says",
    [
        ((), "missing command"),
        (("calibrat", "x.mcap"), "no such command 'calibrat'"),
        (("passport",), "missing command"),
        (("passport", "lg", "AU-0001"), "no such command 'lg'"),
        (("simulate", "--out", "x.mcap", "--program", "bogus"), "unknown chamber program 'bogus'"),
        (("simulate", "--out", "x.mcap", "--format", "csv"), "unknown format 'csv'"),
        (("simulate", "--out", "x.mcap", "--rate-hz", "fast"), "--rate-hz"),
        (("calibrate",), "missing argument 'run'"),
        (("calibrate", "x.mcap", "--registry", "r", "--bogus"), "no such option: --bogus"),
    ],
)
def test_usage_errors_exit_2_with_one_line(monkeypatch, capsys, tmp_path, args, says):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_main(monkeypatch, capsys, *args)
    assert code == 2, (code, err)
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("thermocal: "), err
    assert says in err.lower(), err
    assert "internal error" not in err and not list(tmp_path.iterdir())


def test_version_in_a_console_script():
    p = subprocess.run([THERMOCAL, "--version"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stderr == ""
    assert re.fullmatch(r"thermocal \d+\.\d+\.\d+\S*\n", p.stdout), p.stdout


def _commands(group, path=()):
    """Every (command path, click command) of the application."""
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):
            yield from _commands(cmd, (*path, name))
        else:
            yield (*path, name), cmd


def test_every_option_and_argument_has_plain_help(monkeypatch, capsys):
    root = typer.main.get_command(app)
    commands = list(_commands(root))
    assert len(commands) >= 10
    jargon = re.compile(r"seed \d{3}|<(bool|str|int|float|path|list\[\w+\])>", re.IGNORECASE)
    for path, cmd in commands:
        for p in cmd.params:
            if p.name == "help":
                continue
            assert (p.help or "").strip(), f"{' '.join(path)} {p.name}: no help text"
            assert not jargon.search(p.help), f"{' '.join(path)} {p.name}: {p.help}"
        monkeypatch.setenv("COLUMNS", "200")
        code, out, err = run_main(monkeypatch, capsys, *path, "--help")
        assert code == 0 and err == "", err
        assert not jargon.search(out), f"{' '.join(path)} --help:\n{out}"
        usage = next(ln for ln in out.splitlines() if "Usage:" in ln)
        assert "{" not in usage, usage  # RUN, not {RUN} (a set of choices to a reader)
    code, out, _ = run_main(monkeypatch, capsys, "export", "--help")
    assert code == 0 and "Usage: thermocal export [OPTIONS] UNIT|FILE [V]" in out


def test_inspect_prints_times_in_utc(tmp_path):
    assert utc_text(1_793_491_200_123_456_789) == "2026-11-01 00:00:00.123 UTC"
    summary = {
        "metadata": {"run_id": "r"},
        "plateaus": [],
        "static_positions": [],
        "warnings": [],
        "streams": {
            "voltmeter": {
                "samples": 3,
                "rate_hz": 1.0,
                "t_start_ns": 1_793_491_200_000_000_000,
                "t_end_ns": 1_793_491_202_000_000_000,
                "duration_s": 2.0,
                "gaps": [[1_793_491_201_000_000_000, 5.0]],
                "non_finite": 0,
            }
        },
    }
    text = format_summary(summary)
    assert "t_ns" not in text
    assert "from 2026-11-01 00:00:00.000 UTC to 2026-11-01 00:00:02.000 UTC" in text
    assert "at 2026-11-01 00:00:01.000 UTC" in text


def _with_reader_gone(args: list[str], env: dict | None = None, cwd=None) -> subprocess.CompletedProcess:
    """``thermocal ARGS | head -0``: the read end of stdout is closed before the command writes anything."""
    r, w = os.pipe()
    os.close(r)
    try:
        return subprocess.run(
            [THERMOCAL, *args], stdout=w, stderr=subprocess.PIPE, text=True, timeout=300, env=env, cwd=cwd
        )
    finally:
        os.close(w)


@pytest.mark.slow  # the console script in a subprocess / a fleet flow
def test_output_into_a_closed_pipe_ends_quietly():
    """`thermocal inspect RUN | head` and `export ... | head`: the reader gone is no error (exit 0, nothing on
    stderr), where it was an internal error (BrokenPipeError, exit 3)."""
    run = Path(__file__).resolve().parents[2] / "sample_data" / "standard_short.mcap"
    for args in (["inspect", str(run)], ["inspect", str(run), "--json"]):
        p = _with_reader_gone(args)
        assert (p.returncode, p.stderr) == (0, ""), (args, p.returncode, p.stderr)


@pytest.mark.slow  # the console script in a subprocess / a fleet flow
def test_fleet_summary_names_each_failed_run_once():
    """The fleet's text: counts in words, and a failed run's one-line reason (which names its file) not preceded by
    the same path again."""
    from flows.cli.fleet import fleet_text

    bad = "/in/bad.mcap"
    s = {
        "done": [{"unit": "AU-0002", "version": 1, "status": "pass", "created": True, "runs": ["/in/u2.mcap"]}],
        "failed": [{"run": bad, "reason": f"{bad}: not an MCAP file"}, {"run": "/in/x", "reason": "no voltmeter"}],
        "skipped": [],
    }
    text = fleet_text(s)
    assert text.splitlines()[0] == "done: 1 unit, failed: 2 runs, skipped: 0 runs"
    assert "  FAILED  /in/bad.mcap: not an MCAP file" in text and text.count(bad) == 1
    assert "  FAILED  /in/x: no voltmeter" in text


def test_a_unit_that_failed_is_named_in_its_line(capsys):
    """A unit of a run with several whose calibration failed: its reason names the file and the stream, not the unit
    (the calibration's errors name ``voltmeter``); the line on stderr, and the fleet's, say which unit it is."""
    import typer

    from flows.cli.calibrate import _units_outcome
    from flows.fleet import failure_line

    reason = "/in/r.mcap: voltmeter: t_ns=1..2: no temperature plateau with the six test positions TP1..TP6"
    named = "/in/r.mcap: /unit/AU-0003/voltmeter: unit AU-0003 has a dead channel: uy has no finite sample"
    with pytest.raises(typer.Exit):
        _units_outcome({"units": [], "failed": [{"unit": "AU-0002", "reason": reason}]}, True)
    assert capsys.readouterr().err == f"thermocal: calibrate: {reason} (unit AU-0002)\n"
    assert failure_line({"run": "/in/r.mcap", "unit": "AU-0002", "reason": reason}) == f"{reason} (unit AU-0002)"
    assert failure_line({"run": "/in/r.mcap", "unit": "AU-0003", "reason": named}) == named


def test_unwritable_outputs_and_wrong_files_are_one_line_errors(monkeypatch, capsys, tmp_path):
    """A place that cannot be written, a file that is not a passport, a registry that is not there: exit 2 and one
    line naming the path (were: an internal error with exit 3; a decoder's message; 'unknown unit')."""
    monkeypatch.chdir(tmp_path)
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    run = Path(__file__).resolve().parents[2] / "sample_data" / "standard_short.mcap"
    cases = [
        (
            ("simulate", "--out", str(blocked / "x.mcap"), "--program", "short", "--rate-hz", "0.2"),
            f"{blocked / 'x.mcap'}: cannot write the run",
        ),
        (("apply", str(run), str(run), "--out", "x.parquet"), f"{run}: not a passport: the file is not JSON"),
        (("diagnose", str(run), "--passport", str(blocked)), f"{blocked}: not a passport: the file is not JSON"),
        (("passport", "show", "AU-0001", "--registry", "nothere"), "nothere: no registry here"),
    ]
    for args, says in cases:
        code, out, err = run_main(monkeypatch, capsys, *args)
        assert (code, out) == (2, ""), (args, code, err)
        assert err.count("\n") == 1 and err.startswith(f"thermocal: error: {says}"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]
