"""Which runs a calibration takes: each recording once (its copies left out, its pieces joined), and a warning where
a run's folder names another unit.

- :func:`resolve_run_ids`: the files with one ``run_id`` (docs/log-format.md: unique id of a recording) are copies
  or pieces of that recording, and no observation may count twice. A truncated or identical copy of another (every
  stream's samples a prefix of the other's) is reported as failed with that reason, the complete file used; pieces
  of the recording beside the file holding it whole (their samples all in it, one of them starting later) are left
  out as the same samples twice, not a failure, the whole file used; the pieces a logger wrote one recording into
  (each carrying its run_id, apart in time or sharing samples exactly where they overlap) are all used, to be joined
  by :func:`join_runs`; files with other samples over one stretch of time are two recordings under one id: neither
  is used (both reported, each naming the other).
- :func:`folder_warning`: a run whose folder or file name names a unit (a token shaped like its serial, e.g.
  ``AU-0002`` for ``AU-0001``) other than the serial in its metadata is filed under the metadata's serial, with a
  warning naming both.

- :func:`join_runs`: the runs of one unit given together are one recording (log-format.md, "Other rates and gaps"):
  one :class:`~pipeline.run.Run`, the files in time order, the time between two files a gap within it; samples two
  files share exactly are kept once; two files with other samples over one stretch of time are refused.
- :func:`joined_recordings`: the units with several files, each as one recording of them (:func:`select_runs` then
  :func:`join_runs`), and :func:`recordings_by_files`: those whose recordings are the same files, which are
  segmented together by the consensus of their still times as the file they were cut from is
  (``calibrate PART1 PART2`` and ``fleet`` alike); :func:`unit_recordings` and :func:`segment_recordings`: every
  unit of the files read (in one file or several) as its recording, segmented so (``inspect`` and ``diagnose``);
  :func:`absent_from_pieces`: a unit missing from one of the files its run was cut into, one warning line each.

Used by ``thermocal calibrate`` (the runs on the command line), ``inspect`` and ``fleet`` (the runs under a folder).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from pipeline.errors import CalibrationError, ThermocalError
from pipeline.run import Run, RunMeta, UnitRuns
from pipeline.segment import Segmentation, SegmentSettings

__all__ = [
    "RunInput",
    "absent_from_pieces",
    "folder_warning",
    "is_part_of",
    "is_prefix_of",
    "join_runs",
    "joined_recordings",
    "recordings_by_files",
    "resolve_run_ids",
    "segment_recordings",
    "select_runs",
    "time_span_ns",
    "unit_recordings",
    "units_span_ns",
]


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


def is_part_of(short: Run, long: Run) -> bool:
    """True when every stream of ``short`` is a run of consecutive rows of ``long``'s (the same values), from the row
    at ``short``'s first time on: its samples are all in ``long``, a piece of it or a copy of a stretch of it."""
    longs = long.streams()
    for name, df in short.streams().items():
        if df.height == 0:
            continue
        other = longs.get(name)
        if other is None or df.height > other.height:
            return False
        start = int(other["t_ns"].search_sorted(df["t_ns"][0], side="left"))
        if start + df.height > other.height or not df.equals(other.slice(start, df.height)):
            return False
    return True


def resolve_run_ids(inputs: Sequence[RunInput], read: Callable[[str], Run]) -> tuple[list[RunInput], list[dict]]:
    """Split ``inputs`` into the runs to use and the ones not to use (``{"run", "reason"}``, one line each).

    Runs are grouped by (unit, run_id); a group of one is kept. In a larger group the runs are read (``read``,
    e.g. :func:`pipeline.io.runs.read_run`; a run that cannot be read is left out with its error). Runs whose
    samples are all in a longer (or identical) one of the group (:func:`is_part_of`) are left out: when one of them
    starts later than that run they are the pieces of the recording it holds whole (the same samples twice), each
    listed with ``"part_of"``: that run's path (not a failure); else they are truncated or identical copies of it
    (:func:`is_prefix_of`), each listed with ``"copy_of"``: ``"truncated copy of PATH"`` or ``"copy of PATH"`` (not a
    failure either: the complete file is used). The others are kept when :func:`join_runs` joins them (pieces of
    one recording), else none is. The order of ``inputs`` is kept.
    """
    groups: dict[tuple[str, str], list[RunInput]] = {}
    for item in inputs:
        groups.setdefault((item.unit, item.run_id), []).append(item)
    dropped: dict[str, str] = {}
    part_of: dict[str, str] = {}  # a piece of the recording -> the file holding it whole
    copy_of: dict[str, str] = {}  # a copy (truncated or not) -> the complete file, used in its place
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
        # longest first (stable): a file whose samples are all in one kept before it is a copy or a piece of it
        pieces: list[RunInput] = []
        inside: dict[str, list[RunInput]] = {}
        for i in sorted(readable, key=lambda i: -runs[i.path].voltmeter.height):
            whole = next((k for k in pieces if is_part_of(runs[i.path], runs[k.path])), None)
            if whole is None:
                pieces.append(i)
            else:
                inside.setdefault(whole.path, []).append(i)
        for whole_path, parts in inside.items():
            if not all(is_prefix_of(runs[i.path], runs[whole_path]) for i in parts):
                # the recording in pieces beside the whole file: the same samples twice, the whole file used
                for i in parts:
                    dropped[i.path] = (
                        f"{i.path}: part of {whole_path} (same run_id {run_id!r}; its samples are all in it): the "
                        "same samples twice, not used; the whole file is"
                    )
                    part_of[i.path] = whole_path
                continue
            for i in parts:
                same = runs[i.path].voltmeter.height == runs[whole_path].voltmeter.height
                what = "a copy" if same else "a truncated copy"
                dropped[i.path] = (
                    f"{i.path}: {what} of {whole_path} (same run_id {run_id!r}; its samples are "
                    f"{'the same' if same else 'a prefix of the other'}'s): not used, the complete file is"
                )
                copy_of[i.path] = f"{what.removeprefix('a ')} of {whole_path}"
        if len(pieces) < 2:
            continue
        # the files a logger wrote one recording into (each with the recording's run_id): they join into one run
        # (:func:`join_runs`); files with other samples over one stretch of time are two recordings under one id
        try:
            join_runs([runs[i.path] for i in pieces])
        except CalibrationError as exc:
            if exc.stream == "metadata":  # not a clash of samples: the join says so when the recording is used
                continue
            clash = ", ".join(p for p in (exc.stream, exc.where) if p)
            for i in pieces:
                rest = ", ".join(o.path for o in pieces if o is not i)
                dropped[i.path] = (
                    f"{i.path}: run_id {run_id!r} of unit {unit} is also the run_id of {rest}, with "
                    f"other samples{f' ({clash})' if clash else ''}: which is the recording is unknown, neither is used"
                )
    kept = [i for i in inputs if i.path not in dropped]
    return kept, [
        {
            "run": i.path,
            "reason": dropped[i.path],
            **({"part_of": part_of[i.path]} if i.path in part_of else {}),
            **({"copy_of": copy_of[i.path]} if i.path in copy_of else {}),
        }
        for i in inputs
        if i.path in dropped
    ]


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
    of another run is left out with a warning; the pieces of one recording are kept (:func:`resolve_run_ids`); two
    runs with one run_id and other samples over one stretch of time are a CalibrationError naming both (neither can
    be used); a run whose folder or file name names another unit warns."""
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


def joined_recordings(by_unit: Mapping[str, Sequence[tuple[str, Run]]]) -> dict[str, tuple[Run, list[str], list[str]]]:
    """The units of ``by_unit`` (serial -> its [(path, its run read from that file)]) whose files, once copies are
    left out (:func:`select_runs`), are several: serial -> (the files joined as one recording, :func:`join_runs`;
    the paths of the files kept, in the order given; the selection's warnings). A unit whose files cannot be
    selected or joined is not here: its own calibration says why."""
    out = {}
    for serial, items in by_unit.items():
        if len(items) < 2:
            continue
        path_of = {id(run): p for p, run in items}
        try:
            runs, warnings = select_runs([run for _, run in items])
            if len(runs) > 1:
                out[serial] = (join_runs(runs), [path_of[id(r)] for r in runs], warnings)
        except ThermocalError:
            continue
    return out


def recordings_by_files(joined: Mapping[str, tuple[Run, list[str], list[str]]]) -> dict[frozenset[str], list[str]]:
    """The units of :func:`joined_recordings` by the set of files their recordings were joined from: the units of
    one set, two or more, are segmented together (the consensus of their still times), as the file they were cut
    from is."""
    out: dict[frozenset[str], list[str]] = {}
    for serial, (_, kept, _) in joined.items():
        out.setdefault(frozenset(kept), []).append(serial)
    return out


def unit_recordings(
    read: Sequence[tuple[str, UnitRuns]],
) -> tuple[dict[str, tuple[Run, list[str], list[str]]], dict[str, str]]:
    """Every unit of the files ``read`` ([(path, what :func:`pipeline.io.runs.read_units` read from it)]) as one
    recording: serial -> (its run, the paths it was made of, the selection's warnings), as
    :func:`joined_recordings` gives a unit in several files (a unit in one file: that file's run, ``[path]``,
    ``[]``; one whose other files are copies left out: the file kept); and the units whose files cannot be one
    recording, serial -> the one-line reason (:func:`select_runs` / :func:`join_runs`'s). The units' order is that
    of their first file."""
    by_unit: dict[str, list[tuple[str, Run]]] = {}
    for p, got in read:
        for serial, run in got.units.items():
            by_unit.setdefault(serial, []).append((p, run))
    joined = joined_recordings(by_unit)
    out: dict[str, tuple[Run, list[str], list[str]]] = {}
    failed: dict[str, str] = {}
    for serial, items in by_unit.items():
        if serial in joined:
            out[serial] = joined[serial]
            continue
        if len(items) == 1:
            out[serial] = (items[0][1], [items[0][0]], [])
            continue
        path_of = {id(run): p for p, run in items}
        try:
            runs, warnings = select_runs([run for _, run in items])
            join_runs(runs)  # the reason, when they are not one recording (one run: itself)
        except ThermocalError as exc:
            failed[serial] = exc.one_line()
            continue
        out[serial] = (runs[0], [path_of[id(runs[0])]], warnings)
    return out, failed


def segment_recordings(
    recordings: Mapping[str, tuple[Run, list[str], list[str]]],
    settings: SegmentSettings | None = None,
    only: Sequence[str] | None = None,
) -> tuple[dict[str, Segmentation], list[str]]:
    """Each unit's segmentation of ``recordings`` (:func:`unit_recordings`), as ``calibrate`` makes it: the units
    whose recordings are the same files together, by the consensus of their still times
    (:func:`pipeline.segment_units.segment_units`; a unit alone: its own), and the run-level warnings naming units
    that disagree. ``only``: just the groups holding these units. Raises the segmenter's ThermocalError."""
    from pipeline.segment_units import segment_units

    settings = settings if settings is not None else SegmentSettings()
    segs: dict[str, Segmentation] = {}
    warnings: list[str] = []
    for serials in recordings_by_files(recordings).values():
        if only is not None and not set(serials) & set(only):
            continue
        got, lines = segment_units({s: recordings[s][0] for s in serials}, settings)
        segs.update(got)
        warnings += lines
    return segs, warnings


def absent_from_pieces(
    files: Sequence[tuple[str, str, Sequence[str]]], span_of: Callable[[str], tuple[int, int] | None]
) -> dict[str, list[str]]:
    """The units of a run with several units cut into files that are missing from one of them while the other
    units are in it: serial -> one warning line per such file, naming the unit, the file and the file's time span
    (``span_of(path)``: its first and last voltmeter ns; None: unknown). ``files``: each file holding several units
    as (path, its run_id, the serials it lists); the files of one run_id are the pieces of one recording. A unit
    another file of the run holds over the piece's whole span (the file the pieces were cut from, beside them) is
    not missing there."""
    from pipeline.utc import utc_text

    known: dict[str, tuple[int, int] | None] = {}

    def span_ns(path: str) -> tuple[int, int] | None:  # each file's span read once
        if path not in known:
            known[path] = span_of(path)
        return known[path]

    by_run: dict[str, list[tuple[str, set[str]]]] = {}
    for path, run_id, listed in files:
        by_run.setdefault(run_id, []).append((path, set(listed)))
    out: dict[str, list[str]] = {}
    for run_id, pieces in by_run.items():
        if len(pieces) < 2:
            continue
        every = set().union(*(held for _, held in pieces))
        for path, held in pieces:
            missing = sorted(every - held)
            if not missing:
                continue
            span = span_ns(path)
            when = f"{utc_text(span[0])} .. {utc_text(span[1])}" if span else "time span unknown"
            for serial in missing:
                if span and any(
                    serial in other and (o := span_ns(p)) is not None and o[0] <= span[0] and o[1] >= span[1]
                    for p, other in pieces
                    if p != path
                ):
                    continue  # another file of the run holds the unit over this piece's time: not missing
                out.setdefault(serial, []).append(
                    f"{path}: unit {serial} is missing from this piece of run {run_id!r} ({when}), which holds the "
                    "other units: its recording has no samples over that time"
                )
    return out


#: metadata that says how a recording is calibrated: the files of one recording must agree on it
JOINED_META = ("normal_temp_c", "g_local_mps2", "nominal_gain_v_per_g", "unit_grade")


def join_runs(runs: Sequence[Run]) -> Run:
    """The runs of one unit (already read; :func:`select_runs` has left out copies) as one recording.

    The files are put in time order (by their first voltmeter sample) and each stream concatenated: the time from
    the end of one file to the start of the next is a gap within the recording, as a logger's dropout within one
    file is. Where files overlap in time, the samples they share exactly (same time, same values) are kept once;
    two files with other samples over one stretch of a stream (one unit cannot be recorded twice at once) are a
    CalibrationError naming both and the time. The files must agree on :data:`JOINED_META` (else a
    CalibrationError naming the key). One run comes back as it is.

    The joined run's ``run_id`` is the files' run_ids in time order joined by ``+``, its ``source`` their paths
    likewise, its ``started_utc`` the first file's; other metadata the first file's (keys only another has are
    added); its warnings each file's, prefixed with the file when there are several.
    """
    runs = list(runs)
    if not runs:
        raise CalibrationError("no runs given")
    if len(runs) == 1:
        return runs[0]
    serials = sorted({r.meta.unit_serial for r in runs})
    if len(serials) != 1:
        raise CalibrationError(f"runs of different units given together: {', '.join(serials)}")
    names = [r.source or r.meta.run_id for r in runs]
    for key in JOINED_META:
        values = {getattr(r.meta, key) for r in runs}
        if len(values) > 1:
            said = ", ".join(f"{n}: {getattr(r.meta, key)}" for n, r in zip(names, runs))
            raise CalibrationError(
                f"the runs given together are one recording of {serials[0]}, but their metadata disagree on "
                f"{key!r} ({said})",
                stream="metadata",
            )
    order = sorted(range(len(runs)), key=lambda k: _time_order(runs[k]))
    runs = [runs[k] for k in order]
    names = [names[k] for k in order]
    streams: dict[str, pl.DataFrame | None] = {}
    for name in ("voltmeter", "au_temperature", "chamber", "fixture"):
        frames = [getattr(r, name) for r in runs]
        present = [(k, f) for k, f in enumerate(frames) if f is not None]
        streams[name] = _joined_stream(name, present, names) if present else None
    first = runs[0].meta
    extra: dict[str, str] = {}
    for r in reversed(runs):
        extra.update(r.meta.extra)
    meta = RunMeta(
        unit_serial=first.unit_serial,
        run_id="+".join(dict.fromkeys(r.meta.run_id for r in runs)),
        station=first.station,
        fixture=first.fixture,
        normal_temp_c=first.normal_temp_c,
        g_local_mps2=first.g_local_mps2,
        started_utc=first.started_utc,
        nominal_gain_v_per_g=first.nominal_gain_v_per_g,
        unit_grade=first.unit_grade,
        extra=extra,
    )
    voltmeter, au_temperature = streams["voltmeter"], streams["au_temperature"]
    assert voltmeter is not None and au_temperature is not None  # required streams: every run has them
    return Run(
        meta=meta,
        voltmeter=voltmeter,
        au_temperature=au_temperature,
        chamber=streams["chamber"],
        fixture=streams["fixture"],
        source=" + ".join(r.source for r in runs if r.source),
        warnings=[f"{n}: {w}" for n, r in zip(names, runs) for w in r.warnings]
        + _other_runs_line(runs, names)
        + _thermosensor_step_lines(runs, names),
        unlogged_ns=_unlogged_ns(runs),
        left_out_ns=tuple(x for r in runs for x in r.left_out_ns),
    )


def _other_runs_line(runs: Sequence[Run], names: Sequence[str]) -> list[str]:
    """One warning line when the files joined (in time order, ``names`` their paths) carry more than one run_id:
    separate recordings of the unit (a re-run), calibrated as one recording by design, the time between each
    run_id's last voltmeter sample and the next one's first said; pieces of one run_id give none."""
    spans: dict[str, list[int]] = {}
    files: dict[str, list[str]] = {}
    for n, r in zip(names, runs):
        span = time_span_ns(r.voltmeter)
        got = spans.setdefault(r.meta.run_id, [])
        if span is not None:
            got[:] = [min(got[0], span[0]), max(got[1], span[1])] if got else list(span)
        files.setdefault(r.meta.run_id, []).append(n)
    if len(spans) < 2:
        return []
    ids = list(spans)
    said = ", ".join(f"{i!r} ({', '.join(files[i])})" for i in ids)
    between = [
        f"{(spans[b][0] - spans[a][1]) / 3.6e12:.1f} h" for a, b in zip(ids[:-1], ids[1:]) if spans[a] and spans[b]
    ]
    return [
        f"the files given together are {len(ids)} runs of unit {runs[0].meta.unit_serial} (different run_ids: "
        f"{said}), calibrated as one recording: the time between them ({', '.join(between) or 'unknown'}) is a gap "
        "within it, and the day-to-day repeatability of the unit is not judged"
    ]


#: the AU temperature's value at a join of two files is taken from a straight line through each file's readings
#: within this time (s) of the join (at least :data:`JOIN_MIN_READINGS` of them)
JOIN_WINDOW_S = 15.0
JOIN_MIN_READINGS = 5
#: a join whose files' readings are further apart than this (s) is not judged: the temperature may move between
JOIN_MAX_GAP_S = 15.0
#: a step at a join is a warning when it exceeds this many of its standard errors, and at least this (C): the
#: straight lines miss the bend at a ramp's corner by up to 0.03 C (short program, split at every second)
JOIN_STEP_SIGMAS = 6.0
JOIN_STEP_FLOOR_C = 0.1


def _end_value(t_s: np.ndarray, y: np.ndarray, last: bool) -> tuple[float, float] | None:
    """The value at time 0 of a straight line through a file's readings (``t_s`` s from the join, ``y``, NaN
    dropped) nearest that end (``last``: its last ones), within :data:`JOIN_WINDOW_S` of it and at least
    :data:`JOIN_MIN_READINGS`; with its standard error. None with fewer readings or no spread in time."""
    ok = np.isfinite(y)
    t_s, y = t_s[ok], y[ok]
    if t_s.size < JOIN_MIN_READINGS:
        return None
    near = np.abs(t_s - (t_s[-1] if last else t_s[0])) <= JOIN_WINDOW_S
    if near.sum() < JOIN_MIN_READINGS:
        near = np.zeros(t_s.size, dtype=bool)
        if last:
            near[-JOIN_MIN_READINGS:] = True
        else:
            near[:JOIN_MIN_READINGS] = True
    design = np.column_stack([np.ones(int(near.sum())), t_s[near]])
    normal = design.T @ design
    if np.linalg.det(normal) <= 0:
        return None
    coef, *_ = np.linalg.lstsq(design, y[near], rcond=None)
    resid = y[near] - design @ coef
    var = float(resid @ resid) / (resid.size - 2)
    return float(coef[0]), float(np.sqrt(var * np.linalg.inv(normal)[0, 0]))


def _stream_step(
    before: pl.DataFrame | None, after: pl.DataFrame | None, column: str
) -> tuple[float, float, int] | None:
    """The step (after minus before) of ``column`` at the join of two files' tables of one stream, each side's
    straight line (:func:`_end_value`) taken at the middle of the join: (step, its standard error, join time ns);
    None when a side is missing or too short, or the files are more than :data:`JOIN_MAX_GAP_S` apart."""
    if before is None or after is None or not before.height or not after.height:
        return None
    if column not in before.columns or column not in after.columns:
        return None
    t0, t1 = before["t_ns"].to_numpy(), after["t_ns"].to_numpy()
    if (int(t1[0]) - int(t0[-1])) / 1e9 > JOIN_MAX_GAP_S:
        return None
    at_ns = (int(t0[-1]) + int(t1[0])) // 2
    a = _end_value((t0 - at_ns) / 1e9, before[column].to_numpy().astype(np.float64), last=True)
    b = _end_value((t1 - at_ns) / 1e9, after[column].to_numpy().astype(np.float64), last=False)
    if a is None or b is None:
        return None
    return b[0] - a[0], float(np.hypot(a[1], b[1])), at_ns


def _is_step(step: tuple[float, float, float]) -> bool:
    """A step beyond its noise: :data:`JOIN_STEP_SIGMAS` standard errors and :data:`JOIN_STEP_FLOOR_C`."""
    return abs(step[0]) > max(JOIN_STEP_SIGMAS * step[1], JOIN_STEP_FLOOR_C)


def _thermosensor_step_lines(runs: Sequence[Run], names: Sequence[str]) -> list[str]:
    """One warning line per join of two files (in time order, ``names`` their paths) where the AU temperature steps
    beyond its noise (:func:`_is_step`) while the chamber does not (neither its setpoint nor its air temperature
    steps so; no chamber log: the AU temperature alone): a thermosensor or logger changed between the
    files, whose offset the calibration takes as a temperature change. Names both files, the join's time and the
    step. Joins further apart than :data:`JOIN_MAX_GAP_S` are not judged."""
    from pipeline.utc import utc_text

    lines = []
    for k in range(len(runs) - 1):
        before, after = runs[k], runs[k + 1]
        step = _stream_step(before.au_temperature, after.au_temperature, "temp_c")
        if step is None or not _is_step(step):
            continue
        chamber = [(c, _stream_step(before.chamber, after.chamber, f"{c}_c")) for c in ("setpoint", "air")]
        if any(got is not None and _is_step(got) for _, got in chamber):
            continue
        said = ", ".join(f"{c} {got[0]:+.2f} C" for c, got in chamber if got is not None)
        said = f", while the chamber does not ({said})" if said else ""
        lines.append(
            f"{names[k]} -> {names[k + 1]}: the AU temperature steps {step[0]:+.2f} C at the join of the files "
            f"({utc_text(step[2])}), beyond its noise (+-{step[1]:.3f} C){said}: a "
            "thermosensor or logger changed between the files? The calibration takes the step as the unit's "
            "temperature"
        )
    return lines


def _unlogged_ns(runs: Sequence[Run]) -> tuple[tuple[int, int], ...]:
    """The (first, last) voltmeter ns of the files (in time order) without a fixture log, when another has one (and
    those the files carried already): :attr:`pipeline.run.Run.unlogged_ns`. A file whose log is there but empty
    logged no move: the position logged before holds on through it."""
    if all(r.fixture is None for r in runs):
        return ()
    spans = [s for r in runs for s in r.unlogged_ns]
    spans += [span for r in runs if r.fixture is None and (span := time_span_ns(r.voltmeter))]
    return tuple(sorted(spans))


def _time_order(run: Run) -> tuple:
    """Sort key of the files of a recording, whatever order they were given in: first voltmeter time, the longer
    file first where two start together, then run_id and path."""
    first, last = time_span_ns(run.voltmeter) or (int(np.iinfo(np.int64).max), 0)
    return first, -last, run.meta.run_id, run.source


def time_span_ns(df: pl.DataFrame) -> tuple[int, int] | None:
    """(first, last) ``t_ns`` of a stream's table; None when it has no rows."""
    if not df.height:
        return None
    t = df["t_ns"].to_numpy()
    return int(t.min()), int(t.max())


def units_span_ns(got: UnitRuns) -> tuple[int, int] | None:
    """The first and last voltmeter ns of a file's units (what :func:`pipeline.io.runs.read_units` read), None
    without samples: the time span :func:`absent_from_pieces` names."""
    spans = [span for r in got.units.values() if (span := time_span_ns(r.voltmeter))]
    return (min(a for a, _ in spans), max(b for _, b in spans)) if spans else None


def _joined_stream(name: str, frames: list[tuple[int, pl.DataFrame]], names: list[str]) -> pl.DataFrame:
    """One stream of the joined recording from each file's (``(file index, table)``, in time order of the files).
    Files that do not overlap in this stream are chained as they are (no copy of the samples: the chunks are
    linked); overlapping ones are merged by time, samples shared exactly kept once, and must then follow each
    other file by file (else two recordings claim one stretch of time: CalibrationError)."""
    frames = [(k, f) for k, f in frames if f.height] or frames[:1]
    spans = [time_span_ns(f) or (0, 0) for _, f in frames]
    ordered = sorted(range(len(spans)), key=lambda k: spans[k])
    disjoint = all(spans[ordered[i]][1] < spans[ordered[i + 1]][0] for i in range(len(ordered) - 1))
    if disjoint:
        return pl.concat([frames[k][1] for k in ordered], how="vertical", rechunk=False)
    tagged = pl.concat(
        [f.with_columns(pl.lit(k, dtype=pl.UInt32).alias("_file")) for k, f in frames], how="vertical"
    ).sort(["t_ns", "_file"], maintain_order=True)
    data = [c for c in tagged.columns if c != "_file"]
    merged = tagged.unique(subset=data, keep="first", maintain_order=True)
    if name != "fixture":
        t = merged["t_ns"].to_numpy()
        f = merged["_file"].to_numpy()
        clash = _clash(t, f)
        if clash is not None:
            i, a, b = clash
            raise CalibrationError(
                f"{names[a]} and {names[b]} hold other samples over the same stretch of time (one unit cannot be "
                "recorded twice at once): which is the recording is unknown, neither is used",
                stream=name,
                where=f"t_ns={int(t[i])}",
            )
    return merged.drop("_file")


def _clash(t_ns: np.ndarray, files: np.ndarray) -> tuple[int, int, int] | None:
    """Where the merged samples (times ``t_ns``, file of each ``files``, shared samples kept once) are not one
    file after another: (row index, file, other file) of the first clash (two samples at one time, or a file's
    samples among another's), else None."""
    same = np.flatnonzero(np.diff(t_ns) == 0)
    if same.size:
        i = int(same[0])
        return i + 1, int(files[i]), int(files[i + 1])
    ids, first = np.unique(files, return_index=True)
    last = files.size - 1 - np.unique(files[::-1], return_index=True)[1]
    k = np.argsort(first)
    for a, b in zip(k[:-1], k[1:]):
        if first[b] <= last[a]:
            return int(first[b]), int(ids[a]), int(ids[b])
    return None
