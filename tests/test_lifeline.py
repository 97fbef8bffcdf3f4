"""Pool workers never outlive the run: parent killed or terminated, consumer gone, job failed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from knotlab.core.lifeline import ORPHAN_EXIT_CODE, set_parent_death_signal
from knotlab.core.parallel import imap_processes, map_processes
from tests.processes import children, needs_proc, pool_workers, still_alive_after, wait_until

pytestmark = needs_proc

# A parent whose two workers each announce themselves with a pid file, then sleep in their job.
_SLEEPING_POOL = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    from knotlab.core.parallel import map_processes

    def nap(i):
        Path(sys.argv[1], f"{os.getpid()}.pid").write_text(str(i))
        time.sleep(120)
        return i

    if __name__ == "__main__":
        map_processes(nap, range(4), workers=2, progress=False)
    """
)


def _sleeping_pool(tmp_path: Path) -> tuple[subprocess.Popen, set[int]]:
    """Start the sleeping pool; its process and its children once both workers are in a job."""
    script = tmp_path / "pool.py"
    script.write_text(_SLEEPING_POOL)
    pids = tmp_path / "pids"
    pids.mkdir()
    proc = subprocess.Popen([sys.executable, str(script), str(pids)], stderr=subprocess.DEVNULL)
    try:
        assert wait_until(lambda: len(list(pids.iterdir())) >= 2, timeout=120), "no workers"
        workers = {int(p.stem) for p in pids.iterdir()}
        assert workers <= children(proc.pid)
    except BaseException:
        proc.kill()
        raise
    return proc, children(proc.pid)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_workers_busy_in_a_job_die_with_their_parent(tmp_path, sig):
    proc, kids = _sleeping_pool(tmp_path)
    os.kill(proc.pid, sig)
    assert proc.wait(10) == -sig
    assert still_alive_after(kids, timeout=10) == set()


def test_the_parent_watch_thread_alone_ends_an_orphan(tmp_path):
    # The grandchild sets no death signal, only the polling thread: the portable fallback.
    grandchild = (
        "import os, time; from knotlab.core.lifeline import watch_parent; "
        "watch_parent(os.getppid(), 0.1); print('ready', flush=True); time.sleep(120)"
    )
    child = (
        "import subprocess, sys, time; "
        f"p = subprocess.Popen([sys.executable, '-c', {grandchild!r}], stdout=subprocess.PIPE); "
        "p.stdout.readline(); print(p.pid, flush=True); time.sleep(120)"
    )
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True)
    try:
        orphan = int(proc.stdout.readline())
    finally:
        proc.kill()
        proc.wait(10)
    assert still_alive_after({orphan}, timeout=5) == set()


def test_a_worker_started_after_its_parent_died_exits_at_once():
    code = (
        "import os, sys; from knotlab.core.lifeline import die_with_parent; "
        "die_with_parent(os.getppid() + 1); sys.exit(0)"  # a parent pid that is not ours
    )
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == ORPHAN_EXIT_CODE


def test_the_death_signal_is_available_on_linux():
    assert set_parent_death_signal(0) is True  # signal 0 clears it again for this process


def _pid_after(delay: float) -> int:
    time.sleep(delay)
    return os.getpid()


def _fail_fast(delay: float) -> int:
    if delay == 0:
        raise ValueError("this job fails")
    time.sleep(delay)
    return os.getpid()


def test_a_consumer_that_stops_early_ends_the_workers_at_once():
    before = pool_workers(os.getpid())
    results = imap_processes(_pid_after, [0.0, 120.0, 120.0], workers=2, progress=False)
    _, first = next(results)
    workers = pool_workers(os.getpid()) - before
    assert first in workers
    t0 = time.monotonic()
    results.close()
    assert time.monotonic() - t0 < 15  # not the 120 s the running job would take
    assert still_alive_after(workers, timeout=5) == set()


def test_a_failed_job_ends_the_run_without_waiting_for_the_others():
    before = pool_workers(os.getpid())
    t0 = time.monotonic()
    with pytest.raises(ValueError, match="this job fails"):
        map_processes(_fail_fast, [120.0, 0.0, 120.0], workers=2, progress=False)
    assert time.monotonic() - t0 < 60  # spawning two workers, not the 120 s jobs
    assert pool_workers(os.getpid()) - before == set()


def test_sigterm_unwinds_as_an_exception_and_the_old_handler_comes_back():
    from knotlab.app.cli import Terminated, sigterm_unwinds

    before = signal.getsignal(signal.SIGTERM)
    unwound = []
    with pytest.raises(Terminated), sigterm_unwinds():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises before this ends
        finally:
            unwound.append(True)  # finally blocks run: files close, pools end
    assert unwound == [True]
    assert signal.getsignal(signal.SIGTERM) is before
