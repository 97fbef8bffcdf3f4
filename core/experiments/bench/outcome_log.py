"""The append-only log of finished episodes (``outcomes.jsonl``): one JSON line per (policy, task),
flushed and fsynced, a torn last line repaired on open.

A bench run reads it strictly (``load(strict=True)``): a line that is not a bench outcome (not a
JSON object with the fields bench writes) means the file is not this command's, and is refused
rather than skipped and appended to.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import TextIO

from knotlab.core.errors import KnotlabError
from knotlab.core.textinput import LineError, parse_json, quote, read_lines

OUTCOMES_FILE = "outcomes.jsonl"
# What every line bench writes holds (core.experiments.episode.EpisodeRecord.to_dict), by type.
OUTCOME_FIELDS: dict[str, type | tuple[type, ...]] = {
    "policy": str,
    "task_id": str,
    "success": bool,
    "failure_kind": (str, type(None)),
}


class BenchMismatchError(KnotlabError):
    """An output directory holds results made with different defining arguments, or files that
    are not a bench run's."""


def _outcome_problem(rec: object) -> str | None:
    """Why ``rec`` is not a bench outcome line (None when it is one)."""
    if not isinstance(rec, dict):
        return f"a JSON {type(rec).__name__}, not an object"
    for name, kind in OUTCOME_FIELDS.items():
        if name not in rec:
            return f"no {name!r} field"
        if not isinstance(rec[name], kind):
            return f"{name!r} is {quote(rec[name])}"
    return None


log = logging.getLogger(__name__)


class OutcomeLog:
    """Append-only JSONL of finished episodes; a torn last line (crash mid-write) is dropped."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def load(self, *, strict: bool = False) -> dict[tuple[str, str], dict]:
        """Finished episodes by (policy, task_id); later lines win.

        ``strict``: a line that is not a bench outcome raises BenchMismatchError naming it (and a
        torn last line must at least start like one) instead of being skipped with a warning.
        """
        out: dict[tuple[str, str], dict] = {}
        if not self.path.exists():
            return out
        # split on "\n" only, bounded, decoded line by line (core.textinput)
        for n, line, complete, problem in read_lines(self.path, raise_errors=False):
            if not complete:
                if strict and not line.startswith("{"):
                    self._refuse(n, "an unfinished line that is not a JSON object")
                log.warning("%s:%d: ignoring a torn last line", self.path, n)
                break
            try:
                if problem is not None:
                    raise LineError(self.path, n, problem)
                rec = parse_json(line, self.path, n)
            except LineError as exc:
                if strict:
                    self._refuse(n, exc.problem)
                log.warning("%s:%d: ignoring an unreadable line (%s)", self.path, n, exc.problem)
                continue
            wrong = _outcome_problem(rec) if strict else None
            if wrong is not None:
                self._refuse(n, wrong)
            try:
                out[(rec["policy"], rec["task_id"])] = rec
            except (KeyError, TypeError):
                log.warning("%s:%d: ignoring an unreadable line", self.path, n)
        return out

    def _refuse(self, n: int, problem: str) -> None:
        raise BenchMismatchError(
            f"{self.path}:{n}: not a knotlab bench outcome line ({problem}), so this is not a "
            "bench results folder to resume; use a new --out-dir"
        )

    def _repair_tail(self) -> None:
        """Cut a torn last line so the next append starts on a fresh line."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return
        with open(self.path, "rb+") as fh:
            data = fh.read()
            if data.endswith(b"\n"):
                return
            fh.truncate(data.rfind(b"\n") + 1)

    def open(self) -> TextIO:
        """A line-appending handle (repairs the tail first)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._repair_tail()
        return open(self.path, "a", encoding="utf-8")

    @staticmethod
    def append(fh: TextIO, record: dict) -> None:
        """Write one record as a line, flushed and fsynced (survives a crash right after)."""
        fh.write(json.dumps(record, allow_nan=True) + "\n")
        fh.flush()
        os.fsync(fh.fileno())
