"""Which runs a calibration takes: same run_id never merged (truncated copy dropped, conflicting both dropped);
a folder name naming another unit warns; several files of one unit are one recording (joined in time order)."""

from __future__ import annotations

from dataclasses import replace

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.calibrate.inputs import RunInput, folder_warning, is_prefix_of, resolve_run_ids
from pipeline.io.runs import read_run, write_run
from pipeline.simulate.chamber import SimConfig
from pipeline.simulate.large import simulate_run
from tests.conftest import run_piece


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A short 2 Hz run as MCAP, a truncated copy of it (cut mid-file), and another recording with its run_id."""
    d = tmp_path_factory.mktemp("inputs")
    run = simulate_run(SimConfig(program="short", rate_hz=2.0, seed=1)).run
    full = write_run(run, d / "full.mcap", "mcap", chunk_size=1 << 15)
    cut = d / "copy-truncated.mcap"
    data = full.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    other_run = simulate_run(SimConfig(program="short", rate_hz=2.0, seed=2)).run
    other = write_run(replace(other_run, meta=run.meta), d / "other.mcap", "mcap")
    return run.meta, full, cut, other


def test_truncated_copy_is_a_prefix(runs):
    _, full, cut, other = runs
    a, b, c = read_run(full), read_run(cut), read_run(other)
    assert 0.3 * a.voltmeter.height < b.voltmeter.height < a.voltmeter.height
    assert is_prefix_of(b, a) and is_prefix_of(a, a) and not is_prefix_of(a, b) and not is_prefix_of(c, a)


def test_truncated_copy_is_dropped_and_the_complete_file_used(runs):
    meta, full, cut, _ = runs
    items = [
        RunInput(str(cut), meta.unit_serial, meta.run_id),
        RunInput(str(full), meta.unit_serial, meta.run_id),
        RunInput("/elsewhere/vp.mcap", meta.unit_serial, "another-run"),
    ]
    kept, failed = resolve_run_ids(items, read_run)
    assert [k.path for k in kept] == [str(full), "/elsewhere/vp.mcap"]
    [f] = failed
    assert f["run"] == str(cut) and "truncated copy of " + str(full) in f["reason"] and meta.run_id in f["reason"]
    assert "\n" not in f["reason"]


def test_same_run_id_with_other_samples_uses_neither(runs):
    meta, full, _, other = runs
    items = [RunInput(str(full), meta.unit_serial, meta.run_id), RunInput(str(other), meta.unit_serial, meta.run_id)]
    kept, failed = resolve_run_ids(items, read_run)
    assert kept == [] and [f["run"] for f in failed] == [str(full), str(other)]
    assert str(other) in failed[0]["reason"] and str(full) in failed[1]["reason"]
    assert all("neither is used" in f["reason"] for f in failed)


def test_distinct_run_ids_are_not_read():
    items = [RunInput(f"/x/{k}.mcap", "AU-0001", f"run-{k}") for k in range(3)]
    assert resolve_run_ids(items, read=lambda p: pytest.fail("read")) == (items, [])


@pytest.mark.parametrize(
    "path, serial, warns",
    [
        ("/inbox/AU-0002/tp.mcap", "AU-0001", "says unit AU-0002 but its metadata says AU-0001"),
        ("/inbox/AU-0001/tp.mcap", "AU-0001", None),
        ("/inbox/2026-11-01-ch2-AU-0003.mcap", "AU-0001", "says unit AU-0003"),
        ("/inbox/AU-0002/run-AU-0001.mcap", "AU-0001", None),  # the file names its own unit
        ("/inbox/chamber-2/tp.mcap", "AU-0001", None),  # nothing shaped like a serial
    ],
)
def test_folder_name_naming_another_unit_warns(path, serial, warns):
    got = folder_warning(path, serial, "/inbox")
    assert (got is None) if warns is None else (warns in got and got.startswith(path))


# ---------------------------------------------------------------------------------------------------------------
# several files of one unit are one recording (issue 21, item 3)


@pytest.fixture(scope="module")
def small_run():
    """Ten minutes of the short program at 2 Hz: every stream, a fixture log."""
    import polars as pl

    run = simulate_run(SimConfig(program="short", rate_hz=2.0, seed=4)).run
    t0 = int(run.voltmeter["t_ns"][0])
    t1 = t0 + 3_600 * 10**9
    keep = lambda df: df.filter(pl.col("t_ns") < t1)  # noqa: E731
    return replace(
        run,
        voltmeter=keep(run.voltmeter),
        au_temperature=keep(run.au_temperature),
        chamber=keep(run.chamber),
        fixture=keep(run.fixture),
    )


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    cuts=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=4),
    overlap_s=st.sampled_from([0.0, 0.0, 7.5, 300.0]),
    order=st.randoms(use_true_random=False),
)
def test_files_of_one_recording_join_into_the_whole_run(small_run, cuts, overlap_s, order):
    """A run cut into files at any times (a cut may fall inside a hold or a plateau), the files overlapping by a
    stretch they share exactly or not at all, given in any order: join_runs gives back the whole run's streams,
    every sample once, and names the files' run_ids in time order."""
    from pipeline.calibrate.inputs import join_runs

    t = small_run.voltmeter["t_ns"].to_numpy()
    edges = sorted({int(t[0] + c * (t[-1] - t[0])) for c in cuts})
    bounds = [int(t[0])] + edges + [int(t[-1]) + 1]
    bounds = [b for k, b in enumerate(bounds) if k == 0 or b > bounds[k - 1]]
    pieces = [
        run_piece(small_run, a - (int(overlap_s * 1e9) if k else 0), b, f"part-{k}", source=f"part-{k}.mcap")
        for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:]))
    ]
    pieces = [p for p in pieces if p.voltmeter.height]
    given_order = pieces[:]
    order.shuffle(given_order)
    joined = join_runs(given_order)
    for name in ("voltmeter", "au_temperature", "chamber", "fixture"):
        assert joined.stream(name).equals(small_run.stream(name)), name
    by_start = sorted(pieces, key=lambda p: (int(p.voltmeter["t_ns"][0]), -int(p.voltmeter["t_ns"][-1])))
    assert joined.meta.run_id == "+".join(p.meta.run_id for p in by_start)
    assert joined.meta.unit_serial == small_run.meta.unit_serial


def test_one_file_is_its_own_recording(small_run):
    from pipeline.calibrate.inputs import join_runs

    assert join_runs([small_run]) is small_run


def test_two_files_with_other_samples_at_one_time_are_refused(small_run):
    """Files that claim one stretch of time with other samples (not a copy of each other's part): one line naming
    both and the time, neither used."""
    import polars as pl

    from pipeline.calibrate.inputs import join_runs
    from pipeline.errors import CalibrationError

    t = small_run.voltmeter["t_ns"].to_numpy()
    a = run_piece(small_run, int(t[0]), int(t[600]), "a", source="a.mcap")
    b = run_piece(small_run, int(t[500]), int(t[-1]) + 1, "b", source="b.mcap")
    b = replace(b, voltmeter=b.voltmeter.with_columns(pl.col("uz") + 1e-6))
    with pytest.raises(CalibrationError) as info:
        join_runs([b, a])
    line = info.value.one_line()
    assert "a.mcap and b.mcap hold other samples" in line and f"t_ns={t[500]}" in line and "\n" not in line
    # the same times, sampled between the other file's samples (an interleaved second recording)
    shifted = replace(b, voltmeter=b.voltmeter.with_columns(pl.col("t_ns") + 250_000_000))
    with pytest.raises(CalibrationError, match="hold other samples"):
        join_runs([a, shifted])


def test_files_of_one_recording_agree_on_how_it_is_calibrated(small_run):
    from pipeline.calibrate.inputs import join_runs
    from pipeline.errors import CalibrationError

    t = small_run.voltmeter["t_ns"].to_numpy()
    a = run_piece(small_run, int(t[0]), int(t[600]), "a", source="a.mcap")
    b = run_piece(small_run, int(t[600]), int(t[-1]) + 1, "b", source="b.mcap")
    with pytest.raises(CalibrationError, match="disagree on 'normal_temp_c'.*a.mcap: 20.0, b.mcap: 25.0"):
        join_runs([a, replace(b, meta=replace(b.meta, normal_temp_c=25.0))])
    with pytest.raises(CalibrationError, match="disagree on 'unit_grade'"):
        join_runs([a, replace(b, meta=replace(b.meta, unit_grade="consumer"))])


def test_the_files_a_logger_wrote_one_recording_into_are_all_used(small_run):
    """A logger that writes one recording into several files puts the recording's run_id in each: the pieces (one
    cut inside a hold, two overlapping by samples they share exactly), given in any order beside a truncated copy of
    one, are all used (the copy left out, with a warning) and join into the whole run. Two files with other samples
    over one stretch of time under that id are still refused, the line naming the stream and the time."""
    import polars as pl

    from pipeline.calibrate.inputs import join_runs, select_runs
    from pipeline.errors import CalibrationError

    t = small_run.voltmeter["t_ns"].to_numpy()
    rid = small_run.meta.run_id
    a = run_piece(small_run, int(t[0]), int(t[2000]), rid, source="a.mcap")
    b = run_piece(small_run, int(t[1900]), int(t[5000]), rid, source="b.mcap")  # shares 100 samples with a
    c = run_piece(small_run, int(t[5000]), int(t[-1]) + 1, rid, source="c.mcap")
    c_cut = run_piece(small_run, int(t[5000]), int(t[6000]), rid, source="c-truncated.mcap")
    kept, warnings = select_runs([c, c_cut, a, b])
    assert [r.source for r in kept] == ["c.mcap", "a.mcap", "b.mcap"]
    [w] = warnings
    assert w.startswith("c-truncated.mcap: a truncated copy of c.mcap")
    joined = join_runs(kept)
    for name in ("voltmeter", "au_temperature", "chamber", "fixture"):
        assert joined.stream(name).equals(small_run.stream(name)), name
    assert joined.meta.run_id == rid
    other = replace(b, voltmeter=b.voltmeter.with_columns(pl.col("uz") + 1e-6), source="other.mcap")
    with pytest.raises(CalibrationError) as info:
        select_runs([a, b, other])
    line = info.value.one_line()
    assert "neither is used" in line and f"voltmeter, t_ns={t[1900]}" in line and "\n" not in line


def test_a_file_without_the_fixture_log_is_not_labelled_with_the_one_before(small_run):
    """The files of one recording, the middle one (TP2..TP4 held at +20 C) without a fixture log: the log says
    nothing then, so the position it logged before (TP1) is not carried through that file. Before: one 'fixture
    label conflict ... fixture log says TP1' per hold of the middle file; the positions came from gravity all the
    same. Now no conflict, the same named segments as the whole run's."""
    from pipeline.calibrate.inputs import join_runs
    from pipeline.segment import segment_run

    t0 = int(small_run.voltmeter["t_ns"][0])
    cut = [t0 + int(s * 1e9) for s in (950.0, 1200.0)]
    a = run_piece(small_run, t0, cut[0], "a", source="a.mcap")
    b = run_piece(small_run, cut[0], cut[1], "b", source="b.mcap", fixture=None)
    c = run_piece(small_run, cut[1], t0 + 10**13, "c", source="c.mcap")
    joined = join_runs([c, b, a])
    got, whole = segment_run(joined), segment_run(small_run)
    assert not [w for w in got.warnings if "conflict" in w], got.warnings
    tb = b.voltmeter["t_ns"]
    assert joined.unlogged_ns == ((int(tb[0]), int(tb[-1])),)
    names = lambda seg: [(s.t_start_ns, s.position) for s in seg.segments]  # noqa: E731
    assert names(got) == names(whole)
    held = {s.position for s in got.segments if cut[0] <= s.t_start_ns < cut[1]}
    assert {"TP2", "TP3", "TP4"} <= held
    # the middle file's log there but empty (no move logged in it): TP1 holds on through it, as logged
    empty = replace(b, fixture=small_run.fixture.head(0))
    assert join_runs([a, empty, c]).unlogged_ns == ()
