"""Bad input (issue 7): every run of the broken corpus (tests/acceptance/badcorpus.py) gives a one-line error naming the
file, the stream and the time or row, or is processed with a warning saying what was dropped, and then still calibrates
to the simulator's truth; ``thermocal`` exits non-zero with that line; ``fleet`` reports the failures and calibrates
the rest; every file of the MCAP conformance corpus is refused by ``inspect`` and ``calibrate``.

Most cases run in-process through the steps the calibration flow runs (read_run, observe_run, fit_unit,
verify_unit); a few go through the Prefect flow and the console script (each console start of Prefect costs
seconds).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate.tilt import CalibrationSettings, fit_unit, observe_run, verify_unit
from pipeline.errors import CalibrationError, RunFormatError, ThermocalError
from pipeline.io.runs import read_run
from tests.acceptance.badcorpus import BLOCK_SAMPLES, CASES, Case, build_corpus, truth_at_normal_temp, valid
from tests.conftest import DATA, run_main

pytestmark = pytest.mark.slow  # an end-to-end proof on long or many recordings

CONFORMANCE = DATA / "mcap-conformance"
THERMOCAL = str(Path(sys.executable).parent / "thermocal")
CASE_BY_NAME = {c.name: c for c in CASES}
#: K (V/g) and U0 (V) at +20 C from a recovered run agree with the truth within this (measured: 0.6e-7 .. 3e-7)
TOL_K_V_PER_G = 1e-6
TOL_U0_V = 1e-6


@pytest.fixture(scope="module")
def corpus_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("badcorpus")


@pytest.fixture(scope="module")
def corpus(corpus_root) -> dict[str, Path]:
    return build_corpus(corpus_root)


def calibrate_in_process(path: Path):
    """The flow's steps on one run, without publishing: (run, unit fit, every warning)."""
    run = read_run(path)
    obs, warnings = observe_run(run)
    fit = fit_unit(run.meta.unit_serial, obs, CalibrationSettings(), run.meta.normal_temp_c)
    verify_unit(fit.model, obs, run.meta.normal_temp_c)
    return run, fit, warnings + fit.skipped


def check_error_line(text: str, path: Path, case: Case) -> None:
    """One line that names the file (or the file inside the run directory), the stream and the place."""
    assert "\n" not in text and text == " ".join(text.split())
    assert text.startswith(str(path)), text
    assert case.stream in text and case.where in text, text
    for fragment in case.says:
        assert fragment in text, text


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("thermocal:")]


# --- the corpus, in-process ---------------------------------------------------------------------------------------


def test_corpus_covers_the_issue():
    """Every kind of broken input the issue lists has at least one case."""
    kinds = [
        "truncated-mid-chunk",
        "no-summary",
        "crc",
        "not-matching-schema",
        "missing-stream",
        "unknown-topics",
        "nan-inf",
        "repeated",
        "conflicting-duplicates",
        "backwards",
        "gap",
        "missing-a-position",
        "never-stabilises",
        "metadata-missing",
        "metadata-malformed",
        "wrong-column-type",
        "empty-file",
        "text-file",
        "foreign-mcap",
    ]
    for kind in kinds:
        assert any(kind in c.name for c in CASES), kind
    assert sum(c.error is None for c in CASES) >= 8 and sum(c.error is not None for c in CASES) >= 20


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_broken_run(corpus, case):
    path = corpus[case.name]
    if case.error is not None:
        with pytest.raises(ThermocalError) as info:
            calibrate_in_process(path)
        assert isinstance(info.value, case.error), repr(info.value)
        check_error_line(str(info.value), path, case)
        return
    run, fit, warnings = calibrate_in_process(path)
    if case.says:
        assert any(all(s in w for s in case.says) for w in warnings), warnings
    else:
        assert warnings == []
    assert all("\n" not in w for w in warnings)
    assert case.calibrates
    K, U0 = fit.model.constants_at(np.array([20.0]))
    K_true, U0_true = truth_at_normal_temp()
    assert np.abs(K[0] - K_true).max() < TOL_K_V_PER_G
    assert np.abs(U0[0] - U0_true).max() < TOL_U0_V


def test_what_is_recovered_is_exactly_the_good_data(corpus):
    """Recovered runs hold the valid run's samples: all of them (no summary, unknown topics, a late block, a
    repeated block), a bit-exact prefix (truncated), or all but the gap."""
    v = valid().run.voltmeter
    for name in ("mcap-no-summary", "mcap-unknown-topics", "mcap-backwards-timestamps", "mcap-repeated-message"):
        got = read_run(corpus[name]).voltmeter
        assert got.equals(v), name
    cut = read_run(corpus["mcap-truncated-mid-chunk"])
    n = cut.voltmeter.height
    assert 0.5 * v.height < n < 0.8 * v.height
    assert cut.voltmeter.equals(v.head(n))
    assert any(f"voltmeter samples up to t_ns={v['t_ns'][n - 1]}" in w for w in cut.warnings)
    gap = read_run(corpus["voltmeter-gap"]).voltmeter
    assert v.height - gap.height == 1500  # 300 s at 5 Hz
    assert gap.join(v, on="t_ns", how="anti").height == 0
    repeated = read_run(corpus["mcap-repeated-message"])
    assert any(f"dropped {BLOCK_SAMPLES} repeated samples" in w for w in repeated.warnings)


def test_a_late_block_changes_nothing_in_the_calibration(corpus):
    """Sorting a block logged out of order, or dropping a repeated one, gives the same constants to the bit."""
    _, ref, _ = calibrate_in_process(corpus["mcap-no-summary"])
    for name in ("mcap-backwards-timestamps", "mcap-repeated-message", "mcap-unknown-topics"):
        _, fit, _ = calibrate_in_process(corpus[name])
        for a, b in zip(ref.per_plateau, fit.per_plateau):
            np.testing.assert_array_equal(a.K, b.K)
            np.testing.assert_array_equal(a.U0, b.U0)


# --- through the flow, the console script and fleet ---------------------------------------------------------------

FLOW_CASES = (
    "mcap-corrupt-chunk-crc",
    "mcap-message-not-matching-schema",
    "clock-jump",
    "parquet-null-timestamp",
    "no-plateau-with-six-positions",
    "temperature-never-stabilises",
)


def test_calibrate_command_in_process(corpus, tmp_path, monkeypatch, capsys):
    """``thermocal calibrate`` (its main(), the Prefect flow): exit 2 and the same line as in-process for broken
    runs, nothing written to the registry; a truncated run is calibrated, with its warning, exit 0 (1 when its
    status is fail, the JSON printed all the same)."""
    registry = tmp_path / "reg"
    for name in FLOW_CASES:
        path = corpus[name]
        with pytest.raises(ThermocalError) as info:
            calibrate_in_process(path)
        # the tilt recipe, as in-process (--method auto may take another method where tilt has too few positions)
        code, out, err = run_main(
            monkeypatch, capsys, "calibrate", str(path), "--registry", str(registry), "--method", "tilt"
        )
        assert code == 2, (name, err)
        assert error_lines(err) == [f"thermocal: error: {info.value.one_line()}"], err
        assert out == ""
    assert not (registry / "units").exists() or not any((registry / "units").iterdir())
    path = corpus["mcap-truncated-mid-chunk"]
    code, out, err = run_main(monkeypatch, capsys, "calibrate", str(path), "--registry", str(registry), "--json")
    result = json.loads(out)
    assert code == (1 if result["status"] == "fail" else 0), err  # docs/contract.md: a fail exits 1
    assert result["version"] == 1 and result["unit"] == read_run(path).meta.unit_serial
    assert any("truncated at byte" in w and "kept" in w for w in result["warnings"])


def test_console_script_refuses_broken_runs(corpus, tmp_path):
    """The real console script: ``inspect`` (no Prefect) prints exactly one line; ``calibrate`` exits 2 with the
    one-line reason."""
    for name in ("mcap-corrupt-chunk-crc", "parquet-wrong-column-type", "lfs-pointer"):
        proc = subprocess.run([THERMOCAL, "inspect", str(corpus[name])], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and proc.stdout == "", proc.stderr
        [line] = proc.stderr.splitlines()
        assert line.startswith(f"thermocal: error: {corpus[name]}")
        assert all(s in line for s in CASE_BY_NAME[name].says)
    path = corpus["temperature-never-stabilises"]
    proc = subprocess.run(
        [THERMOCAL, "calibrate", str(path), "--registry", str(tmp_path / "reg"), "--method", "tilt"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 2, proc.stderr
    [line] = error_lines(proc.stderr)
    assert line.startswith(f"thermocal: error: {path}: au_temperature: t_ns=")
    assert "no temperature plateau" in line and "internal error" not in proc.stderr


def test_fleet_reports_every_broken_run_and_calibrates_the_rest(corpus_root, corpus, tmp_path):
    """``fleet`` over the whole corpus: each broken run is a failure with its one-line reason (never an internal
    error), each recoverable run a new passport."""
    fleet = pytest.importorskip("flows.fleet")
    summary = fleet.run_fleet(str(corpus_root), str(tmp_path / "reg"), pool="thread", workers=4)
    failed = {Path(f["run"]).resolve(): f["reason"] for f in summary["failed"]}
    done = {Path(r).resolve() for d in summary["done"] for r in d["runs"]}
    assert not any(r.startswith("internal error") for r in failed.values()), failed
    for case in CASES:
        path = corpus[case.name].resolve()
        if case.name in ("csv-file", "empty-directory"):  # not run files: fleet does not pick them up
            assert path not in failed and path not in done
        elif case.error is None:
            assert path in done, (case.name, failed.get(path))
        else:
            assert path in failed, case.name
            reason = failed[path]
            assert "\n" not in reason and reason.startswith(str(corpus[case.name])), reason
            if case.error is CalibrationError:  # found past planning: the very line ``calibrate`` prints
                with pytest.raises(CalibrationError) as info:
                    calibrate_in_process(corpus[case.name])
                assert reason == info.value.one_line()
    assert len(summary["done"]) == sum(c.error is None for c in CASES)


# --- the MCAP conformance corpus ----------------------------------------------------------------------------------


def conformance_files() -> list[Path]:
    return sorted(p for p in CONFORMANCE.rglob("*.mcap"))


def test_conformance_corpus_refused_by_inspect(monkeypatch, capsys):
    """``thermocal inspect`` (main(), in-process) on every file: exit 2, one line naming the file and why."""
    files = conformance_files()
    assert len(files) >= 400
    for path in files:
        code, out, err = run_main(monkeypatch, capsys, "inspect", str(path))
        assert code == 2 and out == "", (path, err)
        [line] = err.splitlines()
        assert line.startswith(f"thermocal: error: {path}: ")
        if path.parent == CONFORMANCE:  # beside the scenario folders: its README and licence, text files
            assert "not an MCAP file" in line, line
        else:
            assert "no run topics or run metadata found" in line or "Git LFS pointer" in line, line


def test_conformance_corpus_refused_by_calibrate(tmp_path, monkeypatch, capsys):
    """``calibrate`` refuses every file at its first step (the ingest task is read_run); a few go through the
    whole command (the Prefect flow), one through the console script."""
    files = conformance_files()
    for path in files:
        with pytest.raises(RunFormatError) as info:
            read_run(path)
        assert str(info.value).startswith(f"{path}: ")
    registry = tmp_path / "reg"
    for path in files[:: len(files) // 3][:3]:
        code, out, err = run_main(monkeypatch, capsys, "calibrate", str(path), "--registry", str(registry))
        assert code == 2 and error_lines(err) == [f"thermocal: error: {read_error(path)}"], err
    proc = subprocess.run([THERMOCAL, "inspect", str(files[-1])], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.startswith(f"thermocal: error: {files[-1]}: ")
    assert not registry.exists() or not any(registry.rglob("*.json"))


def read_error(path: Path) -> str:
    try:
        read_run(path)
    except ThermocalError as exc:
        return exc.one_line()
    raise AssertionError(f"{path} was read as a run")


def test_real_mcap_files_of_the_conformance_kinds_are_refused_by_inspect(tmp_path, monkeypatch, capsys):
    """Real MCAP files written like the corpus's (every writer option combination; test_io builds them) through
    ``inspect``: refused as not a run, one line."""
    from mcap.writer import Writer

    from tests.io.test_io import _conformance_like_variants

    for k, opts in enumerate(_conformance_like_variants()):
        path = tmp_path / f"variant-{k}.mcap"
        with open(path, "wb") as f:
            w = Writer(f, **opts)
            w.start(profile="", library="")
            cid = w.register_channel("example", "a", w.register_schema("Example", "c", b"\x04\x05\x06"))
            w.add_message(cid, 2, b"\x01\x02\x03", 1, 10)
            w.add_metadata("myMetadata", {"foo": "bar"})
            w.finish()
        code, _, err = run_main(monkeypatch, capsys, "inspect", str(path))
        assert code == 2 and err.splitlines() == [
            f"thermocal: error: {path}: no run topics or run metadata found: not a thermocal chamber run (expected "
            "metadata 'run' and topics /voltmeter, /au/temperature, /chamber, /fixture; topics in the file: "
            "example)"
        ], err
