"""The broken-run corpus of issue 7, built from one valid simulated run (no binary files are committed).

:func:`build_corpus` writes every :data:`CASES` entry under a folder and returns ``{name: path}``. Each
:class:`Case` says what a reader, the segmenter or the fit must make of it: an error (its class, what it says, the
stream and the kind of place it names), or a run that is processed with a warning saying what was dropped (and, for
most, still calibrates to the simulator's truth).

The valid run is the short chamber program (about 3.5 h: seven plateaus, the test positions on four of them, the
verification positions on five) at 5 Hz. Every case has its own unit serial (``BAD-<k>``) so that ``fleet``
reports each one on its own.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import orjson
import polars as pl
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from pipeline.errors import CalibrationError, RunFormatError, ThermocalError
from pipeline.io.runs import write_run
from pipeline.run import Run
from pipeline.simulate.chamber import SimConfig, SimResult, simulate

RATE_HZ = 5.0
CHUNK_SIZE = 1 << 16  # ~20 chunks: truncation and corruption hit one chunk among many
BLOCK_SAMPLES = 200  # 40 s of voltmeter samples per message

#: a message rewriter: (topic, log_time_ns, data) -> the messages to write instead (none: dropped)
Edit = Callable[[str, int, bytes], list[tuple[str, int, bytes]]]


@functools.cache
def valid() -> SimResult:
    """The valid run everything is made from (cached: the corpus and the tests share it)."""
    return simulate(SimConfig(program="short", rate_hz=RATE_HZ, seed=7, unit_serial="BAD-00"))


def holds(position: str, stage: int | None = None) -> list[tuple[int, int]]:
    """(t_start_ns, t_end_ns) of the simulator's holds of ``position`` (in ``stage`` only, if given)."""
    return [
        (h["t_start_ns"], h["t_end_ns"])
        for h in valid().truth["holds"]
        if h["position"] == position and (stage is None or h["stage"] == stage)
    ]


def truth_at_normal_temp() -> tuple[np.ndarray, np.ndarray]:
    """The unit's true K (V/g) and U0 (V) at +20 C."""
    row = next(r for r in valid().truth["unit_constants_at"] if r["temp_c"] == 20.0)
    return np.array(row["K"]), np.array(row["U0"])


@dataclass(frozen=True)
class Case:
    """One broken run and what must come of it.

    ``error``: the ThermocalError subclass it must raise (None: the run is processed with a warning). ``says``:
    fragments of the error line, or of one warning. ``stream``: the stream or topic the error must name;
    ``where``: the kind of place it must give (``t_ns=``, ``row ``, ``byte ``), empty where none applies (a stream
    that is missing, a file that is not a run). ``calibrates``: a processed run still gives the unit's constants.
    """

    name: str
    build: Callable[[Path, str], Path]
    error: type[ThermocalError] | None
    says: tuple[str, ...]
    stream: str = ""
    where: str = ""
    calibrates: bool = False


# --- writing ----------------------------------------------------------------------------------------------------


def _run(unit: str, **frames: pl.DataFrame) -> Run:
    """The valid run with another unit serial and some stream tables replaced."""
    run = valid().run
    return Run(
        meta=replace(run.meta, unit_serial=unit, run_id=f"run-{unit}"),
        voltmeter=frames.get("voltmeter", run.voltmeter),
        au_temperature=frames.get("au_temperature", run.au_temperature),
        chamber=run.chamber,
        fixture=run.fixture,
    )


def _mcap(run: Run, path: Path, **opts) -> Path:
    return write_run(run, path, "mcap", block_samples=BLOCK_SAMPLES, chunk_size=CHUNK_SIZE, **opts)


def rewrite_mcap(
    src: Path,
    dst: Path,
    edit: Edit | None = None,
    meta: Callable[[dict[str, str]], dict[str, str] | None] | None = None,
    second_meta: dict[str, str] | None = None,
    **writer_opts,
) -> Path:
    """Copy the MCAP file ``src`` message by message (file order) through ``edit``, and its ``run`` metadata
    through ``meta`` (None from it: no metadata; ``second_meta``: a second ``run`` record after it). New topics get
    a schema of their own. ``writer_opts`` go to the mcap Writer (default: the corpus's chunk size, zstd)."""
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        meta_values = next(dict(m.metadata) for m in reader.iter_metadata() if m.name == "run")
        if meta is not None:
            meta_values = meta(meta_values)
        writer = Writer(f_out, **{"chunk_size": CHUNK_SIZE, "compression": CompressionType.ZSTD, **writer_opts})
        writer.start(profile="", library="thermocal badcorpus")
        schemas: dict[str, tuple[str, bytes]] = {}
        channels: dict[str, int] = {}
        if meta_values is not None:
            writer.add_metadata("run", meta_values)
        if second_meta is not None:
            writer.add_metadata("run", second_meta)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            schemas.setdefault(channel.topic, (schema.name, schema.data))
            out = (
                edit(channel.topic, message.log_time, message.data)
                if edit
                else [(channel.topic, message.log_time, message.data)]
            )
            for topic, log_time, data in out:
                if topic not in channels:
                    name, sdata = schemas.get(topic, (f"other{topic.replace('/', '.')}", b"{}"))
                    sid = writer.register_schema(name, "jsonschema", sdata)
                    channels[topic] = writer.register_channel(topic, "json", sid)
                writer.add_message(channels[topic], log_time, data, log_time)
        writer.finish()
    return dst


def _nth_voltmeter_message(n: int, change: Callable[[int, bytes], list[tuple[str, int, bytes]]]) -> Edit:
    """An edit that replaces the ``n``-th /voltmeter message by ``change(log_time, data)``."""
    seen = [0]

    def edit(topic: str, log_time: int, data: bytes) -> list[tuple[str, int, bytes]]:
        if topic == "/voltmeter":
            seen[0] += 1
            if seen[0] == n:
                return change(log_time, data)
        return [(topic, log_time, data)]

    return edit


def voltmeter_message_time(n: int) -> int:
    """log_time of the ``n``-th /voltmeter message (1-based) of the corpus's MCAP files."""
    return int(valid().run.voltmeter["t_ns"][(n - 1) * BLOCK_SAMPLES])


def _base(folder: Path, unit: str) -> Path:
    return _mcap(_run(unit), folder / f".base-{unit}.mcap")


def _chunk_spans(path: Path) -> list[tuple[int, int]]:
    """(offset, length) of every chunk record, from the summary."""
    with open(path, "rb") as f:
        return [(c.chunk_start_offset, c.chunk_length) for c in make_reader(f).get_summary().chunk_indexes]


# --- the cases --------------------------------------------------------------------------------------------------


def _truncated(fraction: float) -> Callable[[Path, str], Path]:
    def build(folder: Path, unit: str) -> Path:
        base = _base(folder, unit)
        offset, length = next(c for c in _chunk_spans(base) if c[0] + c[1] > fraction * base.stat().st_size)
        out = folder / f"truncated-{fraction:.2f}.mcap"
        out.write_bytes(base.read_bytes()[: offset + length // 2])  # cut in the middle of a chunk
        base.unlink()
        return out

    return build


def _crc(folder: Path, unit: str) -> Path:
    path = _mcap(_run(unit), folder / "corrupt-crc.mcap", compression="none")
    data = bytearray(path.read_bytes())
    i = data.index(b'"ux":[', len(data) // 2) + 8
    while not chr(data[i]).isdigit():
        i += 1
    data[i] = ord("7") if data[i] != ord("7") else ord("3")  # still valid JSON: only the CRC can tell
    path.write_bytes(bytes(data))
    return path


def _rewritten(
    name: str,
    edit: Edit | None = None,
    meta: Callable[[dict], dict | None] | None = None,
    second_meta: Callable[[dict], dict] | None = None,
) -> Callable[[Path, str], Path]:
    def build(folder: Path, unit: str) -> Path:
        base = _base(folder, unit)
        second = None
        if second_meta is not None:
            with open(base, "rb") as f:
                second = second_meta(next(dict(m.metadata) for m in make_reader(f).iter_metadata() if m.name == "run"))
        out = rewrite_mcap(base, folder / f"{name}.mcap", edit, meta, second)
        base.unlink()
        return out

    return build


def _drop_topic(topic: str) -> Edit:
    return lambda t, log_time, data: [] if t == topic else [(t, log_time, data)]


def _with_foreign_topics(topic: str, log_time: int, data: bytes) -> list[tuple[str, int, bytes]]:
    out = [(topic, log_time, data)]
    if topic == "/au/temperature":
        out += [("/camera/image", log_time, bytes(range(256)) * 4), ("/diagnostics", log_time, b'{"cpu": 0.5}')]
    return out


def _swap_messages(n: int) -> Edit:
    """Hold back the n-th /voltmeter message and write it after the (n+1)-th: a block logged late."""
    state: dict[str, tuple[str, int, bytes] | int] = {"seen": 0}

    def edit(topic: str, log_time: int, data: bytes) -> list[tuple[str, int, bytes]]:
        if topic != "/voltmeter":
            return [(topic, log_time, data)]
        state["seen"] += 1
        if state["seen"] == n:
            state["held"] = (topic, log_time, data)
            return []
        if state["seen"] == n + 1:
            return [(topic, log_time, data), state.pop("held")]
        return [(topic, log_time, data)]

    return edit


def _conflicting(log_time: int, data: bytes) -> list[tuple[str, int, bytes]]:
    """The message, then a second one with the same times and other ux values."""
    block = orjson.loads(data)
    block["ux"] = [x + 1e-3 if x is not None else None for x in block["ux"]]
    return [("/voltmeter", log_time, data), ("/voltmeter", log_time, orjson.dumps(block))]


def _frames_case(name: str, fmt: str, change: Callable[[], dict[str, pl.DataFrame]]) -> Callable[[Path, str], Path]:
    """The valid run with the stream tables ``change()`` returns, written as MCAP or Parquet."""

    def build(folder: Path, unit: str) -> Path:
        run = _run(unit, **change())
        return _mcap(run, folder / f"{name}.mcap") if fmt == "mcap" else write_run(run, folder / name, "parquet")

    return build


def _in_spans(t_ns: np.ndarray, spans: list[tuple[int, int]]) -> np.ndarray:
    mask = np.zeros(t_ns.size, dtype=bool)
    for a, b in spans:
        mask |= (t_ns >= a) & (t_ns < b)
    return mask


def _nonfinite() -> dict[str, pl.DataFrame]:
    v = valid().run.voltmeter
    t = v["t_ns"].to_numpy()
    ux = v["ux"].to_numpy().copy()
    uz = v["uz"].to_numpy().copy()
    a, _ = holds("TP4", stage=0)[0]
    ux[(t >= a + 20 * 10**9) & (t < a + 30 * 10**9)] = np.nan  # 10 s of NaN inside a hold
    uz[(t >= a - 100 * 10**9) & (t < a - 98 * 10**9)] = np.inf  # 2 s of +inf before it
    temp = valid().run.au_temperature
    tc = temp["temp_c"].to_numpy().copy()
    tc[1000:1005] = np.nan
    return {
        "voltmeter": v.with_columns(pl.Series("ux", ux), pl.Series("uz", uz)),
        "au_temperature": temp.with_columns(pl.Series("temp_c", tc)),
    }


def _all_nan() -> dict[str, pl.DataFrame]:
    v = valid().run.voltmeter
    return {"voltmeter": v.with_columns(*(pl.lit(float("nan")).alias(c) for c in ("ux", "uy", "uz")))}


def _gap() -> dict[str, pl.DataFrame]:
    v = valid().run.voltmeter
    a, _ = holds("TP2", stage=3)[0]
    t = v["t_ns"].to_numpy()
    return {"voltmeter": v.filter(pl.Series(~((t >= a - 100 * 10**9) & (t < a + 200 * 10**9))))}


def _shaken(spans: list[tuple[int, int]]) -> dict[str, pl.DataFrame]:
    """The unit shaken (3 mV of noise) during ``spans``: no static position there."""
    v = valid().run.voltmeter
    t = v["t_ns"].to_numpy()
    mask = _in_spans(t, spans)
    noise = np.random.default_rng(5).normal(0.0, 3e-3, (int(mask.sum()), 3))
    cols = []
    for k, c in enumerate(("ux", "uy", "uz")):
        x = v[c].to_numpy().copy()
        x[mask] += noise[:, k]
        cols.append(pl.Series(c, x))
    return {"voltmeter": v.with_columns(*cols)}


def _drifting() -> dict[str, pl.DataFrame]:
    """The thermosensor drifts by 0.1 C/min all along: no plateau anywhere."""
    temp = valid().run.au_temperature
    t = temp["t_ns"].to_numpy()
    return {
        "au_temperature": temp.with_columns(
            pl.Series("temp_c", temp["temp_c"].to_numpy() + 0.1 / 60 * (t - t[0]) / 1e9)
        )
    }


def _epoch_sample() -> dict[str, pl.DataFrame]:
    """The first voltmeter sample stamped 0 (1970): a logger that had not set its clock yet."""
    v = valid().run.voltmeter
    t = v["t_ns"].to_numpy().copy()
    t[0] = 0
    return {"voltmeter": v.with_columns(pl.Series("t_ns", t))}


def _parquet(name: str, change: Callable[[Path], None]) -> Callable[[Path, str], Path]:
    """A valid Parquet run directory, then ``change(directory)``."""

    def build(folder: Path, unit: str) -> Path:
        d = write_run(_run(unit), folder / name, "parquet")
        change(d)
        return d

    return build


def _voltmeter_parquet(change: Callable[[pl.DataFrame], pl.DataFrame]) -> Callable[[Path], None]:
    """Rewrite the run directory's voltmeter.parquet through ``change``."""

    def apply(d: Path) -> None:
        change(pl.read_parquet(d / "voltmeter.parquet")).write_parquet(d / "voltmeter.parquet")

    return apply


NULL_T_ROW = 1234


def _null_at(df: pl.DataFrame) -> pl.DataFrame:
    t = df["t_ns"].to_list()
    t[NULL_T_ROW] = None
    return df.with_columns(pl.Series("t_ns", t, dtype=pl.Int64))


def _file(name: str, content: bytes) -> Callable[[Path, str], Path]:
    def build(folder: Path, unit: str) -> Path:
        (folder / name).write_bytes(content)
        return folder / name

    return build


def _foreign_mcap(folder: Path, unit: str) -> Path:
    path = folder / "robot-bag.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="someone else")
        sid = w.register_schema("sensor_msgs/Imu", "ros2msg", b"float64[3] a")
        cid = w.register_channel("/imu", "cdr", sid)
        for k in range(100):
            w.add_message(cid, k * 10**7, bytes(24), k * 10**7)
        w.add_metadata("robot", {"name": "r2"})
        w.finish()
    return path


def _empty_dir(folder: Path, unit: str) -> Path:
    (folder / "empty-run").mkdir()
    return folder / "empty-run"


def _corrupt_page(d: Path) -> None:
    """Flip one bit inside the data of the first page of voltmeter.parquet's ``uy`` column (bit-rot)."""
    import pyarrow.parquet as pq

    f = d / "voltmeter.parquet"
    col = pq.ParquetFile(f).metadata.row_group(0).column(2)
    data = bytearray(f.read_bytes())
    data[col.data_page_offset + col.total_compressed_size // 2] ^= 0x04
    f.write_bytes(bytes(data))


def _meta_without(key: str) -> Callable[[dict], dict]:
    return lambda m: {k: v for k, v in m.items() if k != key}


T_BAD_MESSAGE = 37  # the /voltmeter message (1-based) spoilt by the message-level cases

CASES: tuple[Case, ...] = (
    # MCAP files cut, corrupt, or not as the format says
    Case(
        "mcap-truncated-mid-chunk",
        _truncated(0.7),
        None,
        ("truncated at byte", "kept", "complete chunk"),
        calibrates=True,
    ),
    Case(
        "mcap-truncated-in-first-chunk",
        _truncated(0.0),
        RunFormatError,
        ("truncated at byte", "no /voltmeter samples"),
        where="t_ns",
    ),
    Case(
        "mcap-no-summary",
        lambda folder, unit: _mcap(_run(unit), folder / "no-summary.mcap", summary=False),
        None,
        (),
        calibrates=True,
    ),
    Case(
        "mcap-corrupt-chunk-crc",
        _crc,
        RunFormatError,
        ("corrupt chunk", "CRC mismatch", "chunk at byte"),
        stream="/voltmeter",
        where="t_ns",
    ),
    Case(
        "mcap-message-not-matching-schema",
        _rewritten(
            "schema-mismatch",
            _nth_voltmeter_message(T_BAD_MESSAGE, lambda t, d: [("/voltmeter", t, d.replace(b'"uz"', b'"uZ"'))]),
        ),
        RunFormatError,
        (
            "does not match schema thermocal.VoltageBlock",
            "missing key 'uz'",
            f"t_ns={voltmeter_message_time(T_BAD_MESSAGE)}",
        ),
        stream="/voltmeter",
        where="t_ns=",
    ),
    Case(
        "mcap-missing-stream",
        _rewritten("no-temperature", _drop_topic("/au/temperature")),
        RunFormatError,
        ("required stream is missing",),
        stream="au_temperature",
    ),
    Case(
        "mcap-unknown-topics",
        _rewritten("foreign-topics", _with_foreign_topics),
        None,
        ("ignored topics that are not part of a run", "/camera/image", "/diagnostics"),
        calibrates=True,
    ),
    Case(
        "mcap-backwards-timestamps",
        _rewritten("backwards", _swap_messages(T_BAD_MESSAGE)),
        None,
        ("voltmeter", "out of time order", f"t_ns={voltmeter_message_time(T_BAD_MESSAGE)} after"),
        calibrates=True,
    ),
    Case(
        "mcap-repeated-message",
        _rewritten("repeated", _nth_voltmeter_message(T_BAD_MESSAGE, lambda t, d: [("/voltmeter", t, d)] * 2)),
        None,
        ("voltmeter", f"dropped {BLOCK_SAMPLES} repeated samples", f"t_ns={voltmeter_message_time(T_BAD_MESSAGE)}"),
        calibrates=True,
    ),
    Case(
        "mcap-conflicting-duplicates",
        _rewritten("conflicting", _nth_voltmeter_message(T_BAD_MESSAGE, _conflicting)),
        RunFormatError,
        ("two different samples at the same time",),
        stream="voltmeter",
        where=f"t_ns={voltmeter_message_time(T_BAD_MESSAGE)}",
    ),
    Case(
        "mcap-metadata-missing",
        _rewritten("no-metadata", meta=lambda m: None),
        RunFormatError,
        ("no run metadata",),
        stream="metadata",
    ),
    Case(
        "mcap-metadata-malformed",
        _rewritten("bad-metadata", meta=lambda m: {**m, "normal_temp_c": "warm"}),
        RunFormatError,
        ("'normal_temp_c' is not a number",),
        stream="metadata",
    ),
    Case(
        "mcap-two-run-metadata",
        _rewritten("two-run-records", second_meta=lambda m: {**m, "unit_serial": "AU-9999"}),
        RunFormatError,
        ("two 'run' metadata records that differ",),
        stream="metadata",
        where="byte ",
    ),
    Case(
        "mcap-metadata-without-serial",
        _rewritten("no-serial", meta=_meta_without("unit_serial")),
        RunFormatError,
        ("'unit_serial' is missing",),
        stream="metadata",
    ),
    # samples that cannot be used as they are
    Case(
        "nan-inf-samples-parquet",
        _frames_case("nonfinite", "parquet", _nonfinite),
        None,
        ("voltmeter", "non-finite samples excluded (not static), ", "s after the start)"),
        calibrates=True,
    ),
    Case(
        "nan-inf-samples-mcap",
        _frames_case("nonfinite", "mcap", _nonfinite),
        None,
        ("au_temperature", "5 non-finite samples ignored", "first at t_ns="),
        calibrates=True,
    ),
    Case(
        "voltmeter-all-nan",
        _frames_case("all-nan", "mcap", _all_nan),
        RunFormatError,
        ("unit BAD-17 has a dead channel: ux has no finite sample",),
        stream="voltmeter",
    ),
    Case(
        "voltmeter-gap",
        _frames_case("gap", "mcap", _gap),
        None,
        ("voltmeter", "1 gap(s) without samples", "300.2 s after t_ns="),
        calibrates=True,
    ),
    Case(
        "clock-jump",
        _frames_case("epoch-sample", "mcap", _epoch_sample),
        RunFormatError,
        ("time jumps forward", "after t_ns=0"),
        stream="voltmeter",
        where="t_ns=",
    ),
    # runs the segmenter and the fit cannot use (entirely or in part)
    Case(
        "plateau-missing-a-position",
        _frames_case("shaken-once", "mcap", lambda: _shaken(holds("TP3", stage=0))),
        None,
        ("plateau 0 at 20.0 C (20", " UTC): fewer than six test positions (missing TP3)"),
        calibrates=True,
    ),
    # (five of the six positions determine the 12 constants, issue 14: without the two y positions they do not)
    Case(
        "no-plateau-with-six-positions",
        _frames_case("shaken-always", "mcap", lambda: _shaken(holds("TP2") + holds("TP4"))),
        CalibrationError,
        ("no temperature plateau with the six test positions", "missing TP2, TP4"),
        stream="voltmeter",
        where="t_ns=",
    ),
    Case(
        "temperature-never-stabilises",
        _frames_case("drifting", "mcap", _drifting),
        CalibrationError,
        ("no temperature plateau: the AU temperature never stays within",),
        stream="au_temperature",
        where="t_ns=",
    ),
    # Parquet runs
    Case(
        "parquet-wrong-column-type",
        _parquet("text-ux", _voltmeter_parquet(lambda v: v.with_columns(pl.col("ux").cast(pl.String)))),
        RunFormatError,
        ("voltmeter.parquet", "column 'ux' has type String, expected Float64"),
        stream="voltmeter",
    ),
    Case(
        "parquet-float-timestamps",
        _parquet("float-t", _voltmeter_parquet(lambda v: v.with_columns(pl.col("t_ns").cast(pl.Float64)))),
        RunFormatError,
        ("voltmeter.parquet", "column 't_ns' has type Float64, expected Int64"),
        stream="voltmeter",
    ),
    Case(
        "parquet-null-timestamp",
        _parquet("null-t", _voltmeter_parquet(_null_at)),
        RunFormatError,
        ("t_ns is missing (null)",),
        stream="voltmeter",
        where=f"row {NULL_T_ROW}",
    ),
    Case(
        "parquet-empty-file",
        _parquet("empty-temperature", lambda d: (d / "au_temperature.parquet").write_bytes(b"")),
        RunFormatError,
        ("au_temperature.parquet", "not a readable Parquet file"),
        stream="au_temperature",
    ),
    Case(
        "parquet-no-rows",
        _parquet("no-rows", _voltmeter_parquet(lambda v: v.head(0))),
        RunFormatError,
        ("required stream has no samples",),
        stream="voltmeter",
    ),
    Case(
        "parquet-corrupted-page",
        _parquet("bit-rot", _corrupt_page),
        RunFormatError,
        ("voltmeter.parquet", "column 'uy': page checksum mismatch", "corrupted"),
        stream="voltmeter",
        where="rows 0..",
    ),
    Case(
        "parquet-metadata-malformed",
        _parquet("bad-json", lambda d: (d / "run.json").write_bytes(b'{"unit_serial": ')),
        RunFormatError,
        ("run.json", "cannot read the run metadata"),
        stream="metadata",
    ),
    Case(
        "parquet-metadata-missing",
        _parquet("no-json", lambda d: (d / "run.json").unlink()),
        RunFormatError,
        ("run.json is missing",),
    ),
    # files that are not runs at all
    Case("empty-file", _file("empty.mcap", b""), RunFormatError, ("empty file",)),
    Case(
        "text-file",
        _file("notes.mcap", b"AU-0001 looked fine on Tuesday\n" * 20),
        RunFormatError,
        ("not an MCAP file",),
    ),
    Case(
        "image-file",
        _file("photo.mcap", b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8),
        RunFormatError,
        ("not an MCAP file",),
    ),
    Case(
        "lfs-pointer",
        _file("pointer.mcap", b"version https://git-lfs.github.com/spec/v1\noid sha256:ab\nsize 9\n"),
        RunFormatError,
        ("Git LFS pointer",),
    ),
    Case("foreign-mcap", _foreign_mcap, RunFormatError, ("no run topics or run metadata found", "/imu")),
    Case(
        "csv-file",
        _file("samples.csv", b"t_ns,ux,uy,uz\n1,0,0,0\n"),
        RunFormatError,
        ("expected a .mcap file or a Parquet run directory",),
    ),
    Case("empty-directory", _empty_dir, RunFormatError, ("run.json is missing",)),
)


def build_corpus(folder: Path) -> dict[str, Path]:
    """Write every case under ``folder`` (one sub-folder each); returns ``{case name: run path}``."""
    out = {}
    for k, case in enumerate(CASES, start=1):
        sub = folder / case.name
        sub.mkdir(parents=True, exist_ok=True)
        out[case.name] = case.build(sub, f"BAD-{k:02d}")
    return out
