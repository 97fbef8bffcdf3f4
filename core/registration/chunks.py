"""Chunk scheduling: a library scan as independent batches of demos spread over worker threads.

`chunk_plan` cuts the demos into chunks that shrink toward the end; `run_chunks` runs each chunk
through `rpm.rpm_batch` (on a thread pool when there are several workers) and assembles the
`ScanResult`. A demo's results do not depend on its chunk, only the speed does.
Shape suffixes: a demos, b demos in a chunk, n demo points (padded), m scene points,
k TPS basis coefficients, c costs, 3 xyz.
"""

from __future__ import annotations

from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.registration.params import COST_NAMES, RegistrationParams
from knotlab.core.registration.results import ScanResult
from knotlab.core.registration.sides import CloudSide

if TYPE_CHECKING:
    from knotlab.core.registration.rpm import FirstIteration


@dataclass(frozen=True, eq=False)
class _ChunkOut:
    """What `rpm.rpm_batch` returns for one chunk of demos (b of them)."""

    e_f: np.ndarray  # (b, k, 3)
    e_g: np.ndarray  # (b, k_y, 3)
    costs_bc: np.ndarray
    corr_bnm: np.ndarray | None
    failed: dict[int, str]


def chunk_plan(n_items: int, chunk_size: int, n_workers: int) -> list[tuple[int, int]]:
    """[start, stop) ranges of at most chunk_size items that shrink toward the end.

    Guided scheduling: with several workers each chunk is at most 1 / (2 workers) of what is
    left, so the last chunks are small and the workers, taking chunks as they free up, finish
    close together (148 demos in chunks of 16 on 2 workers left one worker idle for up to 16
    demos). A chunk's results do not depend on the chunk it is in (tested), only speed does.
    """
    plan: list[tuple[int, int]] = []
    start = 0
    while start < n_items:
        left = n_items - start
        size = min(chunk_size, left if n_workers <= 1 else -(-left // (2 * n_workers)))
        plan.append((start, start + size))
        start += size
    return plan


def run_chunks(
    demo: CloudSide,
    scene: CloudSide,
    params: RegistrationParams,
    *,
    chunk_size: int,
    n_workers: int,
    keep_corr: bool,
    timings: dict[str, float] | None = None,
    pool: Executor | None = None,
    first: FirstIteration | None = None,
) -> ScanResult:
    """Registers the scene against every demo, in chunks (independent batches) over workers.

    `pool`: an executor with n_workers threads to reuse (LibraryRegistrar keeps one); without
    it a pool is started and stopped for this call (~0.7 ms). `first`: demos whose first
    iteration ran early (`first_iteration_batch`) resume from it.
    """
    # `rpm.register_sides` runs a pair through this function, so the batch driver is imported
    # here, when a scan runs, rather than with the module (they would import each other).
    from knotlab.core.registration.rpm import kernel_inputs, rpm_batch

    n_demos = len(demo)
    demo.cast(np.dtype(params.dtype))  # convert once, before any worker thread reads it
    inputs = kernel_inputs(scene, params)
    good = np.flatnonzero(demo.ok_a)
    chunks = [good[a:b] for a, b in chunk_plan(len(good), chunk_size, n_workers)]

    def work(idx: np.ndarray) -> _ChunkOut:
        # A demo whose fit overflows is detected below and reported; no warning spam for it.
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return rpm_batch(
                demo, idx, scene, params, keep_corr, timings, inputs=inputs, first=first
            )

    if n_workers > 1 and len(chunks) > 1:
        # The kernel releases the GIL, so threads share one copy of the library.
        if pool is not None:
            outs = list(pool.map(work, chunks))
        else:
            with ThreadPoolExecutor(n_workers) as own_pool:
                outs = list(own_pool.map(work, chunks))
    else:
        outs = [work(idx) for idx in chunks]
    n_max = demo.x_an3.shape[1]
    m = int(scene.n_a[0])
    costs = np.full((n_demos, len(COST_NAMES)), np.inf)
    e_f = np.zeros((n_demos, n_max + 4, 3))
    e_g = np.zeros((n_demos, m + 4, 3))
    corr = np.zeros((n_demos, n_max, m)) if keep_corr else None
    ok = demo.ok_a.copy()
    reason = list(demo.reason_a)
    with np.errstate(invalid="ignore"):
        for idx, out in zip(chunks, outs, strict=True):
            k = out.e_f.shape[1]
            costs[idx] = out.costs_bc
            e_f[idx, :k] = out.e_f
            e_g[idx] = out.e_g
            if corr is not None and out.corr_bnm is not None:
                corr[idx, : out.corr_bnm.shape[1]] = out.corr_bnm
            for b, why in out.failed.items():
                ok[idx[b]] = False
                reason[idx[b]] = why
    finite = np.all(np.isfinite(costs), axis=1) & np.all(np.isfinite(e_f), axis=(1, 2))
    finite &= np.all(np.isfinite(e_g), axis=(1, 2))
    for a in np.flatnonzero(ok & ~finite):
        ok[a] = False
        reason[a] = "registration produced non-finite values"
    costs[~ok] = np.inf
    return ScanResult(params, costs, ok, tuple(reason), e_f, e_g, corr, demo, scene)
