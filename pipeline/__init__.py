"""thermocal's library: pure computation for thermal calibration of accelerometer units.

Modules are named for what they hold:

- ``run``: the one canonical in-memory form of a chamber run (whatever the file format)
- ``positions``: the tilt fixture's test (TP) and verification (VP) positions
- ``model``: the metrological model U = K a + U0 and its inverse
- ``io_mcap`` / ``io_parquet`` / ``runio``: readers and writers of the two log layouts
- ``simulate``: the chamber-program simulator, with the catalogue of left-out effects in ``effects``
- ``segment``: temperature plateaus and static positions found from the data
- ``constants``: the 12 constants per plateau (six-position closed form, least squares)
- ``thermal``: temperature models (polynomial, piecewise linear)
- ``compensate``: compensation methods 1 and 2
- ``verify``: gravity-module error at the verification positions
- ``passport``: the passport document
No module here imports Prefect.
"""

__version__ = "0.1.0"
