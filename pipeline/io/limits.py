"""How much memory a run may make the readers take: nothing is allocated from a size a file declares beyond a limit
tied to the file's real size and to this machine's memory.

- A compressed block (an MCAP chunk, a Parquet page) may declare at most what its compressed bytes can hold
  (:data:`MAX_RATIO`: the largest expansion each codec's format allows) and at most :data:`MAX_CHUNK_BYTES`; a
  message at most :data:`MAX_MESSAGE_BYTES`.
- A run's decoded samples may take at most :func:`decoded_cap`: a quarter (:data:`DECODED_SHARE`) of
  :func:`memory_budget` (the machine's memory, or less where the process is limited: ``RLIMIT_AS``, ``RLIMIT_DATA``,
  the cgroup's ``memory.max``), since segmentation and the calibration work on copies of them. Beyond, the run is
  refused in one line before (Parquet: from its footer) or as soon as (MCAP: while decoding) the cap is passed.

Every refusal is one :class:`pipeline.errors.RunFormatError` line naming the file, the stream or byte, the size
declared and the limit.
"""

from __future__ import annotations

import os
import resource
from pathlib import Path

__all__ = [
    "DECODED_SHARE",
    "MAX_CHUNK_BYTES",
    "MAX_MESSAGE_BYTES",
    "MAX_RATIO",
    "decoded_cap",
    "human_bytes",
    "memory_budget",
    "ratio_limit",
]

#: The largest uncompressed MCAP chunk or Parquet page taken (writers use 1-64 MiB).
MAX_CHUNK_BYTES = 256 << 20
#: The largest MCAP message taken (a block of samples: thermocal writes ~80 kB).
MAX_MESSAGE_BYTES = 64 << 20
#: The largest expansion of each codec's format (uncompressed / compressed bytes): zstd's RLE blocks (3 + 1 bytes
#: for 128 KiB), lz4's and snappy's longest matches, deflate's 258-byte matches in 2 bits, brotli's window.
MAX_RATIO = {
    "": 1,
    "none": 1,
    "uncompressed": 1,
    "zstd": 32_768,
    "lz4": 255,
    "lz4_raw": 255,
    "snappy": 22,
    "gzip": 1_032,
    "brotli": 65_536,
}
#: A run's decoded samples may take this share of :func:`memory_budget` (1 / DECODED_SHARE).
DECODED_SHARE = 4


def ratio_limit(codec: str, compressed_bytes: int) -> int | None:
    """The most bytes ``compressed_bytes`` of ``codec`` data can decompress to (None: an unknown codec)."""
    ratio = MAX_RATIO.get(codec.lower())
    return None if ratio is None else ratio * max(int(compressed_bytes), 1)


def memory_budget() -> int:
    """Bytes this process may use: the machine's physical memory, or less where the process is limited (the soft
    ``RLIMIT_AS`` and ``RLIMIT_DATA``, the cgroup's ``memory.max``)."""
    candidates = []
    try:
        candidates.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        pass
    for which in (resource.RLIMIT_AS, getattr(resource, "RLIMIT_DATA", None)):
        if which is None:
            continue
        soft, _ = resource.getrlimit(which)
        if soft != resource.RLIM_INFINITY and soft > 0:
            candidates.append(soft)
    try:
        text = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if text.isdigit():
            candidates.append(int(text))
    except OSError:
        pass
    return min(candidates) if candidates else 8 << 30


def decoded_cap() -> int:
    """The most bytes a run's decoded samples may take (see the module doc)."""
    return memory_budget() // DECODED_SHARE


def human_bytes(n: float) -> str:
    """``3.2 GB``, ``837 bytes``."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} bytes"
