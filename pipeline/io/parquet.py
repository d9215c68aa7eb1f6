"""Chamber runs as Parquet directories (docs/log-format.md).

A run directory holds ``voltmeter.parquet``, ``au_temperature.parquet``, optional ``chamber.parquet`` and
``fixture.parquet`` (the columns of :data:`pipeline.run.STREAM_COLUMNS`), and ``run.json`` with the metadata as
strings. Files are zstd-compressed, written by pyarrow with a CRC-32 in every page header (the Parquet format's
page checksums). Reading first checks those checksums against the pages' bytes (:func:`verify_page_checksums`: the
footer's column-chunk offsets from pyarrow, each page header's ``crc`` field, ``zlib.crc32`` over the memory-mapped
page; about a second per GB), so a flipped bit in a page is a one-line :class:`pipeline.errors.RunFormatError`
naming the file, the column and its rows, never silently different values; pages written without a checksum (other
writers, older thermocal runs) are read unchecked. Then polars' reader decodes (one chunk per row group), zero-copy
where the file already has the canonical types; integer or narrower float columns are widened, a timestamp column
is taken as nanoseconds; anything else (e.g. strings where numbers are expected) is a RunFormatError naming the file
and the column.

A run with several units (log-format.md) has a string column ``unit`` in ``voltmeter.parquet`` and
``au_temperature.parquet`` (written unit after unit, each unit's rows in row groups of their own) and ``units`` in
``run.json``; ``chamber.parquet`` and ``fixture.parquet`` are shared. Reading splits those tables by unit: a unit's rows
in one contiguous stretch (as written here) are a slice of the table, not a copy.

Memory is bounded before anything is decoded (:mod:`pipeline.io.limits`): the rows the footers declare, times the
columns' widths, must fit :func:`pipeline.io.limits.decoded_cap` (104 M constant rows compress to 2 MB, and decode to
3.3 GB); every page may declare no more uncompressed bytes than its codec can expand its stored bytes to, and at most
``MAX_CHUNK_BYTES``. Only regular files are read (a FIFO named ``voltmeter.parquet`` is one line, never a hang).
"""

from __future__ import annotations

import mmap
import shutil
import tempfile
import zlib
from pathlib import Path

import orjson
import polars as pl
import pyarrow.parquet as pq

from pipeline.errors import RunFormatError
from pipeline.io.checks import assemble_run, assemble_units, writable_streams, writable_units
from pipeline.io.files import read_regular_bytes, require_regular
from pipeline.io.limits import MAX_CHUNK_BYTES, decoded_cap, human_bytes, ratio_limit
from pipeline.run import PER_UNIT_STREAMS, REQUIRED_STREAMS, STREAM_COLUMNS, UNITS_KEY, Run, UnitRuns

META_FILE = "run.json"
#: Rows per row group written (polars' reader gives one chunk per row group; the segmenter reads slabs of them).
ROW_GROUP_ROWS = 1 << 17
RUN_FILES = frozenset({META_FILE, *(f"{s}.parquet" for s in STREAM_COLUMNS)})
#: the column naming each row's unit in the per-unit streams of a run with several units
UNIT_COLUMN = "unit"


def write_parquet_run(run: Run | UnitRuns, directory: str | Path) -> Path:
    """Write ``run`` (one unit's, or a :class:`UnitRuns` of several) as a Parquet run directory; return its path.

    The directory is written beside its final place under a temporary name, then renamed. An existing run directory
    (holding only run files) is replaced; any other existing non-empty directory is refused.
    """
    target = Path(directory)
    if isinstance(run, UnitRuns):
        shared, per_unit = writable_units(run, path=str(target))
        meta_values = run.meta_values
    else:
        shared, per_unit = writable_streams(run, path=str(target)), {}
        meta_values = run.meta.to_strings()
    if target.exists():
        if not target.is_dir() or not {p.name for p in target.iterdir()} <= RUN_FILES:
            raise RunFormatError("exists and is not a Parquet run directory; not replacing it", path=str(target))
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    try:
        for stream, df in shared.items():
            _write_stream(df, tmp / f"{stream}.parquet")
        for stream in PER_UNIT_STREAMS if per_unit else ():
            _write_unit_stream({u: streams[stream] for u, streams in per_unit.items()}, tmp / f"{stream}.parquet")
        meta = orjson.dumps(meta_values, option=orjson.OPT_INDENT_2 | orjson.OPT_SORT_KEYS)
        (tmp / META_FILE).write_bytes(meta + b"\n")
        tmp.chmod(0o755)
        if target.exists():
            old = target.with_name(f"{tmp.name}.old")
            target.rename(old)
            tmp.rename(target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


_WRITE_OPTIONS = dict(compression="zstd", compression_level=3, write_statistics=True, write_page_checksum=True)


def _write_stream(df: pl.DataFrame, path: Path) -> None:
    """One stream's file: zstd, statistics, a CRC-32 in every page header; dictionary encoding for strings only."""
    strings = [c for c, dt in df.schema.items() if dt == pl.String]
    pq.write_table(
        df.to_arrow(), path, use_dictionary=strings or False, row_group_size=ROW_GROUP_ROWS, **_WRITE_OPTIONS
    )


def _write_unit_stream(tables: dict[str, pl.DataFrame], path: Path) -> None:
    """One per-unit stream of a run with several units: the units' tables one after the other with their ``unit``
    column (dictionary-encoded), each unit's rows in row groups of their own (no table of all units is built)."""
    writer = None
    try:
        for serial, df in tables.items():
            table = df.with_columns(pl.lit(serial, dtype=pl.String).alias(UNIT_COLUMN)).to_arrow()
            if writer is None:
                writer = pq.ParquetWriter(path, table.schema, use_dictionary=[UNIT_COLUMN], **_WRITE_OPTIONS)
            writer.write_table(table, row_group_size=ROW_GROUP_ROWS)
    finally:
        if writer is not None:
            writer.close()


def read_parquet_run(directory: str | Path) -> Run:
    """Read a single-unit Parquet run directory into a :class:`Run` (see the module doc for what is accepted); a
    run with several units is refused unless it holds one (:func:`read_parquet_units` reads every unit)."""
    return read_parquet_units(directory).one()


def read_parquet_units(directory: str | Path, only: set[str] | None = None) -> UnitRuns:
    """Read a Parquet run directory of one or several units as a :class:`UnitRuns` (a single-unit run: one unit,
    ``several`` False); ``only``: the serials wanted, of a run with several units."""
    d = Path(directory)
    if not d.is_dir():
        raise RunFormatError("not a directory (a Parquet run is a directory)", path=str(d))
    meta_path = d / META_FILE
    if not meta_path.is_file():
        raise RunFormatError(f"not a Parquet run directory: {META_FILE} is missing", path=str(d))
    meta = _read_meta(meta_path)
    several = UNITS_KEY in meta
    files: dict[str, Path] = {}
    for stream in STREAM_COLUMNS:
        f = d / f"{stream}.parquet"
        if f.exists():
            require_regular(f)
            files[stream] = f
        elif stream in REQUIRED_STREAMS:
            raise RunFormatError(f"required stream file {f.name} is missing", path=str(d), stream=stream)
    _check_decoded_size(d, files)
    frames: dict[str, pl.DataFrame] = {}
    per_unit: dict[str, dict[str, pl.DataFrame]] = {}
    for stream, f in files.items():
        if several and stream in PER_UNIT_STREAMS:
            for serial, df in _read_unit_stream(f, stream, only).items():
                per_unit.setdefault(serial, {})[stream] = df
        else:
            frames[stream] = _read_stream(f, stream)
    if several:
        return assemble_units(
            meta,
            frames,
            per_unit,
            path=str(d),
            warnings=[],
            stream_label=lambda serial, stream: f"{stream}.parquet unit {serial}",
            only=only,
        )
    if any(UNIT_COLUMN in pq.read_schema(d / f"{s}.parquet").names for s in frames if s in PER_UNIT_STREAMS):
        raise RunFormatError(
            f"the streams have a {UNIT_COLUMN!r} column but {META_FILE} has no {UNITS_KEY!r} key",
            path=str(d),
            stream="metadata",
        )
    run = assemble_run(meta, frames, path=str(d), warnings=[])
    return UnitRuns({run.meta.unit_serial: run}, source=str(d), warnings=run.warnings)


def _check_decoded_size(d: Path, files: dict[str, Path]) -> None:
    """The rows the files' footers declare, decoded, within :func:`pipeline.io.limits.decoded_cap` (checked before
    anything is decoded)."""
    total, biggest = 0, ("", 0)
    for stream, f in files.items():
        try:
            rows = pq.ParquetFile(f).metadata.num_rows
        except Exception as exc:
            raise RunFormatError(
                f"not a readable Parquet file ({_one_line(exc)})", path=str(f), stream=stream
            ) from None
        width = sum(8 if dtype != pl.String else 64 for dtype in STREAM_COLUMNS[stream].values())
        total += rows * width
        biggest = max(biggest, (stream, rows * width), key=lambda x: x[1])
    cap = decoded_cap()
    if total > cap:
        stream, size = biggest
        raise RunFormatError(
            f"the files declare {human_bytes(total)} of samples once decoded ({stream}: {human_bytes(size)}), more "
            f"than {human_bytes(cap)}, a quarter of the memory this process may use: the run is too large for this "
            "machine (split it, or read it on a larger one); nothing was decoded",
            path=str(d),
            stream=stream,
        )


def _read_meta(path: Path) -> dict[str, str]:
    try:
        values = orjson.loads(read_regular_bytes(path, what="run metadata", limit=16 << 20, error=RunFormatError))
    except orjson.JSONDecodeError as exc:
        raise RunFormatError(f"cannot read the run metadata ({exc})", path=str(path), stream="metadata") from None
    if not isinstance(values, dict):
        raise RunFormatError("run metadata is not a JSON object", path=str(path), stream="metadata")
    out = {}
    for key, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (str, int, float)):
            raise RunFormatError(
                f"metadata key {key!r} must be a string, got {value!r}", path=str(path), stream="metadata"
            )
        out[key] = value if isinstance(value, str) else repr(value)
    return out


def _read_unit_stream(path: Path, stream: str, only: set[str] | None) -> dict[str, pl.DataFrame]:
    """A per-unit stream of a run with several units, split by its ``unit`` column: {serial: canonical table}.
    A unit's rows in one contiguous stretch are a slice of the table read (no copy); rows of units interleaved are
    gathered per unit (a copy). A missing or null ``unit`` is a RunFormatError naming the file and the row."""
    df = _read_frame(path, stream)
    if UNIT_COLUMN not in df.columns:
        raise RunFormatError(
            f"column {UNIT_COLUMN!r} is missing: {META_FILE} lists units (columns: {', '.join(df.columns)})",
            path=str(path),
            stream=stream,
        )
    units = _canonical_column(df[UNIT_COLUMN], pl.String(), path=str(path), stream=stream)
    if units.null_count():
        raise RunFormatError(
            f"column {UNIT_COLUMN!r} is missing (null)",
            path=str(path),
            stream=stream,
            where=f"row {units.is_null().arg_max()}",
        )
    table = _canonical(df, stream, path)
    change = (units != units.shift(1)).fill_null(True)
    starts = change.arg_true().to_list()
    values = units.gather(starts).to_list()
    if len(set(values)) == len(values):  # each unit one contiguous stretch: slices
        bounds = [*starts, table.height]
        out = {u: table.slice(a, b - a) for u, a, b in zip(values, bounds[:-1], bounds[1:])}
    else:
        out = {u: table.filter(units == u) for u in dict.fromkeys(values)}
    return {u: t for u, t in out.items() if only is None or u in only}


def _read_frame(path: Path, stream: str) -> pl.DataFrame:
    # polars' own reader decodes straight into the frame's memory, one chunk per row group (no rechunking copy):
    # at 59 M rows it needs half the memory and a third of the CPU time of pyarrow.read_table + from_arrow.
    verify_page_checksums(path, stream)
    try:
        return pl.read_parquet(path)
    except (pl.exceptions.PolarsError, OSError) as exc:
        raise RunFormatError(f"not a readable Parquet file ({_one_line(exc)})", path=str(path), stream=stream) from None


def _read_stream(path: Path, stream: str) -> pl.DataFrame:
    return _canonical(_read_frame(path, stream), stream, path)


def _canonical(df: pl.DataFrame, stream: str, path: Path) -> pl.DataFrame:
    """The stream's canonical columns of ``df`` (see the module doc)."""
    columns = []
    for name, dtype in STREAM_COLUMNS[stream].items():
        if name not in df.columns:
            raise RunFormatError(
                f"column {name!r} is missing (columns: {', '.join(df.columns)})", path=str(path), stream=stream
            )
        columns.append(_canonical_column(df[name], dtype, path=str(path), stream=stream))
    return pl.DataFrame(columns)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _canonical_column(s: pl.Series, dtype: pl.DataType, *, path: str, stream: str) -> pl.Series:
    """``s`` with the canonical dtype when that is safe, else RunFormatError naming file and column."""
    have = s.dtype
    if have == dtype:
        out = s
    elif dtype == pl.Float64 and (have.is_float() or have.is_integer()):
        out = s.cast(pl.Float64)
    elif dtype == pl.Int64 and have.is_integer():
        try:
            out = s.cast(pl.Int64, strict=True)
        except pl.exceptions.PolarsError:
            raise RunFormatError(
                f"column {s.name!r} ({have}) has values beyond int64", path=path, stream=stream
            ) from None
    elif dtype == pl.Int64 and isinstance(have, pl.Datetime):
        out = s.dt.epoch("ns")
    elif dtype == pl.String and isinstance(have, (pl.Categorical, pl.Enum)):
        out = s.cast(pl.String)
    else:
        raise RunFormatError(f"column {s.name!r} has type {have}, expected {dtype}", path=path, stream=stream)
    if dtype == pl.Float64 and out.null_count():
        out = out.fill_null(float("nan"))  # missing samples are NaN, as in MCAP files
    return out.rename(s.name)


# --- page checksums -----------------------------------------------------------------------------------------------
# Thrift compact protocol, just enough to read a PageHeader's compressed_page_size (field 3) and crc (field 4) and
# skip everything else (parquet.thrift). Field types of the compact protocol:
(_T_TRUE, _T_FALSE, _T_BYTE, _T_I16, _T_I32, _T_I64, _T_DOUBLE, _T_BINARY, _T_LIST, _T_SET, _T_MAP, _T_STRUCT) = range(
    1, 13
)


class _Corrupt(Exception):
    """A page header that cannot be parsed."""


def _varint(buf, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = buf[i]
        i += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, i
        shift += 7
        if shift > 63:
            raise _Corrupt("varint too long")


def _zigzag(n: int) -> int:
    return (n >> 1) ^ -(n & 1)


def _skip(buf, i: int, ftype: int, depth: int = 0) -> int:
    if depth > 32:
        raise _Corrupt("nesting too deep")
    if ftype in (_T_TRUE, _T_FALSE):
        return i
    if ftype == _T_BYTE:
        return i + 1
    if ftype in (_T_I16, _T_I32, _T_I64):
        return _varint(buf, i)[1]
    if ftype == _T_DOUBLE:
        return i + 8
    if ftype == _T_BINARY:
        n, i = _varint(buf, i)
        return i + n
    if ftype in (_T_LIST, _T_SET):
        head = buf[i]
        i += 1
        n, etype = head >> 4, head & 0x0F
        if n == 15:
            n, i = _varint(buf, i)
        for _ in range(n):
            i = _skip(buf, i, etype, depth + 1)
        return i
    if ftype == _T_MAP:
        n, i = _varint(buf, i)
        if n:
            kv = buf[i]
            i += 1
            for _ in range(n):
                i = _skip(buf, _skip(buf, i, kv >> 4, depth + 1), kv & 0x0F, depth + 1)
        return i
    if ftype == _T_STRUCT:
        while True:
            head = buf[i]
            i += 1
            if head == 0:
                return i
            if not head >> 4:
                i = _varint(buf, i)[1]
            i = _skip(buf, i, head & 0x0F, depth + 1)
    raise _Corrupt(f"unknown field type {ftype}")


def _page_header(buf, i: int) -> tuple[int, int | None, int, int]:
    """(compressed page size, crc or None, offset of the page's data, uncompressed page size) of the PageHeader at
    ``i``."""
    fid = 0
    size = crc = raw = None
    while True:
        head = buf[i]
        i += 1
        if head == 0:
            break
        ftype = head & 0x0F
        if head >> 4:
            fid += head >> 4
        else:
            fid, i = _varint(buf, i)
            fid = _zigzag(fid)
        if ftype == _T_I32 and fid in (2, 3, 4):
            value, i = _varint(buf, i)
            if fid == 2:
                raw = _zigzag(value)
            elif fid == 3:
                size = _zigzag(value)
            else:
                crc = _zigzag(value) & 0xFFFFFFFF
        else:
            i = _skip(buf, i, ftype)
    if size is None or size < 0:
        raise _Corrupt("page header without a valid compressed size")
    if raw is None or raw < 0:
        raise _Corrupt("page header without a valid uncompressed size")
    return size, crc, i, raw


def verify_page_checksums(path: str | Path, stream: str | None = None) -> int:
    """Check every page's CRC-32 (Parquet page checksums) in a Parquet file; return the number of pages checked.

    The column chunks' offsets come from the file's footer (pyarrow); each page header is read, and ``zlib.crc32``
    of the page's bytes (as stored, compressed) compared with the header's ``crc``. Pages without a ``crc`` are
    skipped. A mismatch, a page header that cannot be read, or a page declaring more uncompressed bytes than its
    codec can expand its stored bytes to (:mod:`pipeline.io.limits`), is a one-line RunFormatError naming the file,
    the column and the rows of its row group.
    """
    path = Path(path)
    try:
        meta = pq.ParquetFile(path).metadata
    except Exception as exc:
        raise RunFormatError(f"not a readable Parquet file ({_one_line(exc)})", path=str(path), stream=stream) from None
    checked = 0
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        view = memoryview(buf)
        try:
            first_row = 0
            for g in range(meta.num_row_groups):
                rg = meta.row_group(g)
                rows = f"rows {first_row}..{first_row + rg.num_rows - 1}"
                first_row += rg.num_rows
                for c in range(rg.num_columns):
                    col = rg.column(c)
                    name = col.path_in_schema
                    codec = str(col.compression)
                    start = col.dictionary_page_offset or col.data_page_offset
                    end = start + col.total_compressed_size
                    i = start
                    while i < end:
                        try:
                            size, crc, data, raw = _page_header(view, i)
                        except (_Corrupt, IndexError) as exc:
                            raise RunFormatError(
                                f"column {name!r}: unreadable page header at byte {i} ({exc}): the file is corrupted",
                                path=str(path),
                                stream=stream,
                                where=rows,
                            ) from None
                        if data + size > end:
                            raise RunFormatError(
                                f"column {name!r}: page at byte {i} runs past its column chunk: the file is corrupted",
                                path=str(path),
                                stream=stream,
                                where=rows,
                            )
                        most = ratio_limit(codec, size)
                        if raw > MAX_CHUNK_BYTES or (most is not None and raw > most):
                            raise RunFormatError(
                                f"column {name!r}: page at byte {i} declares {human_bytes(raw)} uncompressed from "
                                f"{human_bytes(size)} of {codec} data: beyond what that format expands to or the "
                                f"{human_bytes(MAX_CHUNK_BYTES)} a page may take; not decoded",
                                path=str(path),
                                stream=stream,
                                where=rows,
                            )
                        if crc is not None:
                            if zlib.crc32(view[data : data + size]) != crc:
                                raise RunFormatError(
                                    f"column {name!r}: page checksum mismatch at byte {i}: the file is corrupted",
                                    path=str(path),
                                    stream=stream,
                                    where=rows,
                                )
                            checked += 1
                        i = data + size
        finally:
            view.release()
    return checked
