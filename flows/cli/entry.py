"""The console entry point :func:`main`: runs :data:`flows.cli.app.app` (every command registered by
importing :mod:`flows.cli`) with one-line usage errors and exit statuses (docs/contract.md)."""

from __future__ import annotations

import sys

import typer

from .app import app


def _usage_line(e: Exception) -> str:
    """One line for a usage error: the message, the command it concerns and where help is."""
    msg = " ".join((e.format_message() if hasattr(e, "format_message") else str(e)).split())
    ctx = getattr(e, "ctx", None)
    cmd = getattr(ctx, "command_path", None) or "thermocal"
    if not msg:  # a group called without its command
        msg = "missing command."
    return f"thermocal: usage error: {msg} (see `{cmd} --help`)"


def main(server_checked: bool = False) -> None:
    """Console entry point: one-line errors, no tracebacks (set THERMOCAL_DEBUG=1 to see them); a closed stdout
    (``| head``) ends the output quietly (:func:`flows.runtime.exit_guarded`). Commands that run a flow go to the
    local server's warm job processes unless PREFECT_API_URL is set (:mod:`flows.localserver`; ``server_checked``: the
    caller, :func:`flows.console.main`, has already found that this command is not one of them)."""
    from ..runtime import exit_guarded

    exit_guarded(lambda: run(server_checked))


def run(server_checked: bool = False) -> int:
    """The command ``sys.argv[1:]``; its exit status (usage errors: their one line and 2). :func:`main` without
    its guard (a job process of the local server guards it itself: :mod:`flows.jobs`)."""
    try:
        argv = sys.argv[1:]
        if not server_checked:
            from ..localserver import run_on_server, runs_on_local_server

            if runs_on_local_server(argv):
                return run_on_server(argv)
        rc = app(standalone_mode=False, prog_name="thermocal")
        if rc == 130:  # typer's answer to Ctrl-C (KeyboardInterrupt) in a command
            raise KeyboardInterrupt
        return rc if isinstance(rc, int) else 0
    except typer.TyperException as e:  # usage: a missing or unknown command, option or value (typer's click errors)
        print(_usage_line(e), file=sys.stderr)
        code = getattr(e, "exit_code", None)
        return code if isinstance(code, int) else 2
    except typer.Exit as e:
        return e.exit_code
    except typer.Abort:
        raise KeyboardInterrupt from None
