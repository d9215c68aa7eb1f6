"""Short-soak and missing-position programs made from the standard one (issue 14): ``variant`` and
``thermocal simulate --soak-min N --drop POS@TEMP[#K]``."""

from __future__ import annotations

import json

import pytest

from pipeline.io.runs import read_run
from pipeline.segment import segment_run
from pipeline.simulate.program import Soak, parse_drop, standard_program, variant
from tests.conftest import run_main


def _holds(prog) -> list[tuple[float, str]]:
    """(setpoint C, position) of every hold, in program order."""
    return [(h.setpoint_start_c, h.position) for h in prog.timetable().holds()]


def test_soaks_shortened_and_positions_dropped():
    std = standard_program()
    short = variant(std, soak_s=1200.0, drop=("TP4@-40", "VP3@+20#2"))
    soaks = [s.duration_s for s in short.steps() if isinstance(s, Soak)]
    assert soaks == [1200.0] * 7 and len([s for s in std.steps() if isinstance(s, Soak)]) == 7
    left = _holds(std)
    left.remove((-40.0, "TP4"))
    k = [i for i, h in enumerate(left) if h == (20.0, "VP3")]
    assert len(k) == 2  # +20 C holds VP3 in its second and third stages
    del left[k[0]]  # the second stage at +20 C (the first holds no VP)
    assert _holds(short) == left
    assert short.timetable().duration_s == pytest.approx(
        std.timetable().duration_s - 2 * 320.0 - 5 * 2400.0 - 2 * 4200.0
    )
    assert short.name == "standard+soak20min-TP4@-40-VP3@+20#2"
    # every stage at +20 C; no soak at all; the program's own positions and holds otherwise untouched
    assert (20.0, "TP1") not in _holds(variant(std, drop=("TP1@20",)))
    assert not [s for s in variant(std, soak_s=0.0).steps() if isinstance(s, Soak)]


@pytest.mark.parametrize(
    "spec, says",
    [
        ("TP4", "expected POSITION@TEMPERATURE"),
        ("TP9@-40", "unknown position 'TP9'"),
        ("TP4@cold", "expected POSITION@TEMPERATURE"),
        ("TP4@-40#0", "counts from 1"),
    ],
)
def test_bad_drop_specs(spec, says):
    with pytest.raises(ValueError, match=says):
        parse_drop(spec)


def test_a_position_the_program_does_not_hold_there_is_refused():
    with pytest.raises(ValueError, match="holds no such position at that setpoint: VP1@-40"):
        variant(standard_program(), drop=("VP1@-40",))
    with pytest.raises(ValueError, match="TP1@20#4"):
        variant(standard_program(), drop=("TP1@20#4",))
    with pytest.raises(ValueError, match="soak must be >= 0"):
        variant(standard_program(), soak_s=-1.0)


def test_cli_writes_the_variant_and_the_segmenter_finds_it(tmp_path, monkeypatch, capsys):
    """The short program (soaks 15 min) soaked 12 min, TP4 left out at -40 C: seven plateaus found, -40 C without
    TP4 (held in its settling or on it), every other test position there."""
    out = tmp_path / "r.mcap"
    code, text, err = run_main(
        monkeypatch,
        capsys,
        "simulate",
        "--out",
        str(out),
        "--program",
        "short",
        "--rate-hz",
        "1",
        "--soak-min",
        "12",
        "--drop",
        "TP4@-40",
        "--json",
    )
    assert code in (0, None), err
    truth = json.loads((tmp_path / "r.truth.json").read_text())
    assert truth["program"] == "short+soak12min-TP4@-40"
    assert not [h for h in truth["holds"] if h["setpoint_c"] == -40.0 and h["position"] == "TP4"]
    seg = segment_run(read_run(out))
    assert [round(p.temp_c) for p in seg.plateaus] == [20, -40, -10, 20, 45, 70, 20]
    cold = {s.position for s in seg.segments if 1 in (s.plateau, s.settling)}
    assert cold >= {"TP1", "TP2", "TP3", "TP5", "TP6"} and "TP4" not in cold
    for args, says in [
        (("--drop", "TP4@-30"), "--drop: program 'standard' holds no such position"),
        (("--drop", "XX@1"), "--drop: unknown position 'XX'"),
        (("--soak-min", "-5"), "--soak-min: soak must be 0 minutes or more"),
    ]:
        code, text, err = run_main(monkeypatch, capsys, "simulate", "--out", str(tmp_path / "x.mcap"), *args)
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "x.mcap").exists()
