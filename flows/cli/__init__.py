"""The ``thermocal`` command line (docs/contract.md). Commands that take ``--json`` print one JSON object on stdout;
logs and progress go to stderr; failures exit non-zero with a one-line reason on stderr.

One module per command or command group, each registering its commands on the apps of :mod:`flows.cli.app`:
``inspect``, ``simulate``, ``calibrate``, ``fleet`` (``fleet`` and ``serve``), ``diagnose``, ``apply``,
``export``, ``report``, ``passport`` (the ``passport`` group), ``trends``, ``server`` (the ``server`` group), ``key``
(the ``key`` group); :mod:`flows.cli.app` holds what several share (the apps, help texts, ``JsonFlag``,
:func:`~flows.cli.app.emit`, the calibration options' checks) and :mod:`flows.cli.entry` the console entry point
:func:`main`. A new command is a new module here, imported below.

Prefect is imported only by the commands that run a flow (``calibrate``, ``fleet``, ``serve``). Without
``PREFECT_API_URL``, ``calibrate`` and ``fleet`` run in a warm job process of thermocal's local Prefect server
(:mod:`flows.localserver`, started on first use; ``thermocal server ...``), which records their flow runs.
"""

from __future__ import annotations

# isort: off
# importing a command module registers its commands; this order is the order of `thermocal --help`
from . import inspect, simulate, calibrate, export, apply, diagnose, fleet, server, report, passport, trends, key  # noqa: F401

# isort: on
from .app import app
from .entry import main

__all__ = ["app", "main"]
