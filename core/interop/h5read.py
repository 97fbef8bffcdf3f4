"""The input boundary for HDF5 files: open, list groups and read datasets with limits.

Every HDF5 reader of knotlab goes through here, so a bad file is refused the same way everywhere:
one `CorruptFileError` naming the file, the group and the key, with at most ~80 characters of a
bad value quoted. Shapes are checked from the dataset's metadata before anything is read, so a
huge or mis-shaped dataset costs nothing; numbers must be finite.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from knotlab.core.errors import CorruptFileError, InvalidInputError
from knotlab.core.textinput import MAX_JSON_DEPTH, json_depth_exceeds, quote

MAX_GROUPS = 100_000  # segments or labelled states in one file
MAX_ROWS = 1_000_000  # cloud points, waypoints or rope nodes in one dataset
MAX_TEXT_BYTES = 1_000_000  # a description, an action name or a JSON attribute


class H5File:
    """An open HDF5 file whose reads raise one clear error naming file, group and key."""

    def __init__(self, handle: Any, path: Path) -> None:
        self.handle = handle
        self.path = path

    def fail(self, where: str, problem: str) -> CorruptFileError:
        """The error for ``problem`` at ``where`` (a group, or group/key)."""
        return CorruptFileError(f"{self.path}: {where}: {problem}")

    def group_names(self) -> list[str]:
        """The file's top-level group names (datasets at the top level are refused)."""
        names = list(self.handle.keys())
        if len(names) > MAX_GROUPS:
            raise self.fail("/", f"{len(names)} groups, more than the limit {MAX_GROUPS}")
        for name in names:
            if not self.is_group(name):
                raise self.fail(name, "expected a group, found a dataset")
        return names

    def is_group(self, name: str) -> bool:
        """Whether ``name`` is a group of the file."""
        import h5py

        return isinstance(self.handle.get(name, getlink=False), h5py.Group)

    def has(self, group: str, key: str) -> bool:
        """Whether ``group`` holds ``key`` (a dataset or a sub-group path)."""
        return key in self.handle[group]

    def array(
        self, group: str, key: str, shape: tuple[int | None, ...], *, min_rows: int = 1
    ) -> np.ndarray:
        """Dataset ``group/key`` as finite float64 of ``shape`` (None: any length <= the limit)."""
        where = f"{group}/{key}"
        if key not in self.handle[group]:
            raise self.fail(where, "missing")
        dataset = self.handle[group][key]
        if not hasattr(dataset, "shape") or not hasattr(dataset, "dtype"):
            raise self.fail(where, "expected a dataset, found a group")
        got = tuple(int(n) for n in dataset.shape)
        wanted = "x".join("N" if n is None else str(n) for n in shape)
        if len(got) != len(shape) or any(
            n is not None and g != n for g, n in zip(got, shape, strict=False)
        ):
            raise self.fail(where, f"shape {got}, expected ({wanted})")
        if any(g > MAX_ROWS for g in got):
            raise self.fail(where, f"shape {got} exceeds the limit of {MAX_ROWS} rows")
        if got and got[0] < min_rows:
            raise self.fail(where, f"{got[0]} rows, need at least {min_rows}")
        if dataset.dtype.kind not in "fiub":
            raise self.fail(where, f"dtype {dataset.dtype}, expected numbers")
        values = np.asarray(dataset[()], dtype=np.float64)
        if not np.all(np.isfinite(values)):
            raise self.fail(where, "contains NaN or infinite values")
        return values

    def text(self, group: str, key: str, *, default: str | None = None) -> str:
        """Dataset ``group/key`` as a string (bytes decoded as UTF-8); ``default`` if absent."""
        where = f"{group}/{key}"
        if key not in self.handle[group]:
            if default is None:
                raise self.fail(where, "missing")
            return default
        dataset = self.handle[group][key]
        if not hasattr(dataset, "shape") or dataset.shape not in ((), (1,)):
            raise self.fail(where, "expected one string")
        if dataset.dtype.kind not in "SOU" or dataset.dtype.itemsize > MAX_TEXT_BYTES:
            raise self.fail(where, f"dtype {dataset.dtype}, expected a string")
        value = dataset[()] if dataset.shape == () else dataset[0]
        if isinstance(value, bytes):
            try:
                value = value.decode("utf-8")
            except UnicodeDecodeError:
                raise self.fail(where, "not UTF-8 text") from None
        if not isinstance(value, str) or len(value) > MAX_TEXT_BYTES:
            raise self.fail(where, f"expected a string, got {quote(value)}")
        return value

    def scalar(self, group: str, key: str) -> float:
        """Dataset ``group/key`` as one finite number."""
        values = self.array(group, key, (), min_rows=0)
        return float(values)

    def json_attr(self, where: str, name: str, default: Any = None) -> Any:
        """The JSON text attribute ``name`` of ``where`` ('/' for the file), decoded."""
        attrs = self.handle[where].attrs
        if name not in attrs:
            return default
        raw = attrs[name]
        text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
        if len(text) > MAX_TEXT_BYTES or json_depth_exceeds(text, MAX_JSON_DEPTH):
            raise self.fail(f"{where}@{name}", "attribute too long or too deeply nested")
        try:
            return json.loads(text)
        except ValueError:
            raise self.fail(f"{where}@{name}", f"not JSON: {quote(text)}") from None


@contextmanager
def open_h5(path: str | Path, what: str) -> Iterator[H5File]:
    """Open ``path`` for reading as ``what``; a missing or non-HDF5 file is one clear error."""
    import h5py

    p = Path(path)
    if not p.is_file():
        raise InvalidInputError(f"{p}: no such {what} file")
    try:
        handle = h5py.File(p, "r")
    except OSError as exc:
        raise CorruptFileError(f"{p}: not an HDF5 file ({quote(str(exc))})") from None
    try:
        yield H5File(handle, p)
    except (KeyError, OSError, RuntimeError) as exc:  # h5py's view of a damaged file
        raise CorruptFileError(f"{p}: unreadable HDF5 content ({quote(str(exc))})") from None
    finally:
        handle.close()
