"""Canonical JSON of registry records (passport versions, approvals, head statements) and the hashes over it.

One encoding for everything that is hashed or signed: keys sorted, 2-space indent, ASCII, a final newline, no NaN or
infinity (docs/contract.md). A record's ``content_sha256`` and its ``signature`` cover the same bytes: the canonical
JSON of the record without those two fields (:func:`signed_body`).
"""

from __future__ import annotations

import hashlib
import json
import os
from typing import Any

from pipeline.jsonable import json_default

#: Fields of a record that are not part of what is hashed and signed.
SEAL_FIELDS = ("content_sha256", "signature")


def canonical_json(obj: Any) -> bytes:
    """The canonical bytes of a JSON document: sorted keys, indent 2, ASCII, a final newline, no NaN/inf.

    Floats are written with Python's shortest round-trip repr, so load -> canonical_json gives the same bytes.
    Raises ValueError (non-finite number) or TypeError (not JSON-able).
    """
    text = json.dumps(obj, sort_keys=True, indent=2, ensure_ascii=True, allow_nan=False, default=json_default)
    return (text + "\n").encode("ascii")


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def signed_body(record: dict) -> bytes:
    """The bytes a record's ``content_sha256`` hashes and its ``signature`` signs: its canonical JSON without
    the fields in :data:`SEAL_FIELDS`."""
    return canonical_json({k: v for k, v in record.items() if k not in SEAL_FIELDS})


def content_sha256(record: dict) -> str:
    """The self-hash stored in a record: sha256 of :func:`signed_body`."""
    return sha256_bytes(signed_body(record))
