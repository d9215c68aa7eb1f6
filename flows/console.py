"""The ``thermocal`` console script. A command that runs a flow on thermocal's local Prefect server (``calibrate``,
``fleet``: :func:`flows.localserver.runs_on_local_server`) is handed to a warm job process of the server from here,
without importing the command line (typer) or the pipeline (numpy): ~0.15 s of start-up less for a command whose
work is done elsewhere. Every other command, and a flow command with ``PREFECT_API_URL`` set, runs in this process
through :func:`flows.cli.main`.
"""

from __future__ import annotations

import sys


def main() -> None:
    """Console entry point (pyproject's ``thermocal``): one-line errors, a closed stdout ends the output quietly,
    as :func:`flows.cli.main` (the same guard, :func:`flows.runtime.exit_guarded`)."""
    from .localserver import run_on_server, runs_on_local_server

    argv = sys.argv[1:]
    if not runs_on_local_server(argv):
        from .cli import main as cli_main

        cli_main(server_checked=True)
        return
    from .runtime import exit_guarded

    exit_guarded(lambda: run_on_server(argv))


if __name__ == "__main__":
    main()
