"""Calibration recipes (tilt, scalar, differential), publishing into the registry, fleets."""
