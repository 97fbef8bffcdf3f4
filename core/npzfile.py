"""Byte-deterministic .npz files with a JSON header: same content -> same bytes.

Knotlab promises bit-identical regeneration of its shipped files, so the zip layout is ours: fixed
member timestamps, sorted members, deflate. Checked: `np.savez_compressed` is also
byte-deterministic on NumPy 2.4 with Python 3.11 (zipfile's ZipInfo defaults to 1980-01-01), but
it adds zip64 extra fields, so switching would rewrite the bytes of every shipped file, and the
older NumPy releases pyproject allows (>= 1.26) were not checked; the writer stays (40 lines).
Reading uses ``np.load`` (no pickles, ever).
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np

from knotlab.core.atomic import atomic_open
from knotlab.core.errors import CorruptFileError
from knotlab.core.textinput import LineError, parse_json

_FIXED_TIME = (1980, 1, 1, 0, 0, 0)
HEADER_KEY = "header_json"


def write_npz(path: str | Path, arrays: dict[str, np.ndarray], header: dict) -> Path:
    """Write ``arrays`` plus a JSON ``header`` atomically to ``path`` (deflate-compressed)."""
    path = Path(path)
    members = dict(sorted(arrays.items()))
    members[HEADER_KEY] = np.frombuffer(
        json.dumps(header, sort_keys=True).encode("utf-8"), dtype=np.uint8
    )
    # atomic: a crash or an error never leaves a half-written file (or a stray temporary) behind
    with atomic_open(path, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, arr in members.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=_FIXED_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue(), compresslevel=6)
    return path


def read_npz(path: str | Path, kind: str) -> tuple[dict[str, np.ndarray], dict]:
    """Read arrays and header written by :func:`write_npz`; errors name the file and problem."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{kind} file not found: {path}")
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; expected a {kind} file (.npz)")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: np.array(data[k]) for k in data.files}
    except Exception as exc:  # zipfile.BadZipFile, ValueError, EOFError, zlib.error, OSError ...
        raise CorruptFileError(
            f"{path}: cannot read {kind} file (truncated or not a knotlab file): {exc}"
        ) from exc
    if HEADER_KEY not in arrays:
        raise CorruptFileError(f"{path}: {kind} file has no header")
    try:  # bounded depth and integers, one line whatever the bytes (core.textinput)
        header = parse_json(arrays.pop(HEADER_KEY).tobytes(), path)
    except LineError as exc:
        raise CorruptFileError(f"{path}: {kind} header is not valid ({exc.problem})") from None
    if not isinstance(header, dict):
        raise CorruptFileError(f"{path}: {kind} header is not a JSON object")
    return arrays, header
