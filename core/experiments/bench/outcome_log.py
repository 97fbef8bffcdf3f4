"""The append-only log of finished episodes (``outcomes.jsonl``): one JSON line per (policy, task),
flushed and fsynced, a torn last line repaired on open.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import TextIO

OUTCOMES_FILE = "outcomes.jsonl"


log = logging.getLogger(__name__)


class OutcomeLog:
    """Append-only JSONL of finished episodes; a torn last line (crash mid-write) is dropped."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def load(self) -> dict[tuple[str, str], dict]:
        """Finished episodes by (policy, task_id); later lines win."""
        out: dict[tuple[str, str], dict] = {}
        if not self.path.exists():
            return out
        with open(self.path, encoding="utf-8") as fh:
            for n, line in enumerate(fh, start=1):
                if not line.endswith("\n"):
                    log.warning("%s:%d: ignoring a torn last line", self.path, n)
                    break
                try:
                    rec = json.loads(line)
                    out[(rec["policy"], rec["task_id"])] = rec
                except (json.JSONDecodeError, KeyError, TypeError):
                    log.warning("%s:%d: ignoring an unreadable line", self.path, n)
        return out

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
