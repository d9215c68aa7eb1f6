"""Chamber runs as MCAP files (docs/log-format.md): a writer, and a fast reader that says what is wrong with a bad file.

Layout: one metadata record named ``run`` (string to string, written before any data); one channel per stream, topics
``/voltmeter``, ``/au/temperature``, ``/chamber``, ``/fixture``; message encoding ``json``, schema encoding
``jsonschema``, schema names ``thermocal.VoltageBlock`` ... with the schema files of the package's
``schemas/``. A message holds a block of samples (equal-length arrays) and is logged at its first sample's
``t_ns``; ``/fixture`` messages hold one event each. A run with several units (:class:`pipeline.run.UnitRuns`) has per
unit the topics ``/unit/<serial>/voltmeter`` and ``/unit/<serial>/au/temperature`` (:func:`unit_topic`), and the
shared ``/chamber`` and ``/fixture``; the metadata lists the units (``units``). Topics interleave in time order; chunks
are zstd-compressed. JSON has no NaN or infinity: a non-finite sample is written as ``null`` and read back as NaN (so
+-inf come back as NaN).

The reader works on the memory-mapped file at the level of MCAP records, so it can say at which byte a file is cut or
corrupt, and read what is complete:

- it walks the top-level records from the start (cheap: chunks are not opened during the walk), which reads files with
  or without a summary section or indexes alike;
- with a summary that repeats the channels, chunks whose message index lists only topics that are not part of a run
  are skipped without being decompressed; messages of unknown topics are never decoded;
- chunks are decompressed and CRC-checked a few ahead in two worker threads (zstd and crc32 release the GIL) while
  the main thread decodes;
- each run-topic message is decoded by the codec of its channel's message encoding (:data:`CODECS`: ``json``, and
  ``protobuf`` from :mod:`pipeline.io.codec_protobuf`) into numpy arrays, copied straight into pieces of up to a
  million samples which become the chunks of the polars columns: no per-sample objects, no copy of the whole
  table; chunk data is read (pread) and decompressed into a few reused buffers, not through the memory map, so
  neither the file's pages nor per-chunk allocations add to the process's memory;
- a truncated file keeps its complete chunks, with a warning in ``Run.warnings`` saying what was dropped; so does a
  file that turns into zeros (a logger's preallocated file, never written to the end: an opcode 0 record, which MCAP
  does not have, ends the walk at once instead of stepping through gigabytes of zeros);
- memory is bounded (:mod:`pipeline.io.limits`): a chunk may declare no more uncompressed bytes than its codec can
  expand its data to and at most ``MAX_CHUNK_BYTES``, a message at most ``MAX_MESSAGE_BYTES``, and the decoded
  samples at most :func:`pipeline.io.limits.decoded_cap`; lz4 and zstd chunks are decompressed into buffers of
  that bounded size, never of a size the file alone declares;
- only a regular file is read (:func:`pipeline.io.files.open_regular`: a FIFO or a device is one line, never a hang).

Every problem raises :class:`pipeline.errors.RunFormatError` naming the file, the topic and the byte or ``t_ns``.
"""

from __future__ import annotations

import mmap
import os
import struct
import uuid
import zlib
from collections import deque
from collections.abc import Callable, Generator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import zstandard
from mcap.writer import CompressionType, IndexType, Writer

import pipeline
from pipeline.errors import RunFormatError
from pipeline.io.checks import assemble_run, assemble_units, writable_streams, writable_units
from pipeline.io.codec_protobuf import PROTOBUF_CODEC
from pipeline.io.codecs import JSON_CODEC, SCHEMA_NAMES, BlockCodec, BlockMismatch
from pipeline.io.files import open_regular
from pipeline.io.limits import (
    MAX_CHUNK_BYTES,
    MAX_MESSAGE_BYTES,
    decoded_cap,
    human_bytes,
    memory_budget,
    ratio_limit,
)
from pipeline.run import PER_UNIT_STREAMS, REQUIRED_STREAMS, SLAB_SAMPLES, STREAM_COLUMNS, UNITS_KEY, Run, UnitRuns

MAGIC = b"\x89MCAP0\r\n"
RUN_METADATA_NAME = "run"
TOPICS: dict[str, str] = {
    "voltmeter": "/voltmeter",
    "au_temperature": "/au/temperature",
    "chamber": "/chamber",
    "fixture": "/fixture",
}
STREAM_OF_TOPIC: dict[str, str] = {topic: stream for stream, topic in TOPICS.items()}
#: topics of one unit of a run with several units start with this, then the serial, then the stream's topic
UNIT_TOPIC_PREFIX = "/unit/"


def unit_topic(serial: str, stream: str) -> str:
    """The topic of one unit's own stream in a run with several units (``/unit/AU-0102/voltmeter``)."""
    return f"{UNIT_TOPIC_PREFIX}{serial}{TOPICS[stream]}"


def parse_topic(topic: str) -> tuple[str | None, str | None]:
    """(unit serial or None, stream or None) of a topic: ``/voltmeter`` is (None, "voltmeter"),
    ``/unit/AU-0102/au/temperature`` ("AU-0102", "au_temperature"); (None, None) for a topic not part of a run. The
    serial is what lies between the prefix and the stream's topic, so a serial with a ``/`` in it (``IMU/A1``) reads
    back as :func:`unit_topic` wrote it."""
    if topic.startswith(UNIT_TOPIC_PREFIX):
        rest = topic[len(UNIT_TOPIC_PREFIX) :]
        for stream in PER_UNIT_STREAMS:
            if rest.endswith(TOPICS[stream]) and len(rest) > len(TOPICS[stream]):
                return rest[: -len(TOPICS[stream])], stream
        return None, None
    return None, STREAM_OF_TOPIC.get(topic)


# MCAP record opcodes (MCAP specification).
_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _MESSAGE_INDEX, _CHUNK_INDEX = 1, 2, 3, 4, 5, 6, 7, 8
_METADATA, _DATA_END = 0x0C, 0x0F
_RECORD_NAMES = {
    1: "header",
    2: "footer",
    3: "schema",
    4: "channel",
    5: "message",
    6: "chunk",
    7: "message index",
    8: "chunk index",
    9: "attachment",
    10: "attachment index",
    11: "statistics",
    12: "metadata",
    13: "metadata index",
    14: "summary offset",
    15: "data end",
}

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start time, end time, uncompressed size, uncompressed crc
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHANNEL_HEAD = struct.Struct("<HH")  # channel id, schema id

_CHUNKS_AHEAD = 4  # chunks decompressed ahead of decoding
_DECOMPRESS_THREADS = 2  # worker threads decompressing and CRC-checking chunks (both release the GIL)
_PIECE_SAMPLES = (
    SLAB_SAMPLES  # decoded blocks are copied into pieces of up to this many samples (one polars chunk each)
)
_FIRST_PIECE_SAMPLES = 1024  # pieces start this small and double (short streams stay small)
_NUMPY_DTYPES = {pl.Int64: np.int64, pl.Float64: np.float64, pl.String: object}


#: Codecs by channel message encoding; the reader dispatches on it.
CODECS: dict[str, BlockCodec] = {codec.message_encoding: codec for codec in (JSON_CODEC, PROTOBUF_CODEC)}

_COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


# --- writer -----------------------------------------------------------------------------------------------------


def write_mcap(
    run: Run | UnitRuns,
    path: str | Path,
    *,
    block_samples: int = 1000,
    chunk_size: int = 1 << 20,
    compression: str = "zstd",
    summary: bool = True,
    encoding: str = "json",
) -> Path:
    """Write ``run`` (one unit's, or a :class:`UnitRuns` of several) as an MCAP file (docs/log-format.md); return
    the path.

    ``block_samples``: samples per message (at most; ``/fixture`` has one event per message). ``chunk_size``: bytes
    of uncompressed messages per chunk. ``compression``: ``zstd``, ``lz4`` or ``none``. ``summary=False`` writes no
    summary section or indexes (as a logger that was not closed cleanly would). ``encoding`` picks the codec.
    The file is written beside ``path`` under a temporary name and renamed when complete.
    """
    path = Path(path)
    if int(block_samples) < 1:
        raise RunFormatError(f"block_samples must be >= 1, got {block_samples}", path=str(path))
    codec = CODECS.get(encoding)
    if codec is None:
        raise RunFormatError(f"unknown message encoding {encoding!r} (known: {', '.join(CODECS)})", path=str(path))
    if compression not in _COMPRESSIONS:
        raise RunFormatError(f"unknown compression {compression!r} (known: {', '.join(_COMPRESSIONS)})", path=str(path))
    if isinstance(run, UnitRuns):
        shared, per_unit = writable_units(run, path=str(path))
        channels = [(TOPICS[s], s, df) for s, df in shared.items()]
        channels += [(unit_topic(u, s), s, df) for u, streams in per_unit.items() for s, df in streams.items()]
        meta = run.meta_values
    else:
        channels = [(TOPICS[s], s, df) for s, df in writable_streams(run, path=str(path)).items()]
        meta = run.meta.to_strings()
    options: dict[str, Any] = (
        {}
        if summary
        else dict(
            repeat_schemas=False,
            repeat_channels=False,
            use_statistics=False,
            use_summary_offsets=False,
            index_types=IndexType.NONE,
        )
    )

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        with open(tmp, "xb") as f:
            writer = Writer(f, chunk_size=chunk_size, compression=_COMPRESSIONS[compression], **options)
            writer.start(profile="", library=f"thermocal {pipeline.__version__}")
            try:
                _write_records(writer, codec, meta, channels, int(block_samples))
            finally:
                writer.finish()
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _write_records(
    writer: Writer,
    codec: BlockCodec,
    meta: dict[str, str],
    channels: list[tuple[str, str, pl.DataFrame]],
    block_samples: int,
) -> None:
    """``channels``: (topic, stream, table) of every channel, in the order they are registered."""
    schema_ids: dict[str, int] = {}
    channel_ids = []
    for topic, stream, _ in channels:
        if stream not in schema_ids:
            schema_ids[stream] = writer.register_schema(
                SCHEMA_NAMES[stream], codec.schema_encoding, codec.schema_data(stream)
            )
        channel_ids.append(writer.register_channel(topic, codec.message_encoding, schema_ids[stream]))
    # The metadata goes out before the first chunk, so a truncated file still has it.
    writer.add_metadata(RUN_METADATA_NAME, meta)

    arrays = [{c: df[c].to_numpy() for c in df.columns} for _, _, df in channels]
    for k, start, stop in _blocks_in_time_order([(s, df) for _, s, df in channels], block_samples):
        stream = channels[k][1]
        block = {c: a[start:stop] for c, a in arrays[k].items()}
        log_time_ns = int(block["t_ns"][0])
        sequence = start // (1 if stream == "fixture" else block_samples)
        writer.add_message(channel_ids[k], log_time_ns, codec.encode(stream, block), log_time_ns, sequence & 0xFFFFFFFF)


def _blocks_in_time_order(channels: list[tuple[str, pl.DataFrame]], block_samples: int) -> list[tuple[int, int, int]]:
    """(channel index, start row, stop row) of every message of the (stream, table) ``channels``, ordered by
    first-sample time (ties: channel order)."""
    t0, rank, starts, stops = [], [], [], []
    for k, (stream, df) in enumerate(channels):
        size = 1 if stream == "fixture" else block_samples
        s = np.arange(0, df.height, size)
        t0.append(df["t_ns"].to_numpy()[s])
        rank.append(np.full(len(s), k))
        starts.append(s)
        stops.append(np.minimum(s + size, df.height))
    t0_a, rank_a, starts_a, stops_a = (np.concatenate(x) for x in (t0, rank, starts, stops))
    order = np.lexsort((starts_a, rank_a, t0_a))
    return [(int(rank_a[i]), int(starts_a[i]), int(stops_a[i])) for i in order]


# --- reader -----------------------------------------------------------------------------------------------------


def read_mcap(path: str | Path) -> Run:
    """Read a single-unit chamber run from an MCAP file (with or without summary and indexes); see the module doc.
    A run with several units is refused unless it holds one (:func:`read_mcap_units` reads every unit)."""
    return read_mcap_units(path).one()


def read_mcap_units(path: str | Path, only: set[str] | None = None) -> UnitRuns:
    """Read an MCAP run of one or several units as a :class:`UnitRuns` (a single-unit run: one unit,
    ``several`` False). ``only``: the serials wanted, of a run with several units (the other units' messages are
    not decoded)."""
    p = Path(path)
    name = str(p)
    if p.is_dir():
        raise RunFormatError("is a directory, not an MCAP file", path=name)
    with open_regular(p) as f:
        size = os.fstat(f.fileno()).st_size
        if size == 0:
            raise RunFormatError("empty file (0 bytes), not an MCAP run", path=name)
        try:
            buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError, MemoryError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc) or type(exc).__name__
            raise RunFormatError(
                f"cannot map the file ({human_bytes(size)}) for reading ({why}): more than the address space this "
                f"process may use ({human_bytes(memory_budget())})",
                path=name,
            ) from None
        with buf:
            return _McapRunReader(name, buf, f.fileno(), only).read()


class _Malformed(ValueError):
    pass


@dataclass
class _Channel:
    topic: str
    stream: str | None  # the run stream it feeds; None: not a run topic, its messages are skipped
    decode: Callable[[str, bytes | memoryview], dict[str, np.ndarray]] | None = None
    unit: str | None = None  # the unit whose own stream it is (run with several units); None: single or shared


class _McapRunReader:
    """One pass over one file: top-level walk (:meth:`_scan`), then the data records in file order."""

    def __init__(self, path: str, buf: mmap.mmap, fd: int, only: set[str] | None = None):
        self.path = path
        self.buf = buf
        self.fd = fd  # chunk data is read with pread into reused buffers, not through the map
        self.size = len(buf)
        self.schemas: dict[int, tuple[str, str, bytes]] = {}  # schema id -> (name, encoding, data)
        self.channels: dict[int, _Channel] = {}
        self.summary_has_channels = False
        self.chunk_channels: dict[int, set[int]] = {}  # chunk record offset -> channel ids, from the indexes
        self.data_records: list[tuple[int, int, int, int]] = []  # (opcode, offset, body start, body end)
        self.meta: dict[str, str] | None = None
        self.columns: dict[tuple[str | None, str], _StreamColumns] = {}  # (unit, stream) -> its decoded samples
        self.only = only  # units wanted (None: all)
        self.skipped: set[str] = set()  # topics whose messages were not decoded
        self.undefined_channel_messages = 0
        self.truncation = ""
        self.warnings: list[str] = []
        self.decoded_bytes = 0  # of samples decoded so far, against the cap
        self.decoded_cap = decoded_cap()

    def fail(self, message: str, *, stream: str | None = None, where: str | None = None) -> RunFormatError:
        return RunFormatError(message, path=self.path, stream=stream, where=where)

    def read(self) -> UnitRuns:
        self._check_magic()
        self._scan()
        chunks = [
            (pos, start, end) for op, pos, start, end in self.data_records if op == _CHUNK and not self._skippable(pos)
        ]
        wanted = {pos for pos, _, _ in chunks}
        opened = self._opened_chunks(chunks)
        try:
            for op, pos, start, end in self.data_records:
                if op == _CHUNK:
                    if pos in wanted:
                        self._chunk_records(*next(opened))
                    continue
                try:
                    self._message(self.buf, start, end, f"byte {pos}")
                except (struct.error, _Malformed):
                    raise self.fail("malformed message record", where=f"byte {pos}") from None
        finally:
            opened.close()  # stops the workers before the file is unmapped
        return self._assemble(len(chunks))

    def _check_magic(self) -> None:
        head = self.buf[:64]
        if head.startswith(b"version https://git-lfs"):
            raise self.fail("not an MCAP file but a Git LFS pointer to one (fetch it with `git lfs pull`)")
        if not head.startswith(MAGIC):
            if MAGIC.startswith(head):
                raise self.fail(f"file is truncated at byte {self.size}: it ends inside the MCAP magic")
            raise self.fail("not an MCAP file (it does not start with the MCAP magic bytes)")

    # -- top-level walk ------------------------------------------------------------------------------------------

    def _scan(self) -> None:
        buf, size = self.buf, self.size
        pos = len(MAGIC)
        in_summary = False
        last_chunk = -1
        while True:
            if pos + 9 > size:
                self._truncated(pos, None, 0, in_summary)
                return
            op, length = _RECORD_HEAD.unpack_from(buf, pos)
            start, end = pos + 9, pos + 9 + length
            if op == 0:  # not an MCAP record: zeros (a preallocated file never written to the end) or garbage
                self._zeros(pos, in_summary)
                return
            if end > size:
                self._truncated(pos, op, length, in_summary)
                return
            if op == _FOOTER:
                if buf[end : end + len(MAGIC)] != MAGIC:
                    what = "is truncated in" if size - end < len(MAGIC) else "does not end with"
                    self.warnings.append(f"the file {what} the closing MCAP magic (byte {end}); all data was read")
                return
            try:
                if op in (_CHUNK, _MESSAGE) and not in_summary:
                    self.data_records.append((op, pos, start, end))
                    if op == _CHUNK:
                        last_chunk = pos
                elif op == _SCHEMA:
                    self._schema(buf, start, end)
                elif op == _CHANNEL:
                    self._channel(buf, start, end, f"byte {pos}")
                    self.summary_has_channels |= in_summary
                elif op == _METADATA:
                    self._metadata(buf, start, end)
                elif op == _MESSAGE_INDEX and last_chunk >= 0 and not in_summary:
                    self.chunk_channels.setdefault(last_chunk, set()).add(_U16.unpack_from(buf, start)[0])
                elif op == _CHUNK_INDEX:
                    self._chunk_index(buf, start, end)
                elif op == _DATA_END:
                    in_summary = True
            except (struct.error, UnicodeDecodeError, _Malformed) as exc:
                detail = f": {exc}" if isinstance(exc, _Malformed) else ""
                raise self.fail(
                    f"malformed {_RECORD_NAMES.get(op, f'opcode {op:#x}')} record{detail}", where=f"byte {pos}"
                ) from None
            pos = end

    def _zeros(self, pos: int, in_summary: bool) -> None:
        """The walk met a record of opcode 0 at ``pos``: say how far the zeros go (up to 1 MiB is looked at) and end
        the file there, as a truncation."""
        probe = bytes(self.buf[pos : min(self.size, pos + (1 << 20))])
        nonzero = len(probe) - len(probe.lstrip(b"\0"))
        if nonzero == len(probe):
            extent = "zeros to its end" if pos + len(probe) == self.size else "zeros for at least 1 MiB"
        else:
            extent = f"{nonzero} zero bytes, then other bytes"
        what = (
            f"an opcode 0 record at byte {pos}, which MCAP does not have: the file holds {extent} "
            f"({human_bytes(self.size - pos)} from there; preallocated and never written, or overwritten)"
        )
        if in_summary:
            self.warnings.append(f"the summary section ends in {what}; all data was read")
        else:
            self.truncation = f"file is unreadable from byte {pos}: {what}"

    def _truncated(self, pos: int, op: int | None, length: int, in_summary: bool) -> None:
        if op is None:
            what = (
                "the file ends without a footer"
                if pos == self.size
                else f"the file ends inside the header of the record at byte {pos}"
            )
        else:
            kind = _RECORD_NAMES.get(op, f"opcode {op:#x}")
            what = f"the {kind} record at byte {pos} needs {length} bytes, only {self.size - pos - 9} remain"
            if op == _CHUNK and pos + 9 + 16 <= self.size:
                t_start, t_end = struct.unpack_from("<QQ", self.buf, pos + 9)
                what += f" (its messages: t_ns {t_start}..{t_end})"
        if in_summary:
            self.warnings.append(
                f"file is truncated at byte {self.size} in its summary section ({what}); all data was read"
            )
        else:
            self.truncation = f"file is truncated at byte {self.size}: {what}"

    # -- records ---------------------------------------------------------------------------------------------------

    def _schema(self, buf, start: int, end: int) -> None:
        (schema_id,) = _U16.unpack_from(buf, start)
        name, p = _string(buf, start + 2, end)
        encoding, p = _string(buf, p, end)
        (n,) = _U32.unpack_from(buf, p)
        if p + 4 + n > end:
            raise _Malformed("schema data runs past the record")
        self.schemas[schema_id] = (name, encoding, bytes(buf[p + 4 : p + 4 + n]))

    def _channel(self, buf, start: int, end: int, where: str) -> None:
        channel_id, schema_id = _CHANNEL_HEAD.unpack_from(buf, start)
        topic, p = _string(buf, start + 4, end)
        encoding, _ = _string(buf, p, end)
        unit, stream = parse_topic(topic)
        if stream is None or (unit is not None and self.only is not None and unit not in self.only):
            self.channels[channel_id] = _Channel(topic, None, unit=unit)
            return
        codec = CODECS.get(encoding)
        if codec is None:
            raise self.fail(
                f"unsupported message encoding {encoding!r} (supported: {', '.join(CODECS)})", stream=topic, where=where
            )
        schema = self.schemas.get(schema_id)
        if schema is not None and schema[0] != SCHEMA_NAMES[stream]:
            raise self.fail(
                f"channel has schema {schema[0]!r}, expected {SCHEMA_NAMES[stream]!r}", stream=topic, where=where
            )
        if schema is not None and codec.check_schema is not None:
            try:
                codec.check_schema(stream, schema[1], schema[2])
            except BlockMismatch as exc:
                raise self.fail(
                    f"{encoding} channel with an unreadable schema: {exc}", stream=topic, where=where
                ) from None
        self.channels[channel_id] = _Channel(topic, stream, codec.decode, unit)
        if (unit, stream) not in self.columns:
            self.columns[unit, stream] = _StreamColumns(stream)

    def _metadata(self, buf, start: int, end: int) -> None:
        name, p = _string(buf, start, end)
        if name != RUN_METADATA_NAME:
            return
        values = _string_map(buf, p, end)
        if self.meta is not None:  # which one describes the recording? neither is taken on trust
            differ = "that differ" if values != self.meta else "(identical)"
            raise self.fail(
                f"two 'run' metadata records {differ}: a run has exactly one", stream="metadata", where=f"byte {start}"
            )
        self.meta = values

    def _chunk_index(self, buf, start: int, end: int) -> None:
        (chunk_offset,) = _U64.unpack_from(buf, start + 16)
        (map_length,) = _U32.unpack_from(buf, start + 32)
        p = start + 36
        if p + map_length > end:
            raise _Malformed("message index offsets run past the record")
        ids = {_U16.unpack_from(buf, q)[0] for q in range(p, p + map_length, 10)}
        if ids:
            self.chunk_channels[chunk_offset] = ids

    def _skippable(self, pos: int) -> bool:
        """True for a chunk the summary and indexes show to hold only topics that are not part of a run."""
        ids = self.chunk_channels.get(pos)
        if not (self.summary_has_channels and ids):
            return False
        if all(i in self.channels and self.channels[i].stream is None for i in ids):
            self.skipped.update(self.channels[i].topic for i in ids if self.channels[i].unit is None)
            return True
        return False

    def _opened_chunks(self, chunks: list[tuple[int, int, int]]) -> Generator[tuple[memoryview, str], None, None]:
        """Decompressed, CRC-checked chunks in order; the next few are opened in worker threads meanwhile
        (pread, zstd and crc32 release the GIL, so this overlaps with decoding). Each chunk in flight has its own
        :class:`_ChunkBuffers`, handed on to a later chunk once the caller has decoded this one (decoding copies
        the samples out), so no memory is allocated per chunk."""
        with ThreadPoolExecutor(max_workers=_DECOMPRESS_THREADS) as pool:
            spare = [_ChunkBuffers() for _ in range(min(_CHUNKS_AHEAD, len(chunks)))]
            ahead: deque = deque(pool.submit(self._open_chunk, *c, spare.pop()) for c in chunks[:_CHUNKS_AHEAD])
            for k in range(len(chunks)):
                raw, where, buffers = ahead.popleft().result()
                yield raw, where
                if k + _CHUNKS_AHEAD < len(chunks):
                    ahead.append(pool.submit(self._open_chunk, *chunks[k + _CHUNKS_AHEAD], buffers))

    def _open_chunk(
        self, pos: int, start: int, end: int, buffers: _ChunkBuffers
    ) -> tuple[memoryview, str, _ChunkBuffers]:
        """The uncompressed records of the chunk record at ``pos`` (in ``buffers``), a description of where it is,
        and ``buffers``."""
        buf = self.buf
        try:
            t_start, t_end, raw_size, crc = _CHUNK_HEAD.unpack_from(buf, start)
            compression, p = _string(buf, start + 28, end)
            (data_length,) = _U64.unpack_from(buf, p)
            p += 8
            if p + data_length > end:
                raise _Malformed("chunk data runs past the record")
        except (struct.error, UnicodeDecodeError, _Malformed):
            raise self.fail("malformed chunk record", where=f"byte {pos}") from None
        where = f"chunk at byte {pos} (t_ns {t_start}..{t_end})"
        topics = self._chunk_topics(pos)
        self._check_chunk_size(compression, raw_size, data_length, where, topics)
        data = buffers.sized("data", data_length)
        if _read_at(self.fd, data, p) != data_length:
            raise self.fail("the file changed while it was read", where=where)
        raw = self._decompress(compression, data, raw_size, where, topics, buffers)
        if crc and zlib.crc32(raw) != crc:
            raise self.fail(
                f"corrupt chunk: CRC mismatch (stored {crc:#010x}, computed {zlib.crc32(raw):#010x})",
                stream=topics,
                where=where,
            )
        return raw, where, buffers

    def _check_chunk_size(self, compression: str, raw_size: int, data_length: int, where: str, topics) -> None:
        """A chunk's declared uncompressed size within what its compressed bytes can hold and the chunk limit
        (:mod:`pipeline.io.limits`): nothing is allocated from a size the file alone declares."""
        most = ratio_limit(compression or "none", data_length)
        if most is not None and raw_size > most:
            raise self.fail(
                f"corrupt chunk: it declares {human_bytes(raw_size)} uncompressed from {human_bytes(data_length)} of "
                f"{compression or 'uncompressed'} data, more than that format can expand to ({human_bytes(most)})",
                stream=topics,
                where=where,
            )
        if max(raw_size, data_length) > MAX_CHUNK_BYTES:
            raise self.fail(
                f"chunk of {human_bytes(max(raw_size, data_length))}: larger than this reader takes in one chunk "
                f"({human_bytes(MAX_CHUNK_BYTES)}; writers use 1-64 MB), not read",
                stream=topics,
                where=where,
            )

    def _chunk_topics(self, pos: int) -> str | None:
        """The topics the indexes list for the chunk at ``pos`` (None for a file without indexes)."""
        ids = self.chunk_channels.get(pos, ())
        return ", ".join(sorted({self.channels[i].topic for i in ids if i in self.channels})) or None

    def _chunk_records(self, raw: memoryview, where: str) -> None:
        """Decode the run messages among the records of one uncompressed chunk."""
        view = raw
        n = len(raw)
        q = 0
        try:
            while q < n:
                op, length = _RECORD_HEAD.unpack_from(raw, q)
                body, q_next = q + 9, q + 9 + length
                if q_next > n:
                    raise _Malformed(f"record at byte {q} of the chunk runs past its end")
                if op == _MESSAGE:
                    self._message(view, body, q_next, where)
                elif op == _CHANNEL:
                    self._channel(raw, body, q_next, where)
                elif op == _SCHEMA:
                    self._schema(raw, body, q_next)
                q = q_next
        except (struct.error, UnicodeDecodeError, _Malformed) as exc:
            detail = f": {exc}" if isinstance(exc, _Malformed) else ""
            raise self.fail(f"corrupt chunk: malformed records{detail}", where=where) from None

    def _decompress(
        self, compression: str, data: memoryview, raw_size: int, where: str, topics: str | None, buffers: _ChunkBuffers
    ) -> memoryview:
        try:
            if compression == "zstd":
                raw = buffers.sized("raw", raw_size)
                with buffers.zstd.stream_reader(data) as reader:
                    got = 0
                    while got < raw_size and (k := reader.readinto(raw[got:])):
                        got += k
                    if got == raw_size and reader.read(1):
                        raise self.fail(
                            f"corrupt chunk: more than the {raw_size} bytes the header says after decompression",
                            stream=topics,
                            where=where,
                        )
                raw = raw[:got]
            elif compression == "lz4":
                try:
                    import lz4.frame
                except ImportError:
                    raise self.fail(
                        "chunk is lz4-compressed and the lz4 package is not installed", where=where
                    ) from None
                decompressor = lz4.frame.LZ4FrameDecompressor()
                raw = memoryview(decompressor.decompress(bytes(data), max_length=raw_size))  # never more
                if not decompressor.eof and len(raw) == raw_size:
                    raise self.fail(
                        f"corrupt chunk: more than the {raw_size} bytes the header says after decompression",
                        stream=topics,
                        where=where,
                    )
            elif compression == "":
                raw = data
            else:
                raise self.fail(f"unsupported chunk compression {compression!r}", where=where)
        except RunFormatError:
            raise
        except Exception as exc:  # zstd / lz4 errors on corrupt data
            raise self.fail(
                f"corrupt chunk: cannot decompress {compression} data ({exc})", stream=topics, where=where
            ) from None
        if len(raw) != raw_size:
            raise self.fail(
                f"corrupt chunk: {len(raw)} bytes after decompression, the header says {raw_size}",
                stream=topics,
                where=where,
            )
        return raw

    def _message(self, buf, start: int, end: int, where: str) -> None:
        if end - start < _MESSAGE_HEAD.size:
            raise _Malformed("message record shorter than its header")
        channel_id, _, log_time, _ = _MESSAGE_HEAD.unpack_from(buf, start)
        if end - start > MAX_MESSAGE_BYTES:
            raise self.fail(
                f"message of {human_bytes(end - start)}: larger than this reader takes "
                f"({human_bytes(MAX_MESSAGE_BYTES)}; a block of samples is tens of kB), not read",
                where=f"t_ns={log_time} ({where})",
            )
        channel = self.channels.get(channel_id)
        if channel is None:
            self.undefined_channel_messages += 1
            return
        if channel.stream is None or channel.decode is None:
            if channel.unit is None:  # not a run topic (another unit's topic, when some units are wanted, is)
                self.skipped.add(channel.topic)
            return
        columns = self.columns[channel.unit, channel.stream]
        try:
            decoded = channel.decode(channel.stream, buf[start + _MESSAGE_HEAD.size : end])
        except BlockMismatch as exc:
            raise self.fail(
                f"message does not match schema {SCHEMA_NAMES[channel.stream]}: {exc}",
                stream=channel.topic,
                where=f"t_ns={log_time} (message {columns.messages} of the topic, {where})",
            ) from None
        self.decoded_bytes += sum(a.nbytes if a.dtype != object else 64 * a.size for a in decoded.values())
        if self.decoded_bytes > self.decoded_cap:
            raise self.fail(
                f"the decoded samples pass {human_bytes(self.decoded_cap)}, a quarter of the memory this process may "
                "use: the run is too large for this machine (split it into several files, or read it on a larger "
                "one)",
                stream=channel.topic,
                where=f"t_ns={log_time} ({where})",
            )
        columns.add(decoded)

    # -- result ----------------------------------------------------------------------------------------------------

    def _assemble(self, chunks_read: int) -> UnitRuns:
        frames = {stream: columns.frame() for (unit, stream), columns in self.columns.items() if unit is None}
        per_unit: dict[str, dict[str, pl.DataFrame]] = {}
        for (unit, stream), columns in self.columns.items():
            if unit is not None:
                per_unit.setdefault(unit, {})[stream] = columns.frame()
        several = bool(per_unit) or (self.meta is not None and UNITS_KEY in self.meta)
        if self.truncation:
            missing = ["'run' metadata"] if self.meta is None else []
            if not several:
                missing += [f"{TOPICS[s]} samples" for s in REQUIRED_STREAMS if s not in frames or not frames[s].height]
            voltmeters = [f["voltmeter"] for f in (frames, *per_unit.values()) if "voltmeter" in f]
            if missing or not any(v.height for v in voltmeters):
                missing = missing or ["voltmeter samples"]
                raise self.fail(f"{self.truncation}; no {' and no '.join(missing)} before that point")
            self.warnings.append(
                f"{self.truncation}; dropped that record and anything after it; kept "
                f"{chunks_read} complete chunk(s), voltmeter samples up to "
                f"t_ns={max(int(v['t_ns'].to_numpy().max()) for v in voltmeters if v.height)}"
            )
        if self.meta is None and not frames:
            topics = sorted({c.topic for c in self.channels.values()})
            found = f"topics in the file: {', '.join(topics)}" if topics else "the file has no channels"
            raise self.fail(
                f"no run topics or run metadata found: not a thermocal chamber run "
                f"(expected metadata 'run' and topics {', '.join(TOPICS.values())}; {found})"
            )
        if self.skipped:
            self.warnings.append(f"ignored topics that are not part of a run: {', '.join(sorted(self.skipped))}")
        if self.undefined_channel_messages:
            self.warnings.append(f"ignored {self.undefined_channel_messages} messages on undefined channels")
        if several:
            shared = {s: df for s, df in frames.items() if s not in PER_UNIT_STREAMS}
            stray = sorted(TOPICS[s] for s in frames if s in PER_UNIT_STREAMS)
            if stray:
                raise self.fail(
                    f"a run with several units has unit topics (/unit/<serial>/...), but the file also has "
                    f"{', '.join(stray)}: which unit they belong to is unknown",
                    stream=stray[0],
                )
            return assemble_units(
                self.meta,
                shared,
                per_unit,
                path=self.path,
                warnings=self.warnings,
                stream_label=unit_topic,
                only=self.only,
            )
        run = assemble_run(self.meta, frames, path=self.path, warnings=self.warnings)
        return UnitRuns({run.meta.unit_serial: run}, source=self.path, warnings=run.warnings)


class _ChunkBuffers:
    """The reused memory of one chunk in flight: its compressed data, its records, its zstd decompressor."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.raw = bytearray()
        self.zstd = zstandard.ZstdDecompressor()

    def sized(self, name: str, size: int) -> memoryview:
        """The first ``size`` bytes of buffer ``name`` (replaced by a larger one when too small)."""
        buf = getattr(self, name)
        if len(buf) < size:
            buf = bytearray(max(size, 2 * len(buf)))
            setattr(self, name, buf)
        return memoryview(buf)[:size]


def _read_at(fd: int, view: memoryview, offset: int) -> int:
    """Read ``len(view)`` bytes of the file at ``offset`` into ``view``; the number of bytes read."""
    got = 0
    while got < len(view):
        if hasattr(os, "preadv"):
            k = os.preadv(fd, [view[got:]], offset + got)
        else:  # no preadv (Windows)
            data = os.pread(fd, len(view) - got, offset + got)
            k = len(data)
            view[got : got + k] = data
        if k == 0:
            break
        got += k
    return got


class _StreamColumns:
    """The decoded samples of one stream, copied block by block into pieces (each becomes one chunk of the polars
    columns: the table is never copied whole). Pieces start at :data:`_FIRST_PIECE_SAMPLES` rows and double up to
    :data:`_PIECE_SAMPLES`."""

    def __init__(self, stream: str):
        self.stream = stream
        self.dtypes = {name: _NUMPY_DTYPES[dtype] for name, dtype in STREAM_COLUMNS[stream].items()}
        self.pieces: list[dict[str, np.ndarray]] = []
        self.current: dict[str, np.ndarray] = {}
        self.capacity = self.filled = self.messages = 0

    def add(self, block: dict[str, np.ndarray]) -> None:
        n = len(block["t_ns"])
        if self.filled + n > self.capacity:
            self._close_piece()
            self.capacity = max(n, min(_PIECE_SAMPLES, max(_FIRST_PIECE_SAMPLES, 2 * self.capacity)))
            self.current = {name: np.empty(self.capacity, dtype=dtype) for name, dtype in self.dtypes.items()}
        for name, values in block.items():
            self.current[name][self.filled : self.filled + n] = values
        self.filled += n
        self.messages += 1

    def _close_piece(self) -> None:
        if self.filled:
            self.pieces.append({name: a[: self.filled] for name, a in self.current.items()})
        self.current, self.filled = {}, 0

    def frame(self) -> pl.DataFrame:
        self._close_piece()
        columns = []
        for name, dtype in STREAM_COLUMNS[self.stream].items():
            series = [pl.Series(name, piece[name], dtype=dtype) for piece in self.pieces]
            columns.append(
                pl.concat(series, rechunk=False)
                if len(series) > 1
                else series[0]
                if series
                else pl.Series(name, [], dtype=dtype)
            )
        return pl.DataFrame(columns)


def _string(buf, p: int, end: int) -> tuple[str, int]:
    """A length-prefixed UTF-8 string at ``p``; returns it and the offset after it."""
    (n,) = _U32.unpack_from(buf, p)
    p += 4
    if p + n > end:
        raise _Malformed("string runs past the record")
    return bytes(buf[p : p + n]).decode("utf-8"), p + n


def _string_map(buf, p: int, end: int) -> dict[str, str]:
    """A length-prefixed map<string, string> at ``p``."""
    (n,) = _U32.unpack_from(buf, p)
    p += 4
    stop = p + n
    if stop > end:
        raise _Malformed("map runs past the record")
    out = {}
    while p < stop:
        key, p = _string(buf, p, stop)
        value, p = _string(buf, p, stop)
        out[key] = value
    return out
