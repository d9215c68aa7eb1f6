"""The chunked simulator for long runs computes simulate()'s signal piece by piece."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.simulate.large import simulate_chunked, simulate_run

LOCAL_EFFECTS = [
    ("time_drift", {}),
    ("thermal_hysteresis", {}),
    ("warmup_transient", {}),
    ("temperature_curvature", {}),
    ("scale_nonlinearity", {}),
    ("fixture_face_error", {}),
]


@pytest.mark.parametrize("effects", [[], LOCAL_EFFECTS])
def test_chunks_give_simulates_signal(effects):
    """Without noise the voltmeter is simulate()'s to the last bit, whatever the chunk size; the other streams, the
    metadata and the truth are the same too."""
    cfg = SimConfig(program="short", rate_hz=5.0, noise_v=0.0, temp_noise_c=0.0, effects=effects)
    whole = simulate(cfg)
    for chunk in (7_777, 1_000_000):
        part = simulate_chunked(cfg, chunk_samples=chunk)
        for name in ("t_ns", "ux", "uy", "uz"):
            np.testing.assert_array_equal(part.run.voltmeter[name].to_numpy(), whole.run.voltmeter[name].to_numpy())
        for stream in ("au_temperature", "chamber", "fixture"):
            assert part.run.stream(stream).equals(whole.run.stream(stream))
        assert part.run.meta == whole.run.meta
        assert part.truth == whole.truth


def test_noise_has_the_configured_size():
    cfg = SimConfig(program="short", rate_hz=5.0, noise_v=20e-6)
    noisy = simulate_chunked(cfg, chunk_samples=10_000).run.voltmeter["ux"].to_numpy()
    clean = simulate_chunked(SimConfig(program="short", rate_hz=5.0, noise_v=0.0)).run.voltmeter["ux"].to_numpy()
    assert np.std(noisy - clean) == pytest.approx(20e-6, rel=0.02)


@pytest.mark.parametrize("effect", ["thermal_lag", "tilt_settling"])
def test_effects_across_samples_are_refused(effect):
    with pytest.raises(ValueError, match="depend on other samples"):
        simulate_chunked(SimConfig(program="short", effects=[(effect, {})]))


def test_simulate_run_chunks_long_runs_only():
    """Above the threshold a run of local effects is computed in chunks (its context is the 1 Hz one); below it,
    or with an effect across samples, in one piece (the context has every voltmeter sample)."""
    cfg = SimConfig(program="short", rate_hz=5.0, noise_v=0.0, temp_noise_c=0.0, effects=[("time_drift", {})])
    n = simulate(cfg).run.voltmeter.height
    chunked = simulate_run(cfg, chunked_above_samples=n - 1)
    assert chunked.context.t_s.size < n / 4
    whole = simulate_run(cfg, chunked_above_samples=n)
    assert whole.context.t_s.size == n
    np.testing.assert_array_equal(chunked.run.voltmeter["ux"].to_numpy(), whole.run.voltmeter["ux"].to_numpy())
    lagged = simulate_run(dataclasses.replace(cfg, effects=[("thermal_lag", {})]), chunked_above_samples=n - 1)
    assert lagged.context.t_s.size == n
