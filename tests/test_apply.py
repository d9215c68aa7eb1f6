"""``apply``: a passport's full model applied to every voltmeter sample (contract.md, "apply output")."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline import compensate
from pipeline.apply import APPLY_COLUMNS, apply_passport, valid_range_c, write_applied
from pipeline.calibrate.tilt import fit_unit, observe_run, verify_unit
from pipeline.passport.document import build_passport, load_model
from pipeline.run import Run
from pipeline.simulate.chamber import SimConfig, simulate

T0 = 20.0


@pytest.fixture(scope="module")
def passport():
    """A tilt passport (poly3 thermal model) of a short-program run at 2 Hz."""
    run = simulate(SimConfig(program="short", seed=8, rate_hz=2.0)).run
    obs, _ = observe_run(run)
    fit = fit_unit("AU-0001", obs)
    rows, status = verify_unit(fit.model, obs, T0)
    return build_passport(fit, rows, status, g_local_mps2=9.80665, plateaus=[])


@pytest.fixture(scope="module")
def other():
    """Another run of the unit (other noise), with a few non-finite voltages."""
    res = simulate(SimConfig(program="short", seed=9, rate_hz=2.0))
    v = res.run.voltmeter.with_columns(pl.when(pl.int_range(pl.len()).is_in([5, 6, 700])).then(float("nan"))
                                       .otherwise(pl.col("uy")).alias("uy"))
    run = Run(meta=res.run.meta, voltmeter=v, au_temperature=res.run.au_temperature, chamber=res.run.chamber,
              fixture=res.run.fixture)
    return run, res.truth


def test_apply_holds_gravity_at_every_hold(passport, other):
    """At every hold of the held-out run (-40..+70 C) the compensated |a| is 1 g within 150 micro-g, and the
    specific force is the held position's within 2 mg (the fixture's face: 0 here)."""
    run, truth = other
    out = apply_passport(passport, run)
    t = out.table
    assert t.columns == list(APPLY_COLUMNS) and t.height == run.voltmeter.height
    assert t["t_ns"].to_list() == run.voltmeter["t_ns"].to_list()
    a = t.select("ax_g", "ay_g", "az_g").to_numpy()
    for h in truth["holds"]:
        sel = (t["t_ns"] > h["t_start_ns"] + 20 * 10**9).to_numpy() & (t["t_ns"] < h["t_end_ns"]).to_numpy()
        m = np.nanmean(a[sel], axis=0)
        assert abs(np.linalg.norm(m) - 1.0) < 1.5e-4, h
        assert np.allclose(m, truth["position_vectors_g"][h["position"]], atol=2e-3)


def test_apply_is_method_1_of_the_passport_model(passport, other):
    """Row for row the same as compensation method 1 with the passport's thermal model at the interpolated
    thermosensor temperature; non-finite inputs give NaN rows, never dropped ones."""
    run, _ = other
    t = apply_passport(passport, run).table
    temp = np.interp(run.t_ns().astype(float), run.au_temperature["t_ns"].to_numpy().astype(float),
                     run.au_temperature["temp_c"].to_numpy())
    ref = compensate.method1(load_model(passport), run.u_v(), temp)
    a = t.select("ax_g", "ay_g", "az_g").to_numpy()
    bad = ~np.isfinite(run.u_v()).all(axis=1)
    assert bad.sum() == 3 and np.isnan(a[bad]).all(axis=1).all()
    assert np.allclose(a[~bad], ref[~bad], rtol=0, atol=1e-12)
    assert np.allclose(t["temp_c"].to_numpy(), temp)


def test_in_range_and_one_warning(passport, other):
    run, _ = other
    assert valid_range_c(passport) == pytest.approx((-40.0, 70.0), abs=0.5)     # from the plateaus
    narrow = dict(passport, valid_temp_c=[0.0, 30.0])
    out = apply_passport(narrow, run)
    temp = out.table["temp_c"].to_numpy()
    assert (out.table["in_range"].to_numpy() == ((temp >= 0.0) & (temp <= 30.0))).all()
    assert 0 < (~out.table["in_range"].to_numpy()).sum() < out.table.height
    assert len(out.warnings) == 1 and "outside the passport's valid temperature range 0 .. 30 C" in out.warnings[0]
    assert apply_passport(dict(passport, valid_temp_c=[-45.0, 75.0]), run).warnings == []


def test_write_parquet_and_mcap(passport, other, tmp_path):
    run, _ = other
    out = apply_passport(passport, run)
    pq = write_applied(out, tmp_path / "a.parquet", passport=passport, run=run)
    back = pl.read_parquet(pq)
    assert back.columns == list(APPLY_COLUMNS) and back.height == run.voltmeter.height
    assert back["in_range"].dtype == pl.Boolean
    mc = write_applied(out, tmp_path / "a.mcap", passport=passport, run=run)
    from mcap.reader import make_reader
    import json

    with open(mc, "rb") as f:
        rows = sum(len(json.loads(m.data)["t_ns"]) for _, _, m in make_reader(f).iter_messages())
    assert rows == run.voltmeter.height
    assert not list(tmp_path.glob(".*partial"))
