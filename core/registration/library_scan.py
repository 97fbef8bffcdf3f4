"""The library scan: one scene against every demo, with the demo side cached per library."""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import fields
from pathlib import Path
from typing import TypedDict, Unpack

import numpy as np

from knotlab.core.atomic import atomic_path
from knotlab.core.errors import InvalidInputError
from knotlab.core.registration.chunks import run_chunks
from knotlab.core.registration.params import CACHE_VERSION, SCAN, RegistrationParams, clean_cloud
from knotlab.core.registration.results import ScanResult
from knotlab.core.registration.rpm import (
    FirstIteration,
    can_start_early,
    first_iteration_batch,
    first_iteration_inputs,
)
from knotlab.core.registration.sides import CloudSide, demo_side, normalise_cloud, scene_side

# Demos per early first-iteration batch: the early worker checks between batches whether the
# scene basis is ready, so this bounds how long the scan waits for it (~0.3 ms at 150 points).
_EARLY_BATCH = 4


class _EarlyFirstIteration:
    """Runs demos' first iterations on one scan thread while the caller factorises the scene.

    The scene's TPS basis (~5 ms at 150 points, serial) is needed only from the first TPS fit
    on; before, the second core idled. Now one worker runs the first iteration's affinity,
    Sinkhorn and targets of demo after demo until `finish` is called, and the scan resumes
    those demos from there (bit-identical; which demos ran early varies, the results do not).
    """

    def __init__(
        self,
        pool: ThreadPoolExecutor,
        demo: CloudSide,
        y_m3: np.ndarray,
        params: RegistrationParams,
    ) -> None:
        dt = np.dtype(params.dtype)
        demo.cast(dt)  # convert once, before the worker thread reads it
        self.first = FirstIteration.allocate(len(demo), demo.x_an3.shape[1], len(y_m3), dt)
        self._stop = threading.Event()
        self._future = pool.submit(self._run, demo, y_m3, params)

    def _run(self, demo: CloudSide, y_m3: np.ndarray, params: RegistrationParams) -> None:
        inputs = first_iteration_inputs(y_m3, params)
        good = np.flatnonzero(demo.ok_a)
        for start in range(0, len(good), _EARLY_BATCH):
            if self._stop.is_set():
                return
            first_iteration_batch(
                demo, good[start : start + _EARLY_BATCH], inputs, params, self.first
            )

    def finish(self) -> FirstIteration:
        """Stop after the current batch and return what ran (raises what the worker raised)."""
        self._stop.set()
        self._future.result()
        return self.first


def library_digest(demo_clouds: Sequence[np.ndarray]) -> str:
    """sha1 over the demo clouds' float64 bytes and shapes (a cache key when none is given)."""
    digest = hashlib.sha1()
    for cloud in demo_clouds:
        arr = np.ascontiguousarray(np.asarray(cloud, dtype=float))
        digest.update(str(arr.shape).encode())
        digest.update(arr.tobytes())
    return digest.hexdigest()


def _params_key(params: RegistrationParams) -> str:
    """The settings the demo-side precomputation depends on."""
    return f"rot{params.rot_coef}_scale{params.scale_m}_cap{params.max_points}"


class LibraryRegistrar:
    """Scans scene clouds against demo libraries; demo-side factorisations cached by library key.

    The cache is per instance: an LRU dict in memory and, when `cache_dir` is given, one `.npz`
    per library under `cache_dir/.cache/`. A library is identified by the caller's key (the
    library's content hash) or, without one, by `library_digest` of the clouds.
    """

    def __init__(
        self,
        params: RegistrationParams = SCAN,
        *,
        cache_dir: str | os.PathLike[str] | None = None,
        max_cached: int = 4,
        chunk_size: int = 8,
        n_workers: int = 1,
    ) -> None:
        if chunk_size < 1 or n_workers < 1 or max_cached < 1:
            raise InvalidInputError("chunk_size, n_workers and max_cached must be >= 1")
        self.params = params
        self.cache_dir = None if cache_dir is None else Path(cache_dir) / ".cache"
        self.max_cached = max_cached
        self.chunk_size = chunk_size
        self.n_workers = n_workers
        self._cache: OrderedDict[str, CloudSide] = OrderedDict()
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid = 0
        self._pool_lock = threading.Lock()

    def _worker_pool(self) -> ThreadPoolExecutor | None:
        """This registrar's scan threads, started on first use and kept (None for 1 worker).

        Re-created in a forked child: the parent's threads do not exist there.
        """
        if self.n_workers <= 1:
            return None
        if self._pool is not None and self._pool_pid != os.getpid():
            # A forked child: the parent's threads are gone, and a lock another thread held at
            # the fork would stay held here for ever.
            self._pool, self._pool_lock = None, threading.Lock()
        with self._pool_lock:
            if self._pool is None or self._pool_pid != os.getpid():
                self._pool = ThreadPoolExecutor(self.n_workers, thread_name_prefix="knotlab-scan")
                self._pool_pid = os.getpid()
            return self._pool

    def close(self) -> None:
        """Stop the scan threads (they are started again if the registrar is used again)."""
        with self._pool_lock:
            if self._pool is not None and self._pool_pid == os.getpid():
                self._pool.shutdown(wait=True)
            self._pool = None

    def __getstate__(self) -> dict:
        # Threads and locks do not pickle; a copy in another process starts its own.
        state = self.__dict__.copy()
        state.update(_pool=None, _pool_pid=0, _pool_lock=None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._pool_lock = threading.Lock()

    def prepare(
        self,
        demo_clouds: Sequence[np.ndarray],
        key: str | None = None,
        params: RegistrationParams | None = None,
    ) -> CloudSide:
        """Demo-side precomputation (normalise, factorise, pad), from cache when possible."""
        params = params or self.params
        full_key = f"{key or library_digest(demo_clouds)}_{_params_key(params)}"
        if full_key in self._cache:
            self._cache.move_to_end(full_key)
            return self._cache[full_key]
        side = self._load(full_key, len(demo_clouds))
        if side is None:
            side = demo_side(demo_clouds, params)
            self._save(full_key, side)
        self._cache[full_key] = side
        while len(self._cache) > self.max_cached:
            self._cache.popitem(last=False)
        return side

    def scan(
        self,
        scene_cloud: np.ndarray,
        demo_clouds: Sequence[np.ndarray],
        key: str | None = None,
        *,
        params: RegistrationParams | None = None,
        keep_correspondence: bool = False,
        timings: dict[str, float] | None = None,
    ) -> ScanResult:
        """Register the scene against every demo (bad demos: ok False, cost +inf; never raises)."""
        params = params or self.params
        demo = self.prepare(demo_clouds, key, params)
        return self.scan_side(
            scene_cloud,
            demo,
            params=params,
            keep_correspondence=keep_correspondence,
            timings=timings,
        )

    def scan_side(
        self,
        scene_cloud: np.ndarray,
        demo: CloudSide,
        *,
        params: RegistrationParams | None = None,
        keep_correspondence: bool = False,
        timings: dict[str, float] | None = None,
    ) -> ScanResult:
        """Register the scene against every demo of a prepared demo side (see :meth:`scan`)."""
        params = params or self.params
        pool = self._worker_pool()
        first = None
        if pool is None or timings is not None or not can_start_early(params, keep_correspondence):
            scene = scene_side(scene_cloud, params)
        else:
            cloud = clean_cloud(scene_cloud, "scene cloud", params.max_points)
            early = _EarlyFirstIteration(pool, demo, normalise_cloud(cloud, params)[1], params)
            try:
                scene = scene_side(cloud, params, cleaned=True)
            finally:
                first = early.finish()
        return run_chunks(
            demo,
            scene,
            params,
            chunk_size=self.chunk_size,
            n_workers=self.n_workers,
            keep_corr=keep_correspondence,
            timings=timings,
            pool=pool,
            first=first,
        )

    def _path(self, full_key: str) -> Path | None:
        if self.cache_dir is None:
            return None
        safe = hashlib.sha1(full_key.encode()).hexdigest()
        return self.cache_dir / f"registration_v{CACHE_VERSION}_{safe}.npz"

    def _save(self, full_key: str, side: CloudSide) -> None:
        path = self._path(full_key)
        if path is None:
            return
        arrays = {f.name: getattr(side, f.name) for f in fields(side) if f.name != "_casts"}
        clouds = arrays.pop("clouds")
        reasons = arrays.pop("reason_a")
        with atomic_path(path) as tmp:  # atomic: a concurrent reader never sees half a file
            np.savez(
                tmp,
                key=np.array(full_key),
                reason_a=np.array(reasons, dtype=str),
                clouds_n=np.array([len(c) for c in clouds]),
                clouds=np.concatenate(clouds) if clouds else np.zeros((0, 3)),
                **arrays,
            )

    def _load(self, full_key: str, n_demos: int) -> CloudSide | None:
        path = self._path(full_key)
        if path is None or not path.exists():
            return None
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != full_key or len(data["n_a"]) != n_demos:
                return None
            names = [
                f.name for f in fields(CloudSide) if f.name not in ("clouds", "reason_a", "_casts")
            ]
            arrays = {name: data[name] for name in names}
            split = np.cumsum(data["clouds_n"])[:-1]
            clouds = tuple(np.split(data["clouds"], split))
            reasons = tuple(str(s) for s in data["reason_a"])
        return CloudSide(clouds=clouds, reason_a=reasons, **arrays)


class _ScanOptions(TypedDict, total=False):
    """The keyword arguments `scan_library` passes on to `LibraryRegistrar.scan`."""

    key: str | None
    keep_correspondence: bool
    timings: dict[str, float] | None


def scan_library(
    scene_cloud: np.ndarray,
    demo_clouds: Sequence[np.ndarray],
    params: RegistrationParams = SCAN,
    **kwargs: Unpack[_ScanOptions],
) -> ScanResult:
    """One-off scan without a cache (see LibraryRegistrar for repeated queries)."""
    return LibraryRegistrar(params).scan(scene_cloud, demo_clouds, **kwargs)
