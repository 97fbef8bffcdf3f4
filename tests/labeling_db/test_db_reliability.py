"""Labels survive concurrency and crashes: 8 labelling processes; a writer killed mid-write."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest

from knotlab.core.selection.labels import LabelledStep
from knotlab.labeling_db.store import open_store
from tests.db_fixtures import make_execution

# One plugin registration, so the session-scoped PostgreSQL server is started once.

N_PROCESSES = 8
EPISODES_PER_PROCESS = 25
STEPS_PER_EPISODE = 5  # 8 x 25 x 5 = 1,000 labels


def _labeller_process(url: str, worker: int, start: mp.synchronize.Event) -> None:
    """One expert: claim the next state, label 5 steps one transaction each, finish; 25 times."""
    store = open_store(url, auto_upgrade=False)
    cloud = np.random.default_rng(worker).normal(size=(8, 3))
    start.wait(60)
    for e in range(EPISODES_PER_PROCESS):
        ep = store.start_episode(f"expert-{worker}")
        assert ep is not None, "ran out of start states"
        for i in range(STEPS_PER_EPISODE):
            outcome = "knot" if i == STEPS_PER_EPISODE - 1 else "progressed"
            demo = f"w{worker}-e{e}-s{i}"
            store.add_label(ep.episode_id, LabelledStep(i, cloud, demo, outcome))
        store.finish_episode(ep.episode_id)
    store.close()


@pytest.mark.slow
def test_eight_processes_label_concurrently_without_losing_or_duplicating(db_url: str) -> None:
    n_states = N_PROCESSES * EPISODES_PER_PROCESS
    with open_store(db_url) as store:
        rng = np.random.default_rng(0)
        state_ids = store.add_start_states([rng.normal(size=(8, 3)) for _ in range(n_states)])
    ctx = mp.get_context("spawn")
    start = ctx.Event()
    procs = [
        ctx.Process(target=_labeller_process, args=(db_url, w, start)) for w in range(N_PROCESSES)
    ]
    for p in procs:
        p.start()
    start.set()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0] * N_PROCESSES
    expected = {
        f"w{w}-e{e}-s{i}"
        for w in range(N_PROCESSES)
        for e in range(EPISODES_PER_PROCESS)
        for i in range(STEPS_PER_EPISODE)
    }
    with open_store(db_url) as store:
        labels = store.labels()
        demos = [lab.chosen_demo for lab in labels]
        assert len(demos) == 1000 and set(demos) == expected  # each label exactly once
        executions = store.training_executions()
        assert len(executions) == n_states
        assert all(len(ex.steps) == STEPS_PER_EPISODE and ex.ended_in_knot for ex in executions)
        for ex in executions:  # every episode holds its own labeller's labels, in order
            worker = ex.labeller.removeprefix("expert-")
            assert all(s.chosen_demo.startswith(f"w{worker}-") for s in ex.steps)
            assert [s.chosen_demo.rsplit("-s", 1)[1] for s in ex.steps] == ["0", "1", "2", "3", "4"]
        episode_ids = {lab.episode_id for lab in labels}
        starts = [store.episode(e).start_state_id for e in episode_ids]
        assert sorted(starts) == sorted(state_ids)  # every state claimed by exactly one episode
        assert store.next_unlabelled_state() is None


def _killed_writer(url: str, committed: mp.synchronize.Event, mid_write: mp.synchronize.Event):
    """Commit 5 executions, then start one long import and stop inside it (to be SIGKILLed)."""
    store = open_store(url, auto_upgrade=False)
    for k in range(5):
        store.add_execution(make_execution(f"committed-{k}", seed=k))
    committed.set()
    big = [make_execution(f"doomed-{k}", n_steps=5, n_points=150, seed=k) for k in range(400)]

    def progress(done: int, total: int) -> None:
        if done >= 300:  # ~300 x 6 states x 1.8 kB written, uncommitted, into the WAL
            mid_write.set()
            time.sleep(120)

    store.add_executions(big, batch_size=50, on_progress=progress)


def test_a_writer_killed_mid_transaction_loses_nothing_committed(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_execution(make_execution("before", seed=99))
    ctx = mp.get_context("spawn")
    committed, mid_write = ctx.Event(), ctx.Event()
    proc = ctx.Process(target=_killed_writer, args=(db_url, committed, mid_write))
    proc.start()
    try:
        assert committed.wait(60) and mid_write.wait(60)
        wal = Path(db_url.removeprefix("sqlite:///") + "-wal")
        if db_url.startswith("sqlite"):
            assert wal.stat().st_size > 1_000_000  # uncommitted pages really reached the disk
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.join(30)
        if proc.is_alive():  # pragma: no cover - never leave the child behind
            proc.kill()
            proc.join()
    assert proc.exitcode == -signal.SIGKILL
    with open_store(db_url) as store:
        keys = [ex.execution_id for ex in store.training_executions(include_unfinished=True)]
        assert keys == ["before"] + [f"committed-{k}" for k in range(5)]
        stats = store.stats()
        assert stats["labels"] == 18 and stats["episodes"] == 6 and stats["dead_end_states"] == 6
        assert stats["rope_states"] == 6 * (3 + 1)  # no orphan states from the killed import
        store.add_execution(make_execution("after", seed=7))  # the lock was released
    if db_url.startswith("sqlite"):
        con = sqlite3.connect(db_url.removeprefix("sqlite:///"))
        assert con.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        con.close()


def _report_workers(queue: mp.Queue) -> None:
    """Runs in a spawned child: which of this module's workers it found, and its process id."""
    queue.put(([f.__name__ for f in (_labeller_process, _killed_writer)], os.getpid()))


def test_spawned_children_can_import_this_module() -> None:
    """Guard: the workers above are importable under spawn (they live at module level)."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    child = ctx.Process(target=_report_workers, args=(queue,))
    child.start()
    names, pid = queue.get(timeout=60)
    child.join(60)
    assert child.exitcode == 0
    assert names == ["_labeller_process", "_killed_writer"]
    assert pid == child.pid != os.getpid()  # computed in the child, not here
