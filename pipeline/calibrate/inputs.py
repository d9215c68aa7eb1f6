"""Which runs a calibration takes: one file per recording, and a warning where a run's folder names another unit.

- :func:`resolve_run_ids`: two files with the same ``run_id`` (docs/log-format.md: unique id of a recording) are never
  merged: the same observations would count twice. When one is a truncated copy of the other (every stream's samples
  a prefix of the other's), the complete file is used and the copy is reported as failed with that reason; when
  they differ otherwise, neither is used (both reported, each naming the other).
- :func:`folder_warning`: a run whose folder or file name names a unit (a token shaped like its serial, e.g.
  ``AU-0002`` for ``AU-0001``) other than the serial in its metadata is filed under the metadata's serial, with a
  warning naming both.

Used by ``thermocal calibrate`` (the runs on the command line) and ``fleet`` (the runs under a folder).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import CalibrationError
from pipeline.run import Run

__all__ = ["RunInput", "folder_warning", "is_prefix_of", "resolve_run_ids", "select_runs"]


@dataclass(frozen=True)
class RunInput:
    """A run file (``path``) with its metadata's unit serial and run_id."""

    path: str
    unit: str
    run_id: str


def is_prefix_of(short: Run, long: Run) -> bool:
    """True when every stream of ``short`` is a leading part (the first rows, same values) of ``long``'s."""
    longs = long.streams()
    for name, df in short.streams().items():
        other = longs.get(name)
        if other is None or df.height > other.height or not df.equals(other.head(df.height)):
            return False
    return True


def resolve_run_ids(inputs: Sequence[RunInput], read: Callable[[str], Run]) -> tuple[list[RunInput], list[dict]]:
    """Split ``inputs`` into the runs to use and the ones not to use (``{"run", "reason"}``, one line each).

    Runs are grouped by (unit, run_id); a group of one is kept. In a larger group the runs are read (``read``,
    e.g. :func:`pipeline.io.runs.read_run`; a run that cannot be read is left out with its error): if every other
    one is a prefix of the longest (:func:`is_prefix_of`: a truncated or identical copy), the longest is kept;
    otherwise none is. The order of ``inputs`` is kept.
    """
    groups: dict[tuple[str, str], list[RunInput]] = {}
    for item in inputs:
        groups.setdefault((item.unit, item.run_id), []).append(item)
    dropped: dict[str, str] = {}
    for (unit, run_id), group in groups.items():
        if len(group) < 2:
            continue
        runs: dict[str, Run] = {}
        for item in group:
            try:
                runs[item.path] = read(item.path)
            except Exception as exc:
                dropped[item.path] = getattr(exc, "one_line", lambda e=exc: f"{type(e).__name__}: {e}")()
        readable = [item for item in group if item.path in runs]
        if len(readable) < 2:
            continue
        longest = max(readable, key=lambda i: runs[i.path].voltmeter.height)
        others = [i for i in readable if i is not longest]
        if all(is_prefix_of(runs[i.path], runs[longest.path]) for i in others):
            for i in others:
                same = runs[i.path].voltmeter.height == runs[longest.path].voltmeter.height
                what = "a copy" if same else "a truncated copy"
                dropped[i.path] = (
                    f"{i.path}: {what} of {longest.path} (same run_id {run_id!r}; its samples are "
                    f"{'the same' if same else 'a prefix of the other'}'s): not used, the complete "
                    "file is"
                )
        else:
            for i in readable:
                rest = ", ".join(o.path for o in readable if o is not i)
                dropped[i.path] = (
                    f"{i.path}: run_id {run_id!r} of unit {unit} is also the run_id of {rest}, with "
                    "other samples: which is the recording is unknown, neither is used"
                )
    kept = [i for i in inputs if i.path not in dropped]
    return kept, [{"run": i.path, "reason": dropped[i.path]} for i in inputs if i.path in dropped]


def _serial_pattern(serial: str) -> re.Pattern[str]:
    """Tokens shaped like ``serial``: its letters and separators as they are, each run of digits any digits."""
    body = "".join(r"\d+" if part.isdigit() else re.escape(part) for part in re.split(r"(\d+)", serial) if part)
    return re.compile(rf"(?<![A-Za-z0-9]){body}(?![A-Za-z0-9])", re.IGNORECASE)


def folder_warning(path: str | Path, serial: str, root: str | Path | None = None) -> str | None:
    """A one-line warning when the names on ``path`` (its folders below ``root``, or its last three folders, and
    its own name) name a unit shaped like ``serial`` but never ``serial`` itself; None otherwise."""
    p = Path(path)
    try:
        parts = p.relative_to(root).parts if root is not None else p.parts[-4:]
    except ValueError:
        parts = p.parts[-4:]
    pattern = _serial_pattern(serial)
    named = [m.group(0) for part in parts for m in pattern.finditer(part)]
    if not named or any(n.lower() == serial.lower() for n in named):
        return None
    return f"{p}: its folder or file name says unit {named[0]} but its metadata says {serial}: filed under {serial}"


def select_runs(runs: Sequence[Run]) -> tuple[list[Run], list[str]]:
    """The runs (already read) one calibration takes, and its warnings (``thermocal calibrate``): a truncated copy
    of another run is left out with a warning; two runs with one run_id and other samples are a CalibrationError
    naming both (neither can be used); a run whose folder or file name names another unit warns."""
    by_path = {r.source or f"<run {k}>": r for k, r in enumerate(runs)}
    items = [RunInput(p, r.meta.unit_serial, r.meta.run_id) for p, r in by_path.items()]
    kept, dropped = resolve_run_ids(items, by_path.__getitem__)
    conflicts = [d for d in dropped if "neither is used" in d["reason"]]
    if conflicts:
        raise CalibrationError(
            conflicts[0]["reason"].removeprefix(f"{conflicts[0]['run']}: "), path=conflicts[0]["run"], stream="metadata"
        )
    warnings = [d["reason"] for d in dropped]
    warnings += [w for p, r in by_path.items() if r.source and (w := folder_warning(p, r.meta.unit_serial))]
    return [by_path[i.path] for i in kept], warnings
