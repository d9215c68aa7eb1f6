"""Prefect flows of thermocal (``calibrate``, ``fleet``) and the ``thermocal`` command line.

Importing this package does not import Prefect; ``flows.runtime.prefect_defaults`` sets the embedded defaults
(local ephemeral mode, no telemetry) before Prefect is imported.
"""
