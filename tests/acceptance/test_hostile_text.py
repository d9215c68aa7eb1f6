"""Control characters in what is printed (issue 26 item 6): an approver's name with ANSI escapes, a file name with a
terminal title sequence, are shown escaped (``\\x1b``), never obeyed by the terminal, in text output, JSON and the
one-line errors."""

from __future__ import annotations

import json

from pipeline.passport.registry import Registry
from tests.acceptance.tampered import publish
from tests.conftest import run_main

HOSTILE = "Eve \x1b[2J\x1b[31mred\x1b]0;pwned\x07 \u202eevil\r"
RAW = ("\x1b", "\x07", "\r", "\u202e")


def _clean(text: str) -> bool:
    return not any(c in text for c in RAW)


def test_an_approvers_name_is_printed_escaped(tmp_path, monkeypatch, capsys):
    reg = Registry(tmp_path / "reg")
    publish(reg, "AU-0601", 1)
    monkeypatch.chdir(tmp_path)
    code, out, err = run_main(
        monkeypatch, capsys, "passport", "approve", "AU-0601", "1", "--by", HOSTILE, "--registry", str(reg.root)
    )
    assert code == 0 and _clean(out) and _clean(err) and "\\x1b[31mred" in out
    for args in (
        ("passport", "log", "AU-0601", "--registry", str(reg.root)),
        ("passport", "show", "AU-0601", "--registry", str(reg.root)),
        ("export", "AU-0601", "--registry", str(reg.root), "--format", "csv"),
        ("report", "AU-0601", "--registry", str(reg.root), "--out", "c.html"),
    ):
        code, out, err = run_main(monkeypatch, capsys, *args)
        assert code == 0, (args, err)
        assert _clean(out) and _clean(err), (args, out)
    code, out, err = run_main(monkeypatch, capsys, "passport", "log", "AU-0601", "--registry", str(reg.root), "--json")
    assert code == 0 and _clean(out) and json.loads(out)["versions"][0]["approved"][0]["by"].startswith("Eve \x1b")


def test_a_hostile_file_name_in_an_error_line_is_escaped(tmp_path, monkeypatch, capsys):
    bad = tmp_path / "run\x1b]0;pwned\x07.mcap"
    bad.write_bytes(b"not an mcap file at all")
    code, out, err = run_main(monkeypatch, capsys, "inspect", str(bad))
    assert code == 2 and out == "" and _clean(err) and err.count("\n") == 1 and "\\x1b]0;pwned\\x07" in err
