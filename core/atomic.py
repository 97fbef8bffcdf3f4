"""Output files: checked before any work starts, then written atomically.

Every knotlab writer goes through here so that bad input never costs a file: `check_output_file`
(or `check_output_dir`) refuses a path that could not be written before a long computation runs,
and `atomic_path` / `atomic_open` write a hidden temporary file in the same folder and
``os.replace`` it onto the target only when writing succeeded, so a crash or an error leaves the
old file (or nothing) and no stray temporary behind.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from knotlab.core.errors import OutputPathError


def _nearest_existing(path: Path) -> Path:
    """``path`` itself or its closest ancestor that exists."""
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return Path(".")


def _check_can_create_in(folder: Path, what: str) -> None:
    """Raise unless ``folder`` exists as a writable directory or could be created."""
    base = _nearest_existing(folder)
    if not base.is_dir():
        raise OutputPathError(f"{what}: {base} is a file, not a folder, so nothing can go under it")
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputPathError(f"{what}: folder {base} is not writable")


def check_output_file(
    path: str | Path, *, flag: str = "--out", suffixes: Sequence[str] = (".npz",)
) -> Path:
    """``path`` if a file can be written there (folder creatable, known suffix), else raise."""
    path = Path(path)
    what = f"{flag} {path}"
    expected = " or ".join(suffixes)
    if path.is_dir():
        raise OutputPathError(f"{what} is a folder; expected a {expected} file name")
    if suffixes and path.suffix.lower() not in suffixes:
        raise OutputPathError(f"{what}: expected a {expected} file name, got {path.name!r}")
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputPathError(f"{what} exists and is read-only; refusing to replace it")
    _check_can_create_in(path.parent, what)
    return path


def check_output_dir(path: str | Path, *, flag: str = "--out") -> Path:
    """``path`` if it is (or can be created as) a writable folder, else raise."""
    path = Path(path)
    what = f"{flag} {path}"
    if path.exists() and not path.is_dir():
        raise OutputPathError(f"{what} is a file; expected a folder")
    _check_can_create_in(path, what)
    return path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``, else it is removed.

    The temporary name keeps the suffix (matplotlib and NumPy choose the format from it) and is
    hidden and random, so concurrent writers of one target never share a temporary file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)  # atomic on one filesystem: readers see the old or the new file
    finally:
        tmp.unlink(missing_ok=True)


@contextmanager
def atomic_open(
    path: str | Path, mode: str = "w", *, encoding: str | None = "utf-8", newline: str | None = None
) -> Iterator[IO]:
    """``open`` for writing whose file appears at ``path`` complete, or not at all."""
    if "b" in mode:
        encoding = None
    with atomic_path(path) as tmp:
        # O_EXCL: never write through a file someone else put at the random name
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with open(fd, mode, encoding=encoding, newline=newline) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())  # the rename must not land before the bytes do
