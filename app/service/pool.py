"""The process pool behind `knotlab serve`: N warm decision workers, each with its own Agent."""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import TypeVar

from knotlab.app.service.workers import ServiceConfig, init_worker, ready
from knotlab.core.lifeline import die_with_parent

R = TypeVar("R")


def _init(config: ServiceConfig, parent_pid: int) -> None:
    die_with_parent(parent_pid)
    init_worker(config)


class WorkerLostError(RuntimeError):
    """A worker process died during a request (the pool was restarted)."""


class DecisionPool:
    """``workers`` spawned processes; `run` answers one job on one of them."""

    def __init__(self, config: ServiceConfig, workers: int) -> None:
        self.config = config
        self.workers = workers
        self._executor = self._start()

    def _start(self) -> ProcessPoolExecutor:
        # spawn: the server's threads and event loop must not be forked into the workers
        return ProcessPoolExecutor(
            self.workers,
            mp_context=mp.get_context("spawn"),
            initializer=_init,
            initargs=(self.config, os.getpid()),
        )

    def warm(self) -> set[int]:
        """Start every worker and load its agent now, not in the first requests; their pids."""
        jobs = [self._executor.submit(ready, 0.5) for _ in range(self.workers)]
        return {job.result() for job in jobs}

    async def run(self, fn: Callable[..., R], *args: object) -> R:
        """``fn(*args)`` on a worker; a worker that died restarts the pool and raises."""
        try:
            return await asyncio.wrap_future(self._executor.submit(fn, *args))
        except BrokenProcessPool:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = self._start()
            raise WorkerLostError(
                "a decision worker stopped during the request; retry it"
            ) from None

    def close(self) -> None:
        """Stop the workers (queued requests are cancelled)."""
        self._executor.shutdown(wait=False, cancel_futures=True)
