"""thermocal's library: pure computation for thermal calibration of accelerometer units (no module imports Prefect).

Physics core (modules named for the physics, units in every docstring):

- ``positions``: the tilt fixture's test (TP) and verification (VP) positions, specific force in g
- ``model``: the metrological model U = K a + U0 (V, V/g) and its inverse
- ``constants``: the 12 constants at one temperature from static positions (closed form, least squares)
- ``thermal``: temperature models of the constants (polynomial, piecewise linear) in dT = T - T0 (C), and the
  temperature-rate terms and lag of the differential method (C/min, s)
- ``compensate``: compensation methods 1 and 2
- ``verify``: gravity-module error at the verification positions (g)
- ``dynamics``: first-order lag (s) and the direction the temperature last came from
- ``uncertainty``: standard uncertainties (1 sigma) of the constants per plateau, at T0 and of the thermal model
- ``plausibility``: fitted constants against the unit type and the run's nominal gain (mV, kelvin, sign mistakes)

Steps and data:

- ``run``: the one canonical in-memory form of a chamber run, whatever the file format
- ``segment``: temperature plateaus and static positions found from the data
- ``settling``: the reading's creep after each move (``tilt_settling``), found in the holds and out of their means
- ``inspect``: what a recording holds, before anything is fitted (plateau program or sweep, poses, methods)
- ``apply``: a passport's full model applied to every voltmeter sample of a recording
- ``plots``: figures (PNG)
- ``jsonable``: the one coercion of results into plain JSON values
- ``utc``: times for people (``t_ns`` as UTC text)
- ``errors``: the one-line error types

Sub-packages:

- ``io``: reading and writing runs (MCAP and Parquet layouts, block codecs, shared checks, schemas as package data)
- ``simulate``: the chamber-run simulator (programs, the simulated unit, chunked long runs)
- ``calibrate``: one recipe per method (``tilt``, ``scalar``, ``differential``: observe each run, then fit and verify,
  into one result type), the observations they share, the settings, the one publish path, fleets
- ``passport``: the passport document and its typed form with the one loader (the right compensation model for
  every method), the registry (storage, integrity, signatures, approvals), the physics-unit diff of two versions
  and which of its changes are significant, exports for flight software (PX4, ArduPilot) and CSV, provenance,
  the text people read (summaries, tables, log, diff) and the calibration certificate
- ``effects``: the catalogue of left-out physics, one module per effect (its simulation, fit terms, explanation
  and properties), the catalogue by id
- ``diagnose``: mismatch diagnosis (locate, name, model, refit)
"""

__version__ = "0.1.0"
