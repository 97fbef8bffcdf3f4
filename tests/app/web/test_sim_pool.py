"""The app's simulation pool: closing it while tries run lets the running try finish with its
frames, the queued ones end with SimPoolClosedError, and nothing is simulated after (no traceback
from a manager torn down under a running try); the app and its workers use one BLAS thread."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import pytest

from knotlab.app.web.sim_pool import SimPool, SimPoolClosedError
from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.parallel import BLAS_VARS
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.sim import RopeWorld
from tests.minilib import mini_library

pytestmark = pytest.mark.xdist_group("minilib")


@pytest.mark.slow
def test_closing_the_pool_lets_the_running_try_finish_and_ends_the_queued_ones(tmp_path):
    lib = mini_library(2)
    path = lib.save(tmp_path / "lib.npz")
    with RopeWorld() as world:
        world.reset(lib[0].pre_nodes_k3)
        snapshot = world.snapshot()
        cloud = LibraryFeaturizer(lib).observe(world)
    pool = SimPool(str(path), workers=1)  # one worker: the others wait
    n = 5  # the executor hands up to two waiting jobs to its workers' queue already: they run
    recorders = [FrameRecorder(1 / 30) for _ in range(n)]
    ended: list[object] = [None] * n

    def try_(k: int) -> None:
        try:
            ended[k] = pool.simulate(snapshot, cloud, 0, recorders[k])
        except Exception as exc:  # recorded, asserted below
            ended[k] = exc

    threads = [threading.Thread(target=try_, args=(k,)) for k in range(n)]
    try:
        threads[0].start()
        deadline = time.monotonic() + 60
        while len(recorders[0]) == 0:  # the first try is being simulated
            assert time.monotonic() < deadline, "the first try never started"
            time.sleep(0.01)
        for t in threads[1:]:
            t.start()
        time.sleep(0.3)  # queued behind it
    finally:
        pool.close()
    for t in threads:
        t.join(timeout=60)
    assert isinstance(ended[0], ActionOutcome), ended[0]
    assert len(recorders[0]) > 1
    for end in ended:  # a result or "stopping", never a half-torn-down queue's error
        assert isinstance(end, (ActionOutcome, SimPoolClosedError)), end
    assert sum(isinstance(end, SimPoolClosedError) for end in ended) >= 2
    assert all(r.finished for r in recorders)
    assert pool.closed
    with pytest.raises(SimPoolClosedError, match="stopping"):
        pool.simulate(snapshot, cloud, 0, FrameRecorder(1 / 30))


@pytest.mark.slow
def test_the_app_and_its_workers_use_one_blas_thread_without_the_command_line(project_root):
    """Tests and benches build the app without `knotlab`'s command line, which pins BLAS: the app
    pins it itself, else its tabs' concurrent LAPACK calls spin against each other."""
    env = {k: v for k, v in os.environ.items() if k not in BLAS_VARS}
    done = subprocess.run(
        [sys.executable, "-m", "tests.app.web.blas_probe"],
        cwd=project_root,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    threads = json.loads(done.stdout.strip().splitlines()[-1])
    assert threads["app"] and set(threads["app"]) == {1}, threads
    assert threads["worker"] and set(threads["worker"]) == {1}, threads
