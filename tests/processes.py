"""Process-tree helpers for the tests that kill a parent and check its workers went with it.

Linux only: they read /proc (no psutil in the environment). A process counts as gone once its
/proc entry is missing or it is a zombie (exited, waiting for its new parent to reap it).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

needs_proc = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads the process tree from /proc"
)


def _stat_fields(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return text[text.rindex(")") + 2 :].split()  # after "pid (comm) ": state, ppid, ...


def children(pid: int) -> set[int]:
    """Live processes whose parent is ``pid``."""
    out = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            fields = _stat_fields(int(entry.name))
            if fields is not None and fields[0] != "Z" and int(fields[1]) == pid:
                out.add(int(entry.name))
    return out


def pool_workers(pid: int) -> set[int]:
    """Children of ``pid`` that are multiprocessing workers (not its resource tracker)."""
    out = set()
    for child in children(pid):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
        except (FileNotFoundError, ProcessLookupError):
            continue
        if b"spawn_main" in cmd:
            out.add(child)
    return out


def alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    fields = _stat_fields(pid)
    return fields is not None and fields[0] != "Z"


def wait_until(condition, timeout: float, interval: float = 0.1) -> bool:
    """Poll ``condition()`` until it is true or ``timeout`` seconds pass; its last value."""
    deadline = time.monotonic() + timeout
    while not (ok := bool(condition())) and time.monotonic() < deadline:
        time.sleep(interval)
    return ok


def still_alive_after(pids: set[int], timeout: float) -> set[int]:
    """The ``pids`` still alive once every one has ended or ``timeout`` seconds passed."""
    wait_until(lambda: not any(alive(p) for p in pids), timeout)
    return {p for p in pids if alive(p)}
