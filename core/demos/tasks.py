"""Train / test start states: demo start ropes perturbed by tent displacements, then settled.

Every task has its own seed derived from (generation seed, split, task number) through a NumPy
SeedSequence, so train and test seeds are disjoint by construction and any single task can be
regenerated alone. Shape suffixes: k = rope nodes, t = tasks.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.arrays import points_n3
from knotlab.core.errors import CorruptFileError, InvalidInputError
from knotlab.core.hashing import ContentHash
from knotlab.core.npzfile import read_npz, write_npz
from knotlab.core.parallel import PerProcess
from knotlab.core.seeds import child_seed, derive_seed

if TYPE_CHECKING:  # the simulator imports pybullet: built in the workers only
    from knotlab.core.world.sim import RopeWorld

TASKSET_FORMAT = "knotlab-task-set"
TASKSET_VERSION = 1
SPLITS: tuple[str, ...] = ("train", "test")
MAX_SETTLE_RETRIES = 20
MIN_CLEARANCE = 0.022  # m between non-neighbouring nodes of a new start (rope diameter 0.02)


@dataclass(frozen=True, eq=False)
class RopeTask:
    """One start state: settled rope nodes, the demo start it perturbs, and its seed."""

    task_id: str
    start_nodes_k3: np.ndarray
    source_start: int
    seed: int

    def __post_init__(self) -> None:
        nodes = points_n3(f"task {self.task_id} start_nodes_k3", self.start_nodes_k3, 3, "nodes")
        object.__setattr__(self, "start_nodes_k3", nodes)


class TaskSet:
    """An ordered set of tasks of one split and perturbation level, with a content hash."""

    def __init__(self, tasks: Sequence[RopeTask], metadata: dict) -> None:
        tasks = tuple(tasks)
        if not tasks:
            raise InvalidInputError("a TaskSet needs at least one task")
        if metadata.get("split") not in SPLITS:
            raise InvalidInputError(f"metadata.split must be one of {SPLITS}")
        k = tasks[0].start_nodes_k3.shape[0]
        if any(t.start_nodes_k3.shape[0] != k for t in tasks):
            raise InvalidInputError("all tasks in a set must have the same number of rope nodes")
        ids = [t.task_id for t in tasks]
        if len(set(ids)) != len(ids):
            raise InvalidInputError("task ids must be unique")
        self.tasks = tasks
        self.metadata = dict(metadata)
        json.dumps(self.metadata)

    def __len__(self) -> int:
        return len(self.tasks)

    def __getitem__(self, i: int) -> RopeTask:
        return self.tasks[i]

    def __iter__(self) -> Iterator[RopeTask]:
        return iter(self.tasks)

    @property
    def task(self) -> str:
        """The task whose starts these are (sets made before tasks were named: overhand)."""
        return str(self.metadata.get("task", "overhand"))

    @property
    def split(self) -> str:
        """'train' or 'test'."""
        return str(self.metadata["split"])

    def seeds(self) -> np.ndarray:
        """Per-task seeds, in order."""
        return np.array([t.seed for t in self.tasks], dtype=np.int64)

    def _arrays(self) -> dict[str, np.ndarray]:
        return {
            "start_nodes_tk3": np.stack([t.start_nodes_k3 for t in self.tasks]),
            "source_start_t": np.array([t.source_start for t in self.tasks], dtype=np.int64),
            "seed_t": self.seeds(),
        }

    def content_hash(self) -> str:
        """SHA-256 (16 hex chars) of the tasks and metadata."""
        h = ContentHash()
        for name, arr in sorted(self._arrays().items()):
            h.text(name).array(arr)
        return h.json({"ids": [t.task_id for t in self.tasks], **self.metadata}).hexdigest()

    def save(self, path: str | Path) -> Path:
        """Write the set to one versioned, byte-deterministic .npz file."""
        header = {
            "format": TASKSET_FORMAT,
            "version": TASKSET_VERSION,
            "hash": self.content_hash(),
            "task_ids": [t.task_id for t in self.tasks],
            "metadata": self.metadata,
        }
        return write_npz(path, self._arrays(), header)

    @classmethod
    def load(cls, path: str | Path) -> TaskSet:
        """Read and validate a task-set file; errors name the file and what is wrong."""
        path = Path(path)
        arrays, header = read_npz(path, "task set")
        try:
            ts = _taskset_from_parts(arrays, header)
        except (CorruptFileError, InvalidInputError, KeyError, TypeError, ValueError) as exc:
            raise CorruptFileError(f"{path}: invalid task set: {exc}") from exc
        if header.get("hash") != ts.content_hash():
            raise CorruptFileError(f"{path}: content hash mismatch: the file was altered")
        return ts


def _taskset_from_parts(arrays: dict[str, np.ndarray], header: dict) -> TaskSet:
    if header.get("format") != TASKSET_FORMAT:
        raise CorruptFileError(f"not a task set (format {header.get('format')!r})")
    if header.get("version") != TASKSET_VERSION:
        raise CorruptFileError(
            f"task set version {header.get('version')} is not supported (expected "
            f"{TASKSET_VERSION}); regenerate it with `knotlab tasks generate`"
        )
    nodes = arrays["start_nodes_tk3"]
    if nodes.dtype != np.float64 or nodes.ndim != 3 or nodes.shape[2] != 3:
        raise CorruptFileError(f"start_nodes_tk3 has dtype {nodes.dtype} shape {nodes.shape}")
    ids = header["task_ids"]
    n = nodes.shape[0]
    if len(ids) != n or arrays["source_start_t"].shape != (n,) or arrays["seed_t"].shape != (n,):
        raise CorruptFileError("task ids, sources and seeds do not match the number of tasks")
    check_rope_scale(nodes)
    tasks = [
        RopeTask(str(ids[i]), nodes[i], int(arrays["source_start_t"][i]), int(arrays["seed_t"][i]))
        for i in range(n)
    ]
    return TaskSet(tasks, header["metadata"])


def check_rope_scale(start_nodes_tk3: np.ndarray) -> None:
    """Raise unless every start rope has the simulated rope's node count and arc length.

    The simulator resamples any rope it is given to ``RopeParams``; a task set made for another
    rope (or in other units) would silently become different tasks, so it is refused instead.
    """
    from knotlab.core.world.rope import rope_length
    from knotlab.core.world.sim import RopeParams

    params = RopeParams()
    k = params.n_links + 1
    if start_nodes_tk3.shape[1] != k:
        raise CorruptFileError(
            f"ropes have {start_nodes_tk3.shape[1]} nodes; the simulated rope has {k} "
            f"(RopeParams.n_links = {params.n_links})"
        )
    for t, nodes_k3 in enumerate(start_nodes_tk3):
        length = rope_length(nodes_k3)
        if not abs(length - params.length) <= params.length_tolerance * params.length:
            raise CorruptFileError(
                f"task {t}: rope arc length {length:.4g} m; the simulated rope is "
                f"{params.length:g} m (within {params.length_tolerance:.0%})"
            )


def task_seed(seed: int, split: str, index: int) -> int:
    """Seed of task ``index`` of ``split``: disjoint across splits by construction."""
    if split not in SPLITS:
        raise InvalidInputError(f"split must be one of {SPLITS}, got {split!r}")
    return child_seed(seed, SPLITS.index(split), index)


@dataclass(frozen=True)
class _TaskJob:
    task_id: str
    seed: int
    source_start: int
    source_nodes_k3: np.ndarray
    rho: float
    n_centres: int
    settle_seconds: float


def _new_world() -> RopeWorld:
    from knotlab.core.world.sim import RopeWorld

    return RopeWorld()


_WORLD = PerProcess(_new_world)  # one simulator per worker process, reused across jobs


def _retry_seed(seed: int, attempt: int) -> int:
    return derive_seed(seed, attempt)


def min_clearance(nodes_k3: np.ndarray, min_gap: int = 2) -> float:
    """Smallest xy distance between rope nodes at least ``min_gap`` apart along the rope."""
    xy = np.asarray(nodes_k3, dtype=float)[:, :2]
    d_kk = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    idx = np.arange(len(xy))
    far = np.abs(idx[:, None] - idx[None]) >= min_gap
    return float(d_kk[far].min()) if far.any() else float("inf")


def _make_task(job: _TaskJob) -> RopeTask:
    """Perturb, settle and check one start state; fresh perturbations of the original on retry.

    A draw is rejected if its xy path self-intersects (before or after settling) or two
    non-neighbouring nodes come closer than ``MIN_CLEARANCE`` (they would start in contact).
    Every retry perturbs the ORIGINAL demo start with a new seed: retries never accumulate.
    """
    from knotlab.core.world.rope import has_xy_self_intersection, perturb_rope, rope_length

    world = _WORLD.get()
    for attempt in range(MAX_SETTLE_RETRIES):
        sub_seed = job.seed if attempt == 0 else _retry_seed(job.seed, attempt)
        try:
            nodes = perturb_rope(
                job.source_nodes_k3, job.rho, n_centres=job.n_centres, seed=sub_seed
            )
        except InvalidInputError:
            continue  # every draw of this sub-seed crossed itself: try the next sub-seed
        if min_clearance(nodes) < MIN_CLEARANCE:
            continue
        world.reset(nodes)
        world.settle(job.settle_seconds)
        settled = world.rope_nodes()
        if (
            np.all(np.isfinite(settled))
            and abs(rope_length(settled) - rope_length(nodes)) < 0.02 * rope_length(nodes)
            and not has_xy_self_intersection(settled)
        ):
            return RopeTask(job.task_id, settled, job.source_start, job.seed)
    raise InvalidInputError(
        f"task {job.task_id}: no valid settled start after {MAX_SETTLE_RETRIES} perturbations"
    )


def generate_tasks(
    start_states: dict[int, np.ndarray],
    n_tasks: int,
    *,
    split: str,
    rho: float,
    seed: int,
    n_centres: int = 7,
    level: str = "main",
    settle_seconds: float = 1.0,
    workers: int | None = None,
    progress: bool = True,
    extra_metadata: dict | None = None,
    task: str = "overhand",
) -> TaskSet:
    """Make ``n_tasks`` start states by perturbing demo start states (tent model), settled."""
    from knotlab.core.parallel import map_processes

    if n_tasks < 1:
        raise InvalidInputError(f"n_tasks must be >= 1, got {n_tasks}")
    if not rho > 0:
        raise InvalidInputError(f"rho must be > 0 metres, got {rho}")
    if not start_states:
        raise InvalidInputError("no demo start states to perturb")
    starts = sorted(start_states)
    jobs = []
    for i in range(n_tasks):
        s = task_seed(seed, split, i)
        source = starts[int(np.random.default_rng(s).integers(len(starts)))]
        jobs.append(
            _TaskJob(
                f"{level}-{split}-{i:04d}",
                s,
                source,
                start_states[source],
                rho,
                n_centres,
                settle_seconds,
            )
        )
    tasks = map_processes(
        _make_task, jobs, workers=workers, desc=f"{split} tasks", progress=progress
    )
    meta = {
        "split": split,
        "level": level,
        "rho": float(rho),
        "n_centres": int(n_centres),
        "seed": int(seed),
        "settle_seconds": float(settle_seconds),
        # Absent means the overhand knot (sets made before tasks were named): same bytes.
        **({} if task == "overhand" else {"task": task}),
        **(extra_metadata or {}),
    }
    return TaskSet(tasks, meta)
