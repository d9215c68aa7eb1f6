"""``thermocal diagnose RUN... [--passport FILE | --registry DIR] [--json]``: the command behind the CLI (no Prefect).

Reads the run (and the passport when given: a file, or the unit's current passport in a registry, see
Reads the run (and the passport when given: a file, or the unit's current passport in a registry, see
:func:`current_passport`; either verified first, :mod:`pipeline.passport.verification`, or used with
``--unverified`` and said so), runs :func:`pipeline.diagnose.diagnosis.diagnose_run`, writes the figure and the
passport extended with the fitted effects (signed by this station, as a loose file), and returns the report
(docs/contract.md's ``diagnose --json`` object plus ``figure`` and ``extended_passport`` paths). Both files are
named ``<run>.diagnose.png`` and ``<run>.diagnose.passport.json`` (``<run>.<unit>.diagnose...`` for one unit of a
run holding several) and go where ``--out`` says, else beside the registry (``REG/diagnose/UNIT/``) with
``--registry``, else into the current folder: never into the data's folder, which may be read-only and is not ours.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.calibrate.inputs import join_runs, segment_recordings, select_runs, time_span_ns, unit_recordings
from pipeline.diagnose.diagnosis import diagnose_run
from pipeline.errors import ThermocalError
from pipeline.io.runs import read_run_meta, read_units
from pipeline.jsonable import to_jsonable
from pipeline.model import OUTPUT_UNITS
from pipeline.passport.canonical import canonical_json
from pipeline.passport.document import load_passport
from pipeline.passport.registry import Registry, load_passport_file
from pipeline.passport.signing import sign_record
from pipeline.run import Run, check_serials
from pipeline.segment import Segmentation

from .runtime import Steps

#: The folder of a registry that diagnose writes into (beside ``units/``, which holds only versions).
REGISTRY_DIAGNOSE_DIR = "diagnose"


def output_folder(out_dir: Path | None, registry: Path | None, unit: str) -> Path:
    """Where diagnose's files go: ``out_dir``, else ``REG/diagnose/UNIT`` beside a registry's units, else the
    current folder."""
    if out_dir is not None:
        return Path(out_dir)
    if registry is not None:
        return Path(registry) / REGISTRY_DIAGNOSE_DIR / unit
    return Path.cwd()


def _named(folder: Path, run: Path, suffix: str) -> Path:
    return folder / f"{Path(run).name.removesuffix('.mcap')}{suffix}"


def current_passport(registry: Path, unit: str, unverified: bool = False):
    """The unit's current passport in ``registry`` (docs/contract.md: the newest approved version, else the newest that
    did not fail: :meth:`pipeline.passport.registry.Registry.load_state`, verified), a description of it (version,
    status, approval) and its :class:`pipeline.passport.registry.VersionState`."""
    doc, st = Registry(registry).load_state(unit, unverified=unverified)
    return load_passport(doc), f"{registry}: {st.text()}", st


def diagnose_command(
    run: Path | Sequence[Path],
    passport: Path | None,
    as_json: bool,
    out_png: Path | None,
    out_passport: Path | None = None,
    registry: Path | None = None,
    unit: str | None = None,
    *,
    out_dir: Path | None = None,
    unverified: bool = False,
) -> dict:
    """Diagnose ``run`` against ``passport``, or the unit's current passport in ``registry`` (either verified,
    or used ``unverified`` and said so), or one fitted from the run when neither is given; write the PNG to
    ``out_png`` and the extended passport to ``out_passport`` (default: in :func:`output_folder`; of one unit of a
    run holding several, named with the unit). ``unit``: the unit of a run holding several (only its streams are
    read). Progress on stderr when it is a terminal (``as_json`` is not used). Returns the report.

    ``run`` may be the files of one recording (any order): read as one, as ``calibrate`` reads them
    (:func:`pipeline.calibrate.inputs.select_runs`, ``join_runs``); the outputs are named after the first in time."""
    runs = [Path(run)] if isinstance(run, (str, os.PathLike)) else [Path(r) for r in run]
    run = runs[0]
    step = Steps("diagnose")
    if passport is not None and registry is not None:
        raise ThermocalError("give --passport or --registry, not both", where="diagnose")
    given, source, state = None, None, None  # the passport first: one that does not verify ends it at once
    if passport is not None:
        doc, state = load_passport_file(passport, unverified=unverified)
        given, source = (
            load_passport(doc),
            str(passport) + (f" ({state.verification.label})" if state.unverified else ""),
        )
    elif registry is not None:
        given, source, state = current_passport(registry, unit or read_run_meta(run).unit_serial, unverified)
    step(f"ingest {', '.join(r.name for r in runs)}")
    the_run, run, seg = _one_recording(runs, unit)
    step("segment, fit and search the residual" if given is None else "segment and search the residual")
    result = diagnose_run(the_run, given, passport_source=source, segmentation=seg)
    step("write figure and extended passport")
    folder = output_folder(out_dir, registry, the_run.meta.unit_serial)
    tag = f".{unit}" if unit else ""
    png = Path(out_png) if out_png is not None else _named(folder, run, f"{tag}.diagnose.png")
    ext = Path(out_passport) if out_passport is not None else _named(folder, run, f"{tag}.diagnose.passport.json")
    try:
        from pipeline.diagnose.plot import plot_diagnosis

        title = f"{the_run.meta.unit_serial} {the_run.meta.run_id}: residual of 30 s blocks, {result.report['verdict']}"
        png.parent.mkdir(parents=True, exist_ok=True)
        plot_diagnosis(png, result, the_run, title=title, output_unit=result.passport.output_unit)
        ext.parent.mkdir(parents=True, exist_ok=True)
        ext.write_bytes(canonical_json(_sealed(result.passport.document, state)))
    except OSError as e:
        raise ThermocalError(f"cannot write: {e.strerror or e}", path=str(e.filename or png)) from None
    report = dict(result.report)
    if state is not None:  # which version of the registry, its status and approval, how it was verified
        report["passport_used"] = state.as_dict()
        if state.warning():
            report["notes"] = [*report.get("notes", []), state.warning()]
    report["output_unit"] = result.passport.output_unit
    report["figure"] = str(png)
    report["extended_passport"] = str(ext)
    return report


def _one_recording(paths: list[Path], unit: str | None) -> tuple[Run, Path, Segmentation | None]:
    """The run of ``paths`` (the files of one recording, joined in time order, copies left out with a warning), the
    file that names the outputs (the first in time) and its segmentation when made here: ``unit`` of a run holding
    several units (the file, or the pieces it was cut into, one run_id) is segmented with the other units of the
    same files, by the consensus of their still times, as ``calibrate`` segments it
    (:func:`pipeline.calibrate.inputs.unit_recordings`, :func:`~pipeline.calibrate.inputs.segment_recordings`);
    None: the diagnosis segments the run alone."""
    read = [(str(p), read_units(p)) for p in paths]
    if unit is not None and len(read) > 1:  # a serial in no file at all; one missing from a piece: the others
        check_serials([got for _, got in read], [unit])
    holding = [(Path(p), got) for p, got in read if unit is None or unit in got.serials]
    runs = [got.one(unit) for _, got in holding]  # the unit named, in the files holding it (else the reader's error)
    if unit is not None and any(got.several and len(got.units) > 1 for _, got in read):
        recordings, _ = unit_recordings(read)
        if unit in recordings:  # else its files are not one recording: select_runs or join_runs says why below
            run, kept, left_out = recordings[unit]
            first = min(kept, key=lambda p: _first_ns(next(got.units[unit] for q, got in read if q == p)))
            if len(kept) == 1:  # its one file: segmented with that file's units, as calibrate segments it
                recordings, _ = unit_recordings([(kept[0], dict(read)[kept[0]])])
            segs, _ = segment_recordings(recordings, only=[unit])
            run.warnings[:0] = left_out
            return run, Path(first), segs[unit]
    if len(runs) == 1:
        return runs[0], holding[0][0], None
    path_of = {id(r): p for r, (p, _) in zip(runs, holding)}
    kept_runs, warnings = select_runs(runs)
    run = join_runs(kept_runs)
    run.warnings[:0] = warnings
    first_run = min(kept_runs, key=_first_ns)
    return run, path_of[id(first_run)], None


def _first_ns(run: Run) -> tuple[int, int]:
    return time_span_ns(run.voltmeter) or (np.iinfo(np.int64).max, 0)


def _sealed(extended: dict, state) -> dict:
    """The extended passport as written: signed by this station when its base verified (or was fitted here), so
    that apply can verify it as a loose file; a base used ``--unverified`` leaves it unsigned (apply then needs
    ``--unverified`` too), with the label recorded."""
    body = _finite({k: v for k, v in to_jsonable(extended).items() if k not in ("content_sha256", "signature")})
    if state is not None and state.unverified:
        return {**body, "derived_from_unverified": state.verification.label}
    return sign_record(body)


def _finite(value):
    """``value`` with every non-finite number made null (canonical JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def diagnose_text(report: dict) -> str:
    """The report for a person: verdict, findings with their explanation, fit and VP errors before and after
    (residuals in uV, or mm/s^2 for outputs in m/s^2: ``output_unit``)."""
    small, uv = OUTPUT_UNITS.get(report.get("output_unit") or "V", OUTPUT_UNITS["V"])
    lines = [
        f"{report['unit']} {report['run_id']}: {report['verdict']}  (passport: {report['passport_source']})",
        f"  residual RMS of {report['noise_v']['block_s']:.0f} s blocks: before {report['rms_before_v'] * uv:.2f} "
        f"{small}, after {report['rms_after_v'] * uv:.2f} {small} (noise {report['rms_noise_v'] * uv:.2f} "
        f"{small})",
    ]
    if report.get("vp_max_abs_dg_before_g") is not None:
        lines.append(
            f"  VP max |dg|: before {report['vp_max_abs_dg_before_g'] * 1e6:.1f} micro-g, after "
            f"{report['vp_max_abs_dg_after_g'] * 1e6:.1f} micro-g"
        )
    for k, f in enumerate(report["findings"], 1):
        w = f["where"]
        lines.append(
            f"  {k}. {f['effect']}"
            + (f" (confounded with {', '.join(f['confounded_with'])})" if f.get("confounded_with") else "")
        )
        lines.append(f"     {f['explanation']}")
        lines.append(
            f"     where: {len(w['windows'])} window(s), axes {'/'.join(w['axes'])}, temperatures "
            f"{', '.join(f'{t:+.0f}' for t in w['temps_c']) or '-'} C, positions "
            f"{' '.join(w['positions']) or '-'}; RMS there {f['rms_before_v'] * uv:.2f} -> "
            f"{f['rms_after_v'] * uv:.2f} {small}"
        )
    for n in report.get("notes", []):
        lines.append(f"  note: {n}")
    lines.append(f"  figure: {report.get('figure')}")
    lines.append(f"  extended passport: {report.get('extended_passport')}")
    return "\n".join(lines)


__all__ = ["diagnose_command", "diagnose_text"]
