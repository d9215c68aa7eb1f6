"""Prefect flows of thermocal (``calibrate``, ``fleet``) and the ``thermocal`` command line.

Importing this package does not import Prefect; ``flows.runtime.prefect_defaults`` sets the defaults (no
telemetry) before Prefect is imported; flow runs are recorded on ``PREFECT_API_URL`` or on thermocal's local server
(``flows.localserver``; its process ``flows.jobserver`` runs the commands in warm job processes).
"""
