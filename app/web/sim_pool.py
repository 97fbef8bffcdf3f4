"""Tries and search expansions simulated in worker processes (tries stream their frames back).

PyBullet keeps the GIL while it steps, so a try simulated on a server thread slows every other
tab's scan, drawing and websocket traffic. Worker processes (spawned, one simulator each) run
the tries instead; each frame is sent back through a queue as it is recorded, so the animation
starts at once. The episode's own world is then restored to the returned snapshot.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import CancelledError, Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.execution.expansion import ExpansionJob, ExpansionResult, expand
from knotlab.core.parallel import PerProcess
from knotlab.core.selection.qmodel import QModel
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.sim import SimSnapshot

if TYPE_CHECKING:
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

_DONE = "done"


class SimPoolClosedError(RuntimeError):
    """The app is stopping: the pool simulates nothing more (a try or search then running
    ends without a result)."""


def _build_tools(library_path: str) -> tuple[RopeWorld, Agent]:
    """A worker's simulator and nearest-neighbour agent on the app's library."""
    from knotlab.core.agent import Agent
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.world.sim import RopeWorld

    return RopeWorld(), Agent(DemoLibrary.load(library_path))


_TOOLS = PerProcess(_build_tools)  # per worker process: library path -> (world, agent)


@dataclass(frozen=True)
class _ModelSpec:
    """Which model's agent a worker needs: equal (and kept) while the library and model are."""

    library_path: str
    model_hash: str
    model: QModel = field(compare=False, hash=False)


def _build_model_agent(spec: _ModelSpec) -> Agent:
    return _TOOLS.get(spec.library_path)[1].with_model(spec.model)


_MODEL_AGENT = PerProcess(_build_model_agent)  # per worker: the agent of the last model


class _StreamingRecorder(FrameRecorder):
    """A recorder that also sends every frame to the app process."""

    def __init__(self, dt: float, out: Any) -> None:
        super().__init__(dt)
        self._out = out

    def add(self, t: float, nodes_k3: np.ndarray, grippers_g3: np.ndarray, closed_g) -> None:
        """Record the frame and send it on."""
        super().add(t, nodes_k3, grippers_g3, closed_g)
        self._out.put((float(t), self._nodes[-1], self._grippers[-1], self._closed[-1]))


def _init(library_path: str, parent_pid: int) -> None:
    from knotlab.core.lifeline import die_with_parent

    die_with_parent(parent_pid)  # a killed server leaves no simulator processes behind
    from knotlab.core.parallel import single_thread_blas

    single_thread_blas()  # numpy is loaded already: the environment alone would come too late
    _TOOLS.get(library_path)


def _try_job(
    library_path: str,
    snapshot: SimSnapshot,
    cloud_n3: np.ndarray,
    demo_index: int,
    frame_dt: float,
    frames_out: Any,
) -> ActionOutcome:
    world, agent = _TOOLS.get(library_path)
    try:
        world.restore(snapshot)
        recorder = _StreamingRecorder(frame_dt, frames_out)
        return agent.act(world, demo_index, cloud_n3=cloud_n3, frames=recorder)
    finally:
        frames_out.put(_DONE)


def _expand_job(library_path: str, model: QModel, job: ExpansionJob) -> ExpansionResult:
    world, _ = _TOOLS.get(library_path)
    agent = _MODEL_AGENT.get(_ModelSpec(library_path, model.content_hash(), model))
    return expand(world, agent.transferer, agent.featurizer, model, job)


class PoolRunner:
    """Runs a lookahead level's expansions at once on the pool (`ExpansionRunner`)."""

    speculates = True

    def __init__(self, pool: SimPool, on_result: Callable[[], None] | None = None) -> None:
        self.pool = pool
        self.on_result = on_result
        # id(job) -> (job, future); the job is kept so that its id is not reused meanwhile
        self._prefetched: dict[int, tuple[ExpansionJob, Any]] = {}
        self.prefetch_hits = 0  # expansions a level found started already

    def _submit(self, model: QModel, job: ExpansionJob) -> Future:
        return self.pool.submit(_expand_job, self.pool.library_path, model, job)

    def prefetch(self, model: QModel, jobs: Sequence[ExpansionJob]) -> None:
        """Queue expansions a later `run` will ask for; they start when a worker is free."""
        for job in jobs:
            if id(job) not in self._prefetched:
                self._prefetched[id(job)] = (job, self._submit(model, job))

    def drop_prefetched(self) -> None:
        """Cancel the prefetched expansions no level asked for (a knot ended the search)."""
        for _job, future in self._prefetched.values():
            future.cancel()
        self._prefetched.clear()

    def run(
        self, world, transferer, featurizer, model: QModel, jobs: Sequence[ExpansionJob]
    ) -> Iterator[ExpansionResult]:
        """Submit every job now (not when the first result is asked for: the search may value
        memo hits first), reusing prefetched ones; yield the results in the jobs' order."""
        futures = []
        for job in jobs:
            early = self._prefetched.pop(id(job), None)
            self.prefetch_hits += early is not None
            futures.append(early[1] if early is not None else self._submit(model, job))
        return self._in_order(futures)

    def _in_order(self, futures: list) -> Iterator[ExpansionResult]:
        try:
            for future in futures:
                result = self.pool.result(future)
                if self.on_result is not None:
                    self.on_result()
                yield result
        finally:  # the search stopped early (a knot): nobody wants the rest
            for future in futures:
                future.cancel()


class SimPool:
    """Worker processes that simulate tries for every tab of the app."""

    def __init__(self, library_path: str, workers: int = 2) -> None:
        ctx = mp.get_context("spawn")
        self.library_path = library_path
        self._manager = ctx.Manager()
        self._closed = threading.Event()
        self._pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=ctx,
            initializer=_init,
            initargs=(library_path, os.getpid()),
        )
        # Start the workers now (imports and simulator), not on the first Enter.
        for f in [self._pool.submit(os.getpid) for _ in range(workers)]:
            f.result(timeout=120)

    def simulate(
        self,
        snapshot: SimSnapshot,
        cloud_n3: np.ndarray,
        demo_index: int,
        recorder: FrameRecorder,
    ) -> ActionOutcome:
        """Run one try in a worker; ``recorder`` fills with its frames as they are simulated."""
        if self._closed.is_set():
            raise SimPoolClosedError("the app is stopping")
        try:
            frames_in = self._manager.Queue()
        except (EOFError, OSError) as exc:  # closed between the check and here
            raise SimPoolClosedError("the app is stopping") from exc
        future = self.submit(
            _try_job, self.library_path, snapshot, cloud_n3, demo_index, recorder.dt, frames_in
        )

        def pump() -> None:
            while True:
                try:
                    item = frames_in.get(timeout=0.5)
                except queue.Empty:
                    if future.done():
                        break
                    continue
                except (EOFError, OSError):  # the manager went away (server stopping)
                    break
                if item == _DONE:
                    break
                recorder.add(*item)
            recorder.finished = True

        pumper = threading.Thread(target=pump, name="try-frames", daemon=True)
        pumper.start()
        try:
            return self.result(future)
        finally:
            pumper.join(timeout=5)
            recorder.finished = True

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Queue ``fn(*args)`` on a worker; SimPoolClosedError once the pool is closing."""
        if self._closed.is_set():
            raise SimPoolClosedError("the app is stopping")
        try:
            return self._pool.submit(fn, *args)
        except RuntimeError as exc:  # "cannot schedule new futures after shutdown"
            raise SimPoolClosedError("the app is stopping") from exc

    def result(self, future: Future) -> Any:
        """``future``'s result; SimPoolClosedError when closing the pool cancelled it."""
        try:
            return future.result()
        except (CancelledError, BrokenProcessPool) as exc:
            if self._closed.is_set():
                raise SimPoolClosedError("the app is stopping") from exc
            raise

    @property
    def closed(self) -> bool:
        """Whether the pool is closing or closed."""
        return self._closed.is_set()

    def close(self) -> None:
        """Stop the workers: queued jobs are cancelled, running ones finish first (so a try
        under way still has its frame queue, and nothing fails half-way with a traceback)."""
        self._closed.set()
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._manager.shutdown()
