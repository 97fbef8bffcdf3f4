"""Content hashes, written once: the 16-hex-character SHA-256 ids that files and results record.

Every file type feeds its own parts (arrays, JSON headers, text) in a fixed order into one
`ContentHash`, so each id is stable across runs, processes and machines (arrays are hashed as
contiguous bytes in the dtype given, JSON with sorted keys).
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

HASH_CHARS = 16


class ContentHash:
    """Incremental SHA-256 over typed parts; ``hexdigest()`` is the short id."""

    def __init__(self) -> None:
        self._h = hashlib.sha256()

    def text(self, value: str) -> ContentHash:
        """Add a string (UTF-8)."""
        self._h.update(value.encode())
        return self

    def array(self, arr: np.ndarray, dtype: str | None = None) -> ContentHash:
        """Add an array's bytes (C order; cast to ``dtype`` first when given)."""
        self._h.update(np.ascontiguousarray(arr, dtype=dtype).tobytes())
        return self

    def tagged_array(self, name: str, arr: np.ndarray) -> ContentHash:
        """Add an array with its name, dtype and shape (so a reshaped array hashes apart)."""
        a = np.ascontiguousarray(arr)
        return self.text(name).text(str(a.dtype.str)).text(str(a.shape)).array(a)

    def json(self, value: object) -> ContentHash:
        """Add a JSON-able value, keys sorted."""
        return self.text(json.dumps(value, sort_keys=True))

    def hexdigest(self) -> str:
        """The id: the first 16 hex characters of the SHA-256 digest."""
        return self._h.hexdigest()[:HASH_CHARS]
