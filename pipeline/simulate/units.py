"""Simulated runs of several units in one chamber (log-format.md, "Runs with several units"): ``thermocal simulate
--units N``.

N units of one type on one fixture through one chamber program: each unit its own constants (the first the unit of
``config``, the others random units of the type), its own noise and thermosensor (its own noise draws); the fixture
turns them all together, so the fixture log and the chamber stream are the first unit's, shared. Each unit is
simulated by :func:`pipeline.simulate.large.simulate_run` (in chunks for long runs); the result is a
:class:`pipeline.run.UnitRuns` and each unit's ground truth.
"""

from __future__ import annotations

import dataclasses
import re

from pipeline.run import Run, UnitRuns
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.large import simulate_run

#: the noise seed of unit k > 0 is the run's seed plus k times this (clear of every seed a single run takes)
_UNIT_SEED_STRIDE = 1 << 32


def unit_serials(first: str, n: int) -> list[str]:
    """``n`` serials counting up from ``first``'s last number, its width kept (``AU-0101`` -> ``AU-0101``,
    ``AU-0102``, ...); a serial without a number gets ``-1``, ``-2``, ..."""
    if n < 1:
        raise ValueError(f"the number of units must be at least 1, got {n}")
    m = re.search(r"(\d+)(?!.*\d)", first)
    if m is None:
        return [first] if n == 1 else [f"{first}-{k + 1}" for k in range(n)]
    width, start = len(m.group(1)), int(m.group(1))
    return [f"{first[: m.start()]}{start + k:0{width}d}{first[m.end() :]}" for k in range(n)]


def unit_configs(config: SimConfig, n: int) -> list[SimConfig]:
    """The settings of each of ``n`` units: unit 0 is ``config`` itself; unit k > 0 a random unit of the type (unit
    seed ``config.unit_seed + k``, or ``k`` for the reference unit's run) with its own noise seed."""
    out = []
    for k, serial in enumerate(unit_serials(config.unit_serial, n)):
        if k == 0:
            out.append(config)
            continue
        unit_seed = k if config.unit_seed is None else config.unit_seed + k
        out.append(
            dataclasses.replace(
                config, unit_serial=serial, unit_seed=unit_seed, seed=config.seed + k * _UNIT_SEED_STRIDE
            )
        )
    return out


def simulate_units(config: SimConfig, n: int) -> tuple[UnitRuns, dict[str, dict]]:
    """``n`` units through ``config``'s program in one run: the :class:`UnitRuns` (one run_id, the shared fixture
    log and chamber of unit 0) and each unit's ground truth by serial."""
    configs = unit_configs(config, n)
    run_id = f"sim-{configs[0].unit_serial}-x{n}-s{config.seed}"
    runs, truths = [], {}
    for c in configs:
        res = simulate_run(c)
        r = res.run
        meta = dataclasses.replace(r.meta, run_id=run_id)
        runs.append(
            Run(meta=meta, voltmeter=r.voltmeter, au_temperature=r.au_temperature, chamber=r.chamber, fixture=r.fixture)
        )
        truths[c.unit_serial] = res.truth
        del res
    return UnitRuns.of_units(runs), truths
