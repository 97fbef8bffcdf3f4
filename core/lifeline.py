"""Worker processes that die with their parent, and pools that end their workers on the way out.

A pool worker blocked in a long job (an oracle search, a bench episode) does not notice that the
process that started it was killed: its job queue holds both ends of a pipe, so no EOF ever comes,
and it would run on as an orphan, holding a core. Two watches end it:

- Linux: ``prctl(PR_SET_PDEATHSIG, SIGTERM)`` makes the kernel send SIGTERM the moment the parent
  dies (SIGKILL included). The kernel ties this to the parent *thread* that started the worker;
  our pools live inside one generator that one thread consumes, so that thread outlives them.
- Everywhere on POSIX: a daemon thread polls ``os.getppid()``, which changes (to init or a
  subreaper) once the parent is gone, and exits the worker within ``PARENT_POLL_S``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time
from collections.abc import Iterable
from multiprocessing.process import BaseProcess

PARENT_POLL_S = 0.5
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
ORPHAN_EXIT_CODE = 128 + signal.SIGTERM  # what a worker ended by its parent's death exits with


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Have Linux send ``sig`` to this process when its parent dies; False where it cannot."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):  # no libc or no prctl (musl without it, a sandbox)
        return False


def watch_parent(parent_pid: int, interval: float = PARENT_POLL_S) -> threading.Thread | None:
    """Start a daemon thread that exits this process once ``parent_pid`` is no longer its parent."""
    if os.name != "posix":  # Windows never re-parents, so getppid() cannot tell
        return None

    def poll() -> None:
        while os.getppid() == parent_pid:
            threading.Event().wait(interval)
        os._exit(ORPHAN_EXIT_CODE)  # no cleanup: the parent that wanted the result is gone

    thread = threading.Thread(target=poll, name="knotlab-parent-watch", daemon=True)
    thread.start()
    return thread


def die_with_parent(parent_pid: int) -> None:
    """Make this (worker) process exit when ``parent_pid``, the process that started it, dies."""
    set_parent_death_signal()
    if os.getppid() != parent_pid:  # it died before the watch was set: nobody will signal us
        os._exit(ORPHAN_EXIT_CODE)
    watch_parent(parent_pid)


def end_processes(processes: Iterable[BaseProcess], grace_s: float = 5.0) -> None:
    """SIGTERM every live process, wait up to ``grace_s`` in all, then SIGKILL what is left."""
    alive = [p for p in processes if p.is_alive()]
    for p in alive:
        p.terminate()
    deadline = time.monotonic() + grace_s
    for p in alive:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(1.0)
