"""The one input boundary of knotlab's text readers: lines, JSON values, integers, times, quotes.

Every reader of a text file a user may hand over (labels JSONL and CSV, tries JSONL, a bench's
``outcomes.jsonl``, the JSON headers of ``.npz`` files) goes through here, so hostile input ends
in one line naming the file, the line and the problem (:class:`LineError`, exit code 2), never in
another exception:

- lines are split on ``b"\\n"`` only (``str.splitlines`` would also split a JSON string at a raw
  U+2028), numbered from 1, decoded as UTF-8 one at a time (a bad byte is reported on its own
  line), and at most :data:`MAX_LINE_BYTES` long, checked while reading (a 200 MB line is never
  held whole, nor echoed);
- JSON is checked for nesting depth (:data:`MAX_JSON_DEPTH`) before ``json.loads``; integers must
  fit in 64 bits; every error of ``json.loads`` (``JSONDecodeError``, ``RecursionError``,
  ``ValueError``, ``OverflowError``) becomes a :class:`LineError`;
- a value quoted in a message is cut to :data:`QUOTE_CHARS` characters (:func:`quote`).
"""

from __future__ import annotations

import json
import re
import reprlib
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from knotlab.core.errors import InvalidInputError

MAX_LINE_BYTES = 16 * 2**20  # a labels line with a 280 000-point cloud; shipped lines < 60 kB
MAX_JSON_DEPTH = 64  # a labels line nests 5 deep
QUOTE_CHARS = 80
INT_MIN, INT_MAX = -(2**63), 2**63 - 1  # SQLite's INTEGER, PostgreSQL's BIGINT


class LineError(InvalidInputError):
    """A line (or a whole small file, ``line=None``) that cannot be read: ``path:line: problem``."""

    def __init__(self, path: str | Path, line: int | None, problem: str) -> None:
        self.path, self.line, self.problem = str(path), line, problem
        super().__init__(f"{path}:{line}: {problem}" if line is not None else f"{path}: {problem}")


class Line(NamedTuple):
    """One line of a text file: its 1-based number, its text without the ``\\n``, whether it
    ended with one (only a file's last line may not: a torn or unterminated line), and why it
    cannot be used (None when it can; then ``text`` is what could be read of it)."""

    number: int
    text: str
    complete: bool
    problem: str | None = None


# ----------------------------------------------------------------------------- quoting

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = QUOTE_CHARS
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 6
_REPR.maxlevel = 3


def quote(value: object, limit: int = QUOTE_CHARS) -> str:
    """``repr(value)`` cut to about ``limit`` characters (never raises, never copies a huge
    value: a 200 MB string is quoted by its first characters and its length)."""
    try:
        if isinstance(value, str) and len(value) > limit:
            return f"{value[:limit]!r}... ({len(value)} characters)"
        if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
            return f"an integer of about {int(value.bit_length() * 0.30103) + 1} digits"
        text = _REPR.repr(value)
    except Exception:  # e.g. a repr that raises
        return f"<a {type(value).__name__}>"
    return text if len(text) <= limit + 5 else text[:limit] + "..."


# ----------------------------------------------------------------------------- lines


def read_lines(
    path: str | Path, *, max_bytes: int | None = None, raise_errors: bool = True
) -> Iterator[Line]:
    """The lines of a UTF-8 text file, split on ``b"\\n"`` only (OS errors pass through).

    A line over ``max_bytes`` (default :data:`MAX_LINE_BYTES`) or one that is not UTF-8 raises
    :class:`LineError` naming it; with ``raise_errors=False`` it is yielded with its ``problem``
    instead (an over-long line's text is empty: it is skipped, never held whole), and reading
    goes on.
    """
    max_bytes = MAX_LINE_BYTES if max_bytes is None else max_bytes
    with open(path, "rb") as fh:
        number = 0
        while True:
            raw = fh.readline(max_bytes + 1)
            if not raw:
                return
            number += 1
            complete = raw.endswith(b"\n")
            problem = None
            if complete:
                raw = raw[:-1]
            elif len(raw) > max_bytes:
                problem = f"line is longer than {max_bytes} bytes (not a knotlab line)"
                while raw and not complete:  # skip the rest of it, a bounded piece at a time
                    raw = fh.readline(max_bytes + 1)
                    complete = raw.endswith(b"\n")
                raw = b""
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                problem = f"not UTF-8 text (byte {exc.start + 1} of the line: {exc.reason})"
                text = raw.decode("utf-8", "replace")
            if problem is not None and raise_errors:
                raise LineError(path, number, problem)
            yield Line(number, text, complete, problem)


# ----------------------------------------------------------------------------- JSON

# A string, or an unterminated one up to the end (so no start is ever retried: linear time).
_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*(?:"|\\?\Z)', re.DOTALL)
_SURROGATE_ESCAPE = re.compile(r"\\u[dD][89a-fA-F]")
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")


def json_depth_exceeds(text: str, limit: int = MAX_JSON_DEPTH) -> bool:
    """Whether the JSON text nests arrays and objects more than ``limit`` deep (strings skipped;
    linear time, no recursion)."""
    if text.count("[") + text.count("{") <= limit:
        return False
    brackets = _NOT_BRACKET.sub("", _JSON_STRING.sub("", text)).encode("ascii")
    depth = 0
    chunk = 1 << 20
    for start in range(0, len(brackets), chunk):
        codes = np.frombuffer(brackets, dtype=np.uint8, count=min(chunk, len(brackets) - start),
                              offset=start)  # fmt: skip
        steps = np.where((codes == ord("[")) | (codes == ord("{")), 1, -1).astype(np.int64)
        running = depth + np.cumsum(steps)
        if int(running.max()) > limit:
            return True
        depth = int(running[-1])
    return False


class _IntOutOfRangeError(ValueError):
    def __init__(self, digits: str) -> None:
        super().__init__(digits)
        self.digits = digits


def _bounded_int(digits: str) -> int:
    if len(digits) > 20:
        raise _IntOutOfRangeError(digits)
    value = int(digits)
    if not INT_MIN <= value <= INT_MAX:
        raise _IntOutOfRangeError(digits)
    return value


def _int_problem(digits: str) -> str:
    return f"integer {quote(digits)} does not fit in 64 bits"


def parse_int(text: str, path: str | Path, line: int | None = None) -> int:
    """A decimal integer that fits in 64 bits, or :class:`LineError` quoting it."""
    stripped = text.strip()
    if not re.fullmatch(r"[+-]?[0-9]+", stripped):
        raise LineError(path, line, f"expected an integer, got {quote(text)}")
    try:
        return _bounded_int(stripped.lstrip("+"))
    except _IntOutOfRangeError:
        raise LineError(path, line, _int_problem(stripped)) from None


def whole_number(value: object, what: str) -> int:
    """A form field's whole number (a number or its text), or one line naming ``what`` is
    wrong: empty, not a number, or not whole (a GUI would otherwise round or truncate it)."""
    if value is None or (isinstance(value, str) and not value.strip()):
        raise InvalidInputError(f"type {what}")
    if isinstance(value, bool):
        raise InvalidInputError(f"{what} must be a whole number, got {quote(value)}")
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, str):
        stripped = value.strip()
        if re.fullmatch(r"[+-]?[0-9]+", stripped):
            try:
                return _bounded_int(stripped.lstrip("+"))
            except _IntOutOfRangeError:
                raise InvalidInputError(f"{what}: {_int_problem(stripped)}") from None
        raise InvalidInputError(f"{what} must be a whole number, got {quote(value)}")
    if isinstance(value, float | np.floating) and np.isfinite(value) and float(value).is_integer():
        return int(value)
    raise InvalidInputError(f"{what} must be a whole number, got {quote(value)}")


def parse_json(text: str | bytes, path: str | Path, line: int | None = None) -> Any:
    """``json.loads(text)`` behind the boundary: depth and integer size checked, and any error
    raised as :class:`LineError` naming ``path`` and ``line`` (never quoting more than a bit)."""
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as exc:
            problem = f"not UTF-8 text (byte {exc.start + 1}: {exc.reason})"
            raise LineError(path, line, problem) from None
    if len(text) > MAX_LINE_BYTES:
        raise LineError(path, line, f"JSON text is longer than {MAX_LINE_BYTES} characters")
    if json_depth_exceeds(text):
        raise LineError(path, line, f"JSON nests more than {MAX_JSON_DEPTH} levels deep")
    try:
        value = json.loads(text, parse_int=_bounded_int)
        if _SURROGATE_ESCAPE.search(text):  # "\\ud800" alone: a str that is not text
            json.dumps(value, ensure_ascii=False).encode("utf-8")
        return value
    except UnicodeEncodeError:
        problem = "a string holds an unpaired surrogate escape (\\ud800 to \\udfff), not text"
    except json.JSONDecodeError as exc:
        problem = f"not JSON ({exc.msg} at column {exc.colno})"
    except _IntOutOfRangeError as exc:
        problem = _int_problem(exc.digits)
    except RecursionError:
        problem = "JSON nests too deeply"
    except (ValueError, OverflowError, TypeError) as exc:
        problem = f"not JSON ({type(exc).__name__}: {quote(str(exc))})"
    raise LineError(path, line, problem)


def parse_time(value: object) -> datetime:
    """An ISO 8601 time with a UTC offset that exists in UTC, or InvalidInputError saying why."""
    want = "expected an ISO 8601 time with a UTC offset"
    if not isinstance(value, str) or len(value) > 64:
        raise InvalidInputError(f"{want}, got {quote(value)}")
    try:
        ts = datetime.fromisoformat(value)
    except ValueError as exc:
        raise InvalidInputError(f"{want}, got {quote(value)} ({exc})") from None
    if ts.tzinfo is None or ts.utcoffset() is None:
        raise InvalidInputError(f"{want}, got {quote(value)} (no UTC offset)")
    try:
        ts.astimezone(UTC)
    except (OverflowError, ValueError):
        raise InvalidInputError(
            f"time {quote(value)} is out of range (years 1 to 9999 in UTC)"
        ) from None
    return ts
