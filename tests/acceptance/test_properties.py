"""Property-based tests (hypothesis) of the readers and the segmenter (issue 7): whatever is done to a valid run,
reading, segmenting and calibrating it either works or raises the project's own error type
(:class:`pipeline.errors.ThermocalError`): never a bare exception.

- MCAP files (with and without summary, compressed or not) with bytes flipped, cut, inserted or deleted;
- Parquet runs whose stream columns get random types, values, NaNs, nulls and infinities;
- random stream tables (times in any order, repeated, gappy; values finite or not, huge or tiny; random fixture
  labels and nominal gains) fed straight to the segmenter and the fit.

Example counts are modest so that the file runs in well under a minute.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType

from pipeline.calibrate.tilt import CalibrationSettings, fit_unit, observe_run, verify_unit
from pipeline.errors import ThermocalError
from pipeline.io.checks import FIXTURE_LABELS
from pipeline.io.runs import read_run, write_run
from pipeline.positions import ALL_POSITIONS
from pipeline.run import Run, RunMeta, make_frame
from pipeline.segment import SegmentSettings, segment_run
from tests.acceptance.badcorpus import rewrite_mcap

pytestmark = pytest.mark.slow  # an end-to-end proof on long or many recordings

T0_NS = 1_793_491_200_000_000_000
META = RunMeta(unit_serial="AU-0042", run_id="prop-run", nominal_gain_v_per_g=-0.55)
#: small segmentation scales, so that a few hundred samples hold plateaus and static positions
SMALL = SegmentSettings(plateau_min_s=60.0, static_window_s=2.0, static_min_s=3.0, settle_trim_s=1.0)
#: examples per property (THERMOCAL_HYPOTHESIS_EXAMPLES=2000 for a deeper search than CI's)
FAST = settings(
    max_examples=int(os.environ.get("THERMOCAL_HYPOTHESIS_EXAMPLES", "60")),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

_DIR = Path(tempfile.mkdtemp(prefix="thermocal-properties-"))
atexit.register(shutil.rmtree, _DIR, ignore_errors=True)


def small_run(n: int = 3000, seed: int = 0) -> Run:
    """10 min at 5 Hz: the six test positions held 20 s each, in turn; 20 C, then a step to -40 C half-way."""
    rng = np.random.default_rng(seed)
    t = T0_NS + np.arange(n, dtype=np.int64) * 200_000_000
    names = list(ALL_POSITIONS)[:6]
    k = (np.arange(n) // 100) % len(names)
    g = np.array([ALL_POSITIONS[names[i]] for i in k], dtype=float)
    u = -0.55 * g + rng.normal(0.0, 5e-6, (n, 3))
    tt = t[::5]
    temp = np.where(np.arange(tt.size) < tt.size // 2, 20.0, -40.0) + rng.normal(0.0, 0.002, tt.size)
    events = np.flatnonzero(np.diff(k) != 0) + 1
    fixture = make_frame(
        "fixture",
        {"t_ns": np.concatenate(([t[0]], t[events])), "position": [names[k[0]]] + [names[k[i]] for i in events]},
    )
    return Run(
        meta=META,
        voltmeter=make_frame("voltmeter", {"t_ns": t, "ux": u[:, 0], "uy": u[:, 1], "uz": u[:, 2]}),
        au_temperature=make_frame("au_temperature", {"t_ns": tt, "temp_c": temp}),
        chamber=make_frame("chamber", {"t_ns": tt, "setpoint_c": np.round(temp), "air_c": temp}),
        fixture=fixture,
    )


def calibrate(run_or_path) -> None:
    """Read (a path), segment, fit and verify; ThermocalError is the only acceptable failure."""
    try:
        run = read_run(run_or_path) if isinstance(run_or_path, Path) else run_or_path
        obs, _ = observe_run(run, SMALL)
        fit = fit_unit(run.meta.unit_serial, obs, CalibrationSettings(segment=SMALL), run.meta.normal_temp_c)
        verify_unit(fit.model, obs, run.meta.normal_temp_c)
        event("calibrated")
    except ThermocalError as exc:
        assert "\n" not in str(exc)
        event(f"{type(exc).__name__}: {exc.message.split(':')[0].split('(')[0][:40]}")


# --- MCAP bytes -----------------------------------------------------------------------------------------------------

_MCAP_VARIANTS = {
    name: write_run(small_run(), _DIR / f"{name}.mcap", "mcap", block_samples=64, chunk_size=4096, **opts).read_bytes()
    for name, opts in {
        "zstd": {},
        "plain": {"compression": "none"},
        "no-summary": {"summary": False, "compression": "none"},
    }.items()
}
# chunks without CRC: a changed byte in a message reaches the message decoder
_MCAP_VARIANTS["no-crc"] = rewrite_mcap(
    _DIR / "plain.mcap", _DIR / "no-crc.mcap", chunk_size=4096, compression=CompressionType.NONE, enable_crcs=False
).read_bytes()


@st.composite
def mutated(draw) -> bytes:
    data = bytearray(_MCAP_VARIANTS[draw(st.sampled_from(sorted(_MCAP_VARIANTS)))])
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))  # places uniform over the file
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "byte", "truncate", "insert", "delete"]))
        if not data:
            break
        i = int(rng.integers(len(data)))
        if kind == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif kind == "byte":
            data[i] = draw(st.integers(0, 255))
        elif kind == "truncate":
            del data[i:]
        elif kind == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=16))
        else:
            del data[i : i + draw(st.integers(1, 64))]
    return bytes(data)


@FAST
@given(mutated())
def test_mutated_mcap_files_raise_only_thermocal_errors(data):
    path = _DIR / "mutated.mcap"
    path.write_bytes(data)
    calibrate(path)


# --- Parquet columns ------------------------------------------------------------------------------------------------

_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**63), 2**63 - 1),
    st.none(),
    st.text(max_size=3),
    st.booleans(),
)
_TYPES = {
    "int64": pa.int64(),
    "int32": pa.int32(),
    "uint64": pa.uint64(),
    "float32": pa.float32(),
    "float64": pa.float64(),
    "string": pa.string(),
    "bool": pa.bool_(),
    "timestamp": pa.timestamp("ns"),
    "date": pa.date32(),
    "null": pa.null(),
    "dictionary": pa.dictionary(pa.int32(), pa.string()),
}


def _column(values: np.ndarray, type_name: str, specials: list) -> pa.Array:
    """``values`` as an Arrow array of ``type_name`` (converted leniently), with ``specials`` written over the
    first rows; None where a value does not convert."""
    items = [*specials[: len(values)], *values[len(specials) :].tolist()]
    t = _TYPES[type_name]
    if type_name == "null":
        return pa.nulls(len(items))
    if type_name == "dictionary":
        return pa.array([None if v is None else str(v) for v in items], type=pa.string()).dictionary_encode()
    out = []
    for v in items:
        try:
            out.append(pa.scalar(v, type=t).as_py() if v is not None else None)
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError, OverflowError):
            out.append(None)
    return pa.array(out, type=t)


@FAST
@given(
    stream=st.sampled_from(["voltmeter", "au_temperature", "chamber", "fixture"]),
    column=st.data(),
    type_name=st.sampled_from(sorted(_TYPES)),
    specials=st.lists(_VALUES, max_size=5),
    drop=st.sampled_from([False] * 5 + [True]),
    rows=st.sampled_from([None, 0, 1, 7]),
)
def test_parquet_columns_of_any_type_raise_only_thermocal_errors(stream, column, type_name, specials, drop, rows):
    d = _DIR / "parquet-run"
    write_run(small_run(), d, "parquet")
    table = pq.read_table(d / f"{stream}.parquet")
    name = column.draw(st.sampled_from(table.column_names))
    if rows is not None:
        table = table.slice(0, rows)
    if drop:
        table = table.drop_columns([name])
    else:
        values = table[name].to_numpy(zero_copy_only=False)
        table = table.set_column(table.column_names.index(name), name, _column(values, type_name, specials))
    pq.write_table(table, d / f"{stream}.parquet")
    calibrate(d)


# --- random stream tables into the segmenter -------------------------------------------------------------------------

_SPECIAL_FLOATS = st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -0.0, 5e-324, 1e308, -1e308, 1e-300])


@st.composite
def random_run(draw) -> Run:
    """A run whose tables a reader could hand over (or a caller could build): times in any order, repeated,
    gappy; voltages either held positions (a random unit's gains and offsets) or random levels, with noise and
    special floats; the temperature in steps; random fixture labels and nominal gains."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    like_a_run = draw(st.booleans())  # else anything goes
    n = draw(st.integers(1500, 3000) if like_a_run else st.one_of(st.integers(0, 60), st.integers(1500, 3000)))
    # steps: a repeated time, 0.2 s, a 30 s gap, a pause of 20 h (the readers refuse more than a day)
    weights = np.array([draw(st.floats(0, 0.3)), 1.0, draw(st.floats(0, 0.01)), draw(st.sampled_from([0, 0.01]))])
    t = T0_NS + np.cumsum(rng.choice([0, 200_000_000, 30 * 10**9, 72_000 * 10**9], p=weights / weights.sum(), size=n))
    hold = 100 if like_a_run else draw(st.sampled_from([1, 25, 100]))
    if like_a_run or draw(st.booleans()):  # held positions, as in a chamber run
        order = list(ALL_POSITIONS) if like_a_run or draw(st.booleans()) else rng.permutation(list(ALL_POSITIONS))
        names = np.resize(order[: draw(st.sampled_from([6, 12]))], n // hold + 1)
        g = np.repeat(np.array([ALL_POSITIONS[x] for x in names]), hold, axis=0)[:n]
        u = g * rng.normal(-0.55, 0.05, 3) + rng.normal(0.0, 0.01, 3)
    else:
        u = (
            draw(st.sampled_from([0.0, 1e-9, 0.55, 1e6]))
            * np.repeat(rng.normal(size=(n // hold + 1, 3)), hold, axis=0)[:n]
        )
    u = u + draw(st.sampled_from([0.0, 1e-6] if like_a_run else [0.0, 1e-6, 1e-2])) * rng.normal(size=(n, 3))
    if draw(st.booleans()) and n:
        swap = rng.integers(0, n, size=max(1, n // 50))
        t[swap] = t[rng.permutation(swap)]
    for _ in range(draw(st.integers(0, 6))):
        if n:
            u[draw(st.integers(0, n - 1)), draw(st.integers(0, 2))] = draw(_SPECIAL_FLOATS)
    span_s = int((t.max() - T0_NS) // 10**9) + 1 if n else draw(st.integers(0, 100))
    m = 10_000 if like_a_run else draw(st.one_of(st.just(10_000), st.integers(0, 100)))  # thermosensor samples
    tt = T0_NS + np.arange(0, span_s + 1, dtype=np.int64)[:m] * 10**9
    temp = np.repeat(rng.choice([-40.0, 20.0, 70.0], size=tt.size // 300 + 1), 300)[: tt.size]
    temp = temp + draw(st.sampled_from([0.0, 0.001] if like_a_run else [0.0, 0.001, 0.1])) * rng.normal(size=tt.size)
    for _ in range(draw(st.integers(0, 3))):
        if tt.size:
            temp[draw(st.integers(0, tt.size - 1))] = draw(_SPECIAL_FLOATS)
    k = draw(st.integers(0, 30))
    fixture = (
        make_frame(
            "fixture",
            {
                "t_ns": np.sort(T0_NS + rng.integers(-(10**10), 10**12, size=k)),
                "position": rng.choice(FIXTURE_LABELS, size=k).tolist(),
            },
        )
        if k
        else None
    )
    gain = draw(st.sampled_from([None, -0.55, 0.55, 0.0, 1e-300, 1e300]))
    return Run(
        meta=replace(META, nominal_gain_v_per_g=gain),
        voltmeter=make_frame("voltmeter", {"t_ns": t, "ux": u[:, 0], "uy": u[:, 1], "uz": u[:, 2]}),
        au_temperature=make_frame("au_temperature", {"t_ns": tt, "temp_c": temp}),
        fixture=fixture,
    )


@FAST
@given(random_run())
def test_segmenter_and_fit_raise_only_thermocal_errors(run):
    try:
        seg = segment_run(run, SMALL)
    except ThermocalError:
        return
    for s in seg.segments:
        assert s.t_start_ns <= s.t_end_ns and s.count >= 0
        assert s.position is None or s.position in ALL_POSITIONS
    calibrate(run)


def test_the_unmutated_files_are_runs():
    """The property tests start from files that read and segment (so the mutations hit a working path)."""
    run = read_run(_DIR / "zstd.mcap")
    assert run.voltmeter.height == 3000 and not run.warnings
    seg = segment_run(run, SMALL)
    assert len(seg.plateaus) >= 2 and len(seg.segments) >= 12
    obs, _ = observe_run(run, SMALL)
    assert fit_unit(run.meta.unit_serial, obs, CalibrationSettings(segment=SMALL)).per_plateau
