"""Compact binary encoding of score arrays: little-endian raw buffers plus a shape.

Floats are stored as '<f8' and ids as '<i8', so files written on any machine read back
bit-exact (NaN payloads included) on any other.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np

FLOAT_DTYPE = np.dtype("<f8")
INT_DTYPE = np.dtype("<i8")


def encode_matrix(matrix: np.ndarray) -> bytes:
    """Raw little-endian float64 bytes of a 2-D matrix in C order."""
    return np.ascontiguousarray(matrix, dtype=FLOAT_DTYPE).tobytes()


def decode_matrix(data: bytes | memoryview, rows: int, cols: int) -> np.ndarray:
    """Read-only (rows, cols) float64 view of bytes written by `encode_matrix`."""
    expected = rows * cols * FLOAT_DTYPE.itemsize
    if len(data) != expected:
        raise ValueError(f"score blob has {len(data)} bytes, expected {expected}")
    return np.frombuffer(data, dtype=FLOAT_DTYPE).reshape(rows, cols)


def encode_ids(ids: np.ndarray) -> bytes:
    """Raw little-endian int64 bytes of a 1-D id array."""
    return np.ascontiguousarray(ids, dtype=INT_DTYPE).tobytes()


def decode_ids(data: bytes | memoryview) -> np.ndarray:
    """Read-only int64 array of bytes written by `encode_ids`."""
    if len(data) % INT_DTYPE.itemsize:
        raise ValueError(f"id blob has {len(data)} bytes, not a multiple of 8")
    return np.frombuffer(data, dtype=INT_DTYPE)


def encode_json(value: Any) -> str:
    """Canonical JSON text (sorted keys, no NaN)."""
    return json.dumps(value, sort_keys=True, allow_nan=False, separators=(",", ":"))


def decode_json(text: str | bytes) -> Any:
    """Parse JSON text stored by `encode_json`."""
    return json.loads(text)


def encode_refs(refs: Sequence[str]) -> str:
    """Instance references as a JSON array."""
    return json.dumps(list(refs), ensure_ascii=False, separators=(",", ":"))


def decode_refs(text: str | bytes) -> tuple[str, ...]:
    """Instance references written by `encode_refs`."""
    return tuple(json.loads(text))


def encode_digests(digests: Sequence[str]) -> bytes | None:
    """sha256 hex digests as 32 raw bytes each; None for none (unknown)."""
    return b"".join(bytes.fromhex(d) for d in digests) if digests else None


def decode_digests(data: bytes | memoryview | None) -> tuple[str, ...]:
    """Hex digests written by `encode_digests` (() for NULL)."""
    if data is None:
        return ()
    raw = bytes(data)
    if len(raw) % 32:
        raise ValueError(f"digest blob has {len(raw)} bytes, not a multiple of 32")
    return tuple(raw[i : i + 32].hex() for i in range(0, len(raw), 32))
