"""Simulated runs too long to simulate in one piece (1 kHz over the 16.5 h standard program: about 59 M samples).

:func:`pipeline.simulate.chamber.simulate` builds every per-sample array of the run at once (the constants K(T) alone
take 72 bytes a sample, about 12 GB all told at 1 kHz). :func:`simulate_chunked` computes the same signal in time chunks
and keeps only the voltmeter samples (32 bytes a sample): the thermal streams, the fixture log, the unit and the
ground truth come from one :func:`~pipeline.simulate.chamber.simulate` call at the thermal rate (1 Hz, where the
voltmeter grid is the thermal grid, so its context's temperature is the true case temperature), and each voltmeter chunk
is ``K(T) a + U0(T) + effects + noise`` with T interpolated from that 1 Hz grid, as in ``simulate``.

Without noise the voltmeter equals ``simulate``'s to rounding (the vibration phases are drawn the same way); the
noise and the thermosensor noise are other draws of the same distributions. Effects must act sample by sample:
``thermal_lag`` and ``tilt_settling`` look across time and are refused.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.effects.base import SignalContext
from pipeline.effects.catalogue import effect_class, make_effect
from pipeline.run import Run, make_frame
from pipeline.simulate.chamber import (
    THERMAL_RATE_HZ,
    SimConfig,
    SimResult,
    _check,
    _face_rotations_rad,
    _specific_force_g,
    output_with_effects_v,
    simulate,
    voltmeter_t_ns,
)
from pipeline.simulate.disturbances import DISTURBANCES, make_disturbance
from pipeline.simulate.program import get_program

#: :func:`simulate_run` computes runs of more voltmeter samples than this in chunks (in one piece: ~200 B a sample)
CHUNKED_ABOVE_SAMPLES = 5_000_000


def simulate_run(config: SimConfig, chunked_above_samples: int = CHUNKED_ABOVE_SAMPLES) -> SimResult:
    """A simulated run of any length: :func:`~pipeline.simulate.chamber.simulate` up to ``chunked_above_samples``
    voltmeter samples, :func:`simulate_chunked` above (about 2 GB instead of 12 GB for the 1 kHz standard run) unless
    an effect needs the whole record (not ``local``), which is then simulated in one piece."""
    _check(config)
    n = int(np.floor(get_program(config.program).timetable().duration_s * config.rate_hz)) + 1
    local = all(effect_class(eid).local for eid, _ in config.effects) and all(
        DISTURBANCES[did].local for did, _ in config.disturbances
    )
    return simulate_chunked(config) if n > chunked_above_samples and local else simulate(config)


def simulate_chunked(config: SimConfig, chunk_samples: int = 1_000_000) -> SimResult:
    """:func:`~pipeline.simulate.chamber.simulate` for long runs, computed ``chunk_samples`` voltmeter samples at a
    time.

    Peak memory is the voltmeter table (32 bytes a sample) plus about 200 bytes a sample of one chunk. The result's
    ``context`` is the 1 Hz one (the per-sample context of a long run is what this function avoids building).
    """
    _check(config)
    refused = [eid for eid, _ in config.effects if not effect_class(eid).local] + [
        did for did, _ in config.disturbances if not DISTURBANCES[did].local
    ]
    if refused:
        raise ValueError(f"effects {refused} depend on other samples; use pipeline.simulate.chamber.simulate")
    if int(chunk_samples) < 1:
        raise ValueError(f"chunk_samples must be >= 1, got {chunk_samples}")
    base = simulate(dataclasses.replace(config, rate_hz=THERMAL_RATE_HZ))
    ctx1 = base.context
    assert ctx1 is not None  # simulate() returns the context it simulated with
    timetable = get_program(config.program).timetable()
    effects = [make_effect(eid, params) for eid, params in config.effects]
    disturbances = [make_disturbance(did, params) for did, params in config.disturbances]
    face_rad = _face_rotations_rad(effects)
    noise = np.random.default_rng([config.seed, 1])

    n = int(np.floor(timetable.duration_s * config.rate_hz)) + 1
    t_ns = np.empty(n, dtype=np.int64)
    u_v = {c: np.empty(n) for c in ("ux", "uy", "uz")}
    for k0 in range(0, n, int(chunk_samples)):
        k = np.arange(k0, min(k0 + int(chunk_samples), n))
        t_s = k / config.rate_hz
        t_ns[k] = voltmeter_t_ns(ctx1.start_ns, k, config, noise)
        # simulate() draws the vibration phases first from default_rng(seed): the same phases in every chunk
        a_g, position_idx = _specific_force_g(
            timetable, t_s, face_rad, config.vibration_g, np.random.default_rng(config.seed)
        )
        ctx = SignalContext(
            t_s=t_s,
            temp_c=np.interp(t_s, ctx1.t_s, ctx1.temp_c),
            a_g=a_g,
            position_idx=position_idx,
            move_start_s=ctx1.move_start_s,
            arrive_s=ctx1.arrive_s,
            constants=ctx1.constants,
            normal_temp_c=config.normal_temp_c,
            ramp_sign=timetable.ramp_sign(t_s),
            start_ns=ctx1.start_ns,
        )
        u = output_with_effects_v(ctx, effects, disturbances, config.noise_v, noise)
        for c, name in enumerate(u_v):
            u_v[name][k] = u[:, c]

    run = base.run
    run = Run(
        meta=run.meta,
        voltmeter=make_frame("voltmeter", {"t_ns": t_ns, **u_v}),
        au_temperature=run.au_temperature,
        chamber=run.chamber,
        fixture=run.fixture,
    )
    truth = dict(base.truth, config=dataclasses.asdict(config))
    return SimResult(run=run, truth=truth, context=ctx1)
