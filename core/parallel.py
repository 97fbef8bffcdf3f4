"""Ordered, seeded work over local processes with a progress bar and one BLAS thread each.

We parallelise over processes (one simulator per worker), never inside BLAS: each worker pins
its BLAS/OpenMP pools to one thread so two workers on two cores do not oversubscribe them.

Workers never outlive the run: each dies with the parent process (`knotlab.core.lifeline`), and
a run that ends early (an error, Ctrl-C, SIGTERM turned into an exception by the command line, a
consumer that stops iterating) terminates its workers instead of waiting for their jobs.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Generic, TypedDict, TypeVar, Unpack

from tqdm import tqdm

from knotlab.core.lifeline import die_with_parent, end_processes

T = TypeVar("T")
R = TypeVar("R")
S = TypeVar("S")

# The environment variables that size BLAS / OpenMP thread pools.
BLAS_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def single_thread_blas() -> None:
    """Limit BLAS/OpenMP to one thread in this process (call before heavy numpy work)."""
    for var in BLAS_VARS:
        os.environ[var] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # env vars above still bind pools created after this point
        pass


def default_workers() -> int:
    """Worker processes to use by default: the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _init_worker(initializer: Callable[[], None] | None, parent_pid: int) -> None:
    die_with_parent(parent_pid)
    single_thread_blas()
    if initializer is not None:
        initializer()


def imap_processes(
    fn: Callable[[T], R],
    items: Iterable[T],
    *,
    workers: int | None = None,
    initializer: Callable[[], None] | None = None,
    desc: str | None = None,
    total: int | None = None,
    progress: bool = True,
) -> Iterator[tuple[int, R]]:
    """Yield (index, fn(item)) as items finish, over ``workers`` processes (1 = in-process)."""
    items = list(items)
    total = len(items) if total is None else total
    workers = default_workers() if workers is None else max(1, workers)
    bar = tqdm(total=total, desc=desc, disable=not progress, dynamic_ncols=True, leave=True)
    try:
        if workers == 1 or len(items) <= 1:
            if initializer is not None:
                initializer()
            for i, item in enumerate(items):
                result = fn(item)
                bar.update(1)
                yield i, result
            return
        ctx = mp.get_context("spawn")  # fork + pybullet/BLAS threads is unsafe
        pool = ProcessPoolExecutor(
            workers, mp_context=ctx, initializer=_init_worker, initargs=(initializer, os.getpid())
        )
        try:
            pending = {pool.submit(fn, item): i for i, item in enumerate(items)}
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = pending.pop(fut)
                    result = fut.result()
                    bar.update(1)
                    yield i, result
        except BaseException:  # nobody will read the remaining results: stop computing them
            _abandon(pool)
            raise
        pool.shutdown(wait=True)
    finally:
        bar.close()


def _abandon(pool: ProcessPoolExecutor) -> None:
    """Cancel the queued jobs and end the workers now (SIGTERM, then SIGKILL after a grace)."""
    # No public handle on the workers before Python 3.14 (terminate_workers); read the dict.
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    end_processes(processes)


class _PoolOptions(TypedDict, total=False):
    """The keyword arguments of :func:`imap_processes`, which :func:`map_processes` passes on."""

    workers: int | None
    initializer: Callable[[], None] | None
    desc: str | None
    total: int | None
    progress: bool


def map_processes(
    fn: Callable[[T], R], items: Iterable[T], **kwargs: Unpack[_PoolOptions]
) -> list[R]:
    """Like :func:`imap_processes` but returns results in input order."""
    items = list(items)
    out: list = [None] * len(items)
    for i, result in imap_processes(fn, items, **kwargs):
        out[i] = result
    return out


class PerProcess(Generic[S]):
    """One process's warm state (a simulator, a featurizer, ...), built on first use per key.

    Pool workers keep expensive objects between jobs; a module holds one ``PerProcess`` with the
    function that builds the state from a key (e.g. a library path), instead of an ad-hoc global
    dict. A different key replaces the state (closing the old one if it has ``close()``), so a
    worker never mixes two libraries.
    """

    def __init__(self, build: Callable[..., S]) -> None:
        self._build = build
        self._key: object = None
        self._state: S | None = None

    def get(self, key: object = None) -> S:
        """The state for ``key``, built now if this process has none for it."""
        if self._state is None or key != self._key:
            self.reset()
            self._state = self._build() if key is None else self._build(key)
            self._key = key
        return self._state

    def current(self) -> S:
        """The state built last (by a pool initializer, say); an error if there is none."""
        if self._state is None:
            raise RuntimeError("per-process state used before it was built")
        return self._state

    def reset(self) -> None:
        """Drop (and close) the current state."""
        state, self._state, self._key = self._state, None, None
        close = getattr(state, "close", None)
        if callable(close):
            close()
