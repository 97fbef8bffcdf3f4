"""Compact array codec for database columns: a small header (dtype, shape), then raw data.

Layout of a blob: ``b"KA"``, format version (1 byte), dtype code (1 byte: ``f`` float32,
``d`` float64), ndim (1 byte), ndim x uint32 shape, then ``prod(shape) * itemsize`` bytes.
Decoding checks every part, so a truncated or altered value is reported, never silently reshaped.
"""

from __future__ import annotations

import struct

import numpy as np

from knotlab.labeling_db.errors import CorruptDatabaseError, InvalidRecordError

_MAGIC = b"KA"
_VERSION = 1
_DTYPES: dict[bytes, np.dtype] = {b"f": np.dtype("<f4"), b"d": np.dtype("<f8")}
_CODES: dict[np.dtype, bytes] = {v: k for k, v in _DTYPES.items()}
_MAX_NDIM = 8


def encode_array(arr: np.ndarray, dtype: str = "float32", *, name: str = "array") -> bytes:
    """Encode a finite numeric array as header + raw bytes (float32 by default, or float64)."""
    target = np.dtype(dtype).newbyteorder("<")
    if target not in _CODES:
        raise InvalidRecordError(f"{name}: dtype must be float32 or float64, got {dtype!r}")
    try:
        a = np.asarray(arr, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidRecordError(f"{name}: not a numeric array ({exc})") from exc
    if a.ndim > _MAX_NDIM:
        raise InvalidRecordError(f"{name}: at most {_MAX_NDIM} dimensions, got {a.ndim}")
    if not np.all(np.isfinite(a)):
        raise InvalidRecordError(f"{name}: contains NaN or infinite values")
    out = a.astype(target)
    if not np.all(np.isfinite(out)):
        raise InvalidRecordError(f"{name}: values overflow {target.name}")
    header = _MAGIC + bytes([_VERSION]) + _CODES[target] + bytes([a.ndim])
    header += struct.pack(f"<{a.ndim}I", *a.shape)
    return header + np.ascontiguousarray(out).tobytes()


def decode_array(blob: bytes | memoryview | None, *, where: str) -> np.ndarray:
    """Decode a blob from :func:`encode_array` into float64; `where` names the row in errors."""
    if blob is None:
        raise CorruptDatabaseError(f"{where}: array value is missing (NULL)")
    data = bytes(blob)
    if len(data) < 5 or data[:2] != _MAGIC:
        raise CorruptDatabaseError(f"{where}: not an encoded array (bad magic bytes)")
    if data[2] != _VERSION:
        raise CorruptDatabaseError(f"{where}: array format version {data[2]} is not {_VERSION}")
    dtype = _DTYPES.get(data[3:4])
    if dtype is None:
        raise CorruptDatabaseError(f"{where}: unknown array dtype code {data[3:4]!r}")
    ndim = data[4]
    if ndim > _MAX_NDIM:
        raise CorruptDatabaseError(f"{where}: array has {ndim} dimensions (max {_MAX_NDIM})")
    start = 5 + 4 * ndim
    if len(data) < start:
        raise CorruptDatabaseError(f"{where}: array header is truncated")
    shape = struct.unpack(f"<{ndim}I", data[5:start])
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if len(data) - start != expected:
        raise CorruptDatabaseError(
            f"{where}: array of shape {shape} and dtype {dtype.name} needs {expected} bytes, "
            f"found {len(data) - start}"
        )
    arr = np.frombuffer(data, dtype=dtype, offset=start).reshape(shape).astype(float)
    if not np.all(np.isfinite(arr)):
        raise CorruptDatabaseError(f"{where}: array contains NaN or infinite values")
    return arr
