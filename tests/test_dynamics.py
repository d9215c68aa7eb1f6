"""The smoothed thermosensor between its readings (pipeline.dynamics): a thermosensor read once a minute gives the
temperature at any time as well as one read every second, and nothing is made up across its gaps."""

from __future__ import annotations

import numpy as np

from pipeline.dynamics import Thermosensor, first_order_lag, smooth_temperature


def _case_temperature() -> tuple[np.ndarray, np.ndarray]:
    """A unit's case temperature each second through one leg of the differential program's cycle (+20 C held
    30 min, 1 C/min to -40 C, 30 min soak, 1 C/min to +70 C, 30 min soak: the chamber air 90 s behind the setpoint,
    the case 600 s behind the air)."""
    knots_s = np.cumsum([0.0, 1800.0, 3600.0, 1800.0, 6600.0, 1800.0])
    setpoint = np.array([20.0, 20.0, -40.0, -40.0, 70.0, 70.0])
    t = np.arange(knots_s[-1] + 1.0)
    return t, first_order_lag(t, first_order_lag(t, np.interp(t, knots_s, setpoint), 90.0), 600.0)


def _error_c(t, case, every_s: float, query_s) -> np.ndarray:
    """The smoothed thermosensor read every ``every_s`` (noiseless) at ``query_s``, less the case temperature."""
    step = int(every_s)
    sensor = Thermosensor(t[::step], *smooth_temperature(t[::step], case[::step], 301.0))
    return sensor.at(query_s)[0] - np.interp(query_s, t, case)


def test_a_thermosensor_read_once_a_minute_is_not_cut_into_chords():
    """At the differential method's 10-s block centres, readings a minute apart give the temperature within 0.7 mC
    rms (readings every second: 0.6 mC; straight chords between the minute readings were off by 2.7 mC rms, 10 mC at
    the ends of the ramps: the same error at the same point of every cycle, which biased the quadratic bias terms of
    a differential calibration by 4 to 6 of their standard uncertainties)."""
    t, case = _case_temperature()
    q = np.arange(65.0, t[-1] - 60.0, 10.0)
    every_second, every_minute = _error_c(t, case, 1.0, q), _error_c(t, case, 60.0, q)
    rms = [float(np.sqrt(np.mean(e**2))) for e in (every_second, every_minute)]
    assert rms[1] < 1.3 * rms[0] and rms[1] < 7e-4, rms
    assert np.abs(every_minute).max() < 2.0 * np.abs(every_second).max(), rms


def test_across_a_gap_the_temperature_is_a_straight_line():
    """An hour without readings in a ramp: no cubic swing across it (its end slopes would carry it tens of C away),
    the straight line between the readings either side, as at the record's ends the nearest reading."""
    t, case = _case_temperature()
    keep = (t % 60 == 0) & ((t < 4000) | (t > 7600))
    ts, temp = t[keep], case[keep]
    sensor = Thermosensor(ts, *smooth_temperature(ts, temp, 301.0))
    q = np.arange(3950.0, 7700.0, 10.0)
    i = np.searchsorted(ts, 4000.0) - 1
    inside = (q > ts[i]) & (q < ts[i + 1])
    chord = np.interp(q, ts[[i, i + 1]], sensor.temp_c[[i, i + 1]])
    assert inside.sum() > 300 and np.allclose(sensor.at(q)[0][inside], chord[inside])
    assert np.array_equal(sensor.at(np.array([-5.0, 1e9]))[0], sensor.temp_c[[0, -1]])
