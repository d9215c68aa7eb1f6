"""``apply``: a passport's full model applied to every voltmeter sample (docs/contract.md, "apply output")."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from pipeline import compensate
from pipeline.apply import APPLY_COLUMNS, apply_passport, write_applied
from pipeline.calibrate.tilt import fit_unit, observe_run, verify_unit
from pipeline.io.runs import write_run
from pipeline.passport.document import build_passport, load_model, load_passport
from pipeline.run import Run
from pipeline.simulate.chamber import SimConfig, simulate
from pipeline.utc import utc_text
from tests.conftest import run_main

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
    v = res.run.voltmeter.with_columns(
        pl.when(pl.int_range(pl.len()).is_in([5, 6, 700])).then(float("nan")).otherwise(pl.col("uy")).alias("uy")
    )
    run = Run(
        meta=res.run.meta,
        voltmeter=v,
        au_temperature=res.run.au_temperature,
        chamber=res.run.chamber,
        fixture=res.run.fixture,
    )
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
    temp = np.interp(
        run.t_ns().astype(float),
        run.au_temperature["t_ns"].to_numpy().astype(float),
        run.au_temperature["temp_c"].to_numpy(),
    )
    ref = compensate.method1(load_model(passport), run.u_v(), temp)
    a = t.select("ax_g", "ay_g", "az_g").to_numpy()
    bad = ~np.isfinite(run.u_v()).all(axis=1)
    assert bad.sum() == 3 and np.isnan(a[bad]).all(axis=1).all()
    assert np.allclose(a[~bad], ref[~bad], rtol=0, atol=1e-12)
    assert np.allclose(t["temp_c"].to_numpy(), temp)


def test_in_range_and_one_warning(passport, other):
    run, _ = other
    assert load_passport(passport).valid_range_c == pytest.approx((-40.0, 70.0), abs=0.5)  # from the plateaus
    narrow = dict(passport, valid_temp_c=[0.0, 30.0])
    out = apply_passport(narrow, run)
    temp = out.table["temp_c"].to_numpy()
    assert (out.table["in_range"].to_numpy() == ((temp >= 0.0) & (temp <= 30.0))).all()
    assert 0 < (~out.table["in_range"].to_numpy()).sum() < out.table.height
    assert len(out.warnings) == 1 and "outside the passport's valid temperature range 0 .. 30 C" in out.warnings[0]
    first = int(out.table.filter(~pl.col("in_range"))["t_ns"][0])  # the time for people: UTC, not raw t_ns
    assert f"(the first at {utc_text(first)})" in out.warnings[0] and "t_ns" not in out.warnings[0]
    assert apply_passport(dict(passport, valid_temp_c=[-45.0, 75.0]), run).warnings == []
    failed = apply_passport(dict(passport, valid_temp_c=[-45.0, 75.0], status="fail"), run).warnings
    assert len(failed) == 1 and "failed its verification (status fail)" in failed[0]
    # another unit's passport: applied, with one line naming both (was silent: a consumer unit's passport on a
    # navigation unit's run, exit 0 and no word)
    (other_unit,) = apply_passport(dict(passport, valid_temp_c=[-45.0, 75.0], unit="CU-0001"), run).warnings
    assert other_unit.startswith("the passport is unit CU-0001's (v") and "the run records unit AU-0001" in other_unit


def test_write_parquet_and_mcap(passport, other, tmp_path):
    run, _ = other
    out = apply_passport(passport, run)
    pq = write_applied(out, tmp_path / "a.parquet", passport=passport, run=run)
    back = pl.read_parquet(pq)
    assert back.columns == list(APPLY_COLUMNS) and back.height == run.voltmeter.height
    assert back["in_range"].dtype == pl.Boolean
    mc = write_applied(out, tmp_path / "a.mcap", passport=passport, run=run)
    import json

    from mcap.reader import make_reader

    with open(mc, "rb") as f:
        rows = sum(len(json.loads(m.data)["t_ns"]) for _, _, m in make_reader(f).iter_messages())
    assert rows == run.voltmeter.height
    csv = write_applied(out, tmp_path / "a.CSV", passport=passport, run=run)  # the suffix in any case
    head = csv.read_text().splitlines()[:6]
    assert head[0] == "# thermocal.passport_unit: AU-0001"
    assert head[4] == "# thermocal.passport_verification: not checked"
    assert head[5] == ",".join(APPLY_COLUMNS)
    assert_frame_equal(pl.read_csv(csv, comment_prefix="#"), out.table)  # every value back to the bit, NaN as NaN
    assert not list(tmp_path.glob(".*partial"))


@pytest.mark.parametrize("run_id", ["lab run 7\nx,y,z\n1,2,3", "r\r\n# thermocal.valid_temp_c: -99,99", "tab\there"])
def test_csv_metadata_is_one_line_a_key_whatever_the_run_id_holds(passport, other, tmp_path, run_id):
    """A run_id (free text in the run's metadata) with a newline wrote lines of its own into the CSV's head: 'x,y,z'
    read as the header row (polars: 'found more fields than defined in Schema'), or a forged '# thermocal.' line.
    Now each key is one line, its control characters escaped as the terminal output escapes them (printable): the
    five keys, then the columns, the table back to the bit."""
    import dataclasses

    run, _ = other
    run = dataclasses.replace(run, meta=dataclasses.replace(run.meta, run_id=run_id))
    out = apply_passport(passport, run)
    csv = write_applied(out, tmp_path / "a.csv", passport=passport, run=run)
    head = csv.read_text().splitlines()[:6]
    assert [h.split(":")[0] for h in head[:5]] == [
        f"# thermocal.{k}"
        for k in ("passport_unit", "passport_version", "run_id", "valid_temp_c", "passport_verification")
    ]
    escaped = run_id.replace("\n", "\\x0a").replace("\r", "\\x0d").replace("\t", "\\x09")
    assert head[2] == f"# thermocal.run_id: {escaped}"
    assert head[5] == ",".join(APPLY_COLUMNS)
    assert_frame_equal(pl.read_csv(csv, comment_prefix="#"), out.table)


def test_cli_writes_csv_and_refuses_a_name_of_no_format(passport, other, tmp_path, monkeypatch, capsys):
    """``apply --out x.csv`` wrote a Parquet file named x.csv (any name but .mcap was Parquet); now CSV, and a name
    of a format apply does not write (.json, .xlsx) is refused in one line, exit 2, before anything is read."""
    import json

    run, _ = other
    run_file = write_run(run, tmp_path / "run.mcap", "mcap")
    passport_file = tmp_path / "passport.json"
    passport_file.write_text(json.dumps(passport))
    for name in ("x.json", "x.xlsx"):
        code, out, err = run_main(monkeypatch, capsys, "apply", str(passport_file), str(run_file), "--out", name)
        assert (code, out) == (2, "") and err.count("\n") == 1, err
        assert f"{name}: apply writes Parquet (.parquet, .pq or no suffix), MCAP (.mcap) or CSV (.csv)" in err
        assert not (tmp_path / name).exists()
    target = tmp_path / "applied.csv"
    code, out, err = run_main(
        monkeypatch, capsys, "apply", str(passport_file), str(run_file), "--out", str(target), "--unverified"
    )
    assert code == 0, err
    back = pl.read_csv(target, comment_prefix="#")
    assert back.columns == list(APPLY_COLUMNS) and back.height == run.voltmeter.height
    assert "# thermocal.passport_verification: UNVERIFIED (--unverified): " in target.read_text()


@pytest.fixture(scope="module")
def diagnosed():
    """A run with hysteresis and zero-offset drift (1 uV noise), diagnosed against a passport of a clean run of the
    unit: (the base passport, the passport extended by diagnose, the run, the simulator's signal context)."""
    from pipeline.diagnose.diagnosis import diagnose_run, fit_passport
    from pipeline.diagnose.signal import segment_settings_for
    from pipeline.segment import segment_run

    calib = simulate(SimConfig(program="short", rate_hz=2.0, seed=5)).run
    base = fit_passport(calib, segment_run(calib, segment_settings_for(calib)))
    res = simulate(
        SimConfig(
            program="short",
            rate_hz=2.0,
            seed=6,
            noise_v=1e-6,
            effects=[
                ("thermal_hysteresis", {"h_v": [20e-6, -15e-6, 10e-6]}),
                ("time_drift", {"r_v_per_h": [4e-6, -3e-6, 2e-6]}),
            ],
        )
    )
    extended = diagnose_run(res.run, base).passport
    assert {e["effect"] for e in extended.document["extended_model"]["effects"]} == {"thermal_hysteresis", "time_drift"}
    return base, extended, res.run, res.context


def _static_error_ug(applied, ctx) -> np.ndarray:
    a = applied.table.select("ax_g", "ay_g", "az_g").to_numpy()
    static = ctx.position_idx >= 0
    return np.sqrt(np.mean((a[static] - ctx.a_g[static]) ** 2, axis=0)) * 1e6


def test_extended_passport_applies_its_time_and_temperature_terms(diagnosed):
    """apply of a passport extended by diagnose evaluates the extended model from the recording's own columns
    (time since its start, the direction of the last ramp): sample for sample what diagnose's model gives with the
    simulator's full context (median 1.5 micro-g; the ramp direction is known from the setpoint, the simulator's to
    the sample), and against the true specific force at the holds 2-3 micro-g RMS where the base model leaves
    20-40 (was: the base model, with a warning)."""
    from pipeline.passport.document import compensate_extended

    base, extended, run, ctx = diagnosed
    out = apply_passport(extended, run)
    assert not any("extended" in w for w in out.warnings), out.warnings
    ours, theirs = _static_error_ug(out, ctx), _static_error_ug(apply_passport(base, run), ctx)
    assert np.all(ours < 4.0) and np.all(theirs > 15.0), (ours, theirs)
    a = out.table.select("ax_g", "ay_g", "az_g").to_numpy()
    full = compensate_extended(extended, run.u_v(), ctx)
    dev = np.abs(a - full)[ctx.position_idx >= 0].max(axis=1) * 1e6
    assert np.median(dev) < 1.5 and np.percentile(dev, 90) < 5.0, (np.median(dev), np.percentile(dev, 90))


def test_extended_terms_that_need_the_fixture_are_named_in_one_warning(diagnosed):
    """A settling term needs the fixture's moves, which apply does not locate: left out, the rest applied, and one
    warning line says which term and why."""
    _, extended, run, _ = diagnosed
    ext_model = dict(extended.document["extended_model"])
    ext_model["effects"] = [
        *ext_model["effects"],
        {"effect": "tilt_settling", "parameters": {"f": 1e-4, "tau_s": 20.0}},
    ]
    out = apply_passport({**extended.document, "extended_model": ext_model}, run)
    said = [w for w in out.warnings if "extended model" in w]
    assert len(said) == 1 and "\n" not in said[0]
    assert "without tilt_settling" in said[0] and "fixture's moves" in said[0]
    same = apply_passport(extended, run).table.select("ax_g", "ay_g", "az_g").to_numpy()
    assert np.array_equal(out.table.select("ax_g", "ay_g", "az_g").to_numpy(), same, equal_nan=True)
