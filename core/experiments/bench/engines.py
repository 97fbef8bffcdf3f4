"""Where episodes run: local worker processes or Ray actors, each holding a warm `BenchWorker`
(a world and one Agent per policy) that it reuses for every job.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any, Literal, get_args

import numpy as np

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.execution.memo import OutcomeMemo
from knotlab.core.machine import numeric_kind
from knotlab.core.parallel import PerProcess
from knotlab.core.selection.qmodel import QModel
from knotlab.core.world.estimate import EstimatorKind
from knotlab.core.world.mismatch import NOMINAL, NOMINAL_SETTING, PhysicsParams, PhysicsSetting

if TYPE_CHECKING:  # the agent imports the simulator's records: only for the checker
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld


log = logging.getLogger(__name__)

Engine = Literal["local", "ray"]  # where episodes run: worker processes here, or Ray actors
ENGINES: tuple[Engine, ...] = get_args(Engine)
# Outcomes one task's policies may share: ~70 simulations a task on the main set (measured,
# bench/sharing.py), each a few hundred kB with its trajectory, so a task never evicts.
SHARED_MEMO_SIZE = 512
_MODEL_WORLDS = 8  # model worlds a worker keeps (each a PyBullet client)


@dataclass(frozen=True, eq=False)
class EpisodeJob:
    """One episode to run: a policy on a task."""

    policy: str
    task_index: int
    task_id: str
    start_nodes_k3: np.ndarray
    seed: int
    max_steps: int
    noise: float


@dataclass(frozen=True, eq=False)
class WorkerSpec:
    """What every worker needs to build its warm state (pickled once per worker)."""

    library: DemoLibrary
    model: QModel | None = None
    task: str | None = None  # None: the task the library records
    # The world that executes and the agent's model of it (core/world/mismatch.py and
    # estimate.py); the defaults are the nominal world, simulated in itself.
    world: PhysicsSetting = NOMINAL_SETTING
    agent_model: PhysicsSetting = NOMINAL_SETTING
    estimator: EstimatorKind = EstimatorKind.PERFECT


class BenchWorker:
    """A worker's warm state: a world and one agent per policy, all on one warm featurizer."""

    def __init__(self, spec: WorkerSpec) -> None:
        from knotlab.core.agent import Agent
        from knotlab.core.parallel import single_thread_blas
        from knotlab.core.world.sim import RopeWorld

        single_thread_blas()
        self.spec = spec
        self.world = RopeWorld()
        # Worlds by physics (the world that executes, and apart from them the agent's model
        # worlds), kept for the worker's life: the outcome memo keys a world by its identity.
        self._worlds: dict[PhysicsParams, RopeWorld] = {NOMINAL: self.world}
        self._model_worlds: dict[PhysicsParams, RopeWorld] = {}
        # The base agent (nearest neighbour) checks the library and model once and warms the
        # registrar; every policy's agent shares its caches.
        self.agent = Agent(spec.library, spec.model, "nn", task=spec.task)
        self._agents: dict[str, Agent] = {"nn": self.agent}
        self.node = _ray_node_id()

    def agent_for(self, name: str) -> Agent:
        """The agent of policy ``name``, built on first use."""
        if name not in self._agents:
            self._agents[name] = self.agent.with_policy(name)
        return self._agents[name]

    def run_group(self, jobs: Sequence[EpisodeJob]) -> list[dict]:
        """Run one task's episodes (one per policy) with one outcome memo shared between them.

        An execution one policy simulated is restored, not simulated, when another asks for it
        from the same state and cloud: the same episodes (bit-identical), less simulation. The
        memo lives for this task only.
        """
        memo = OutcomeMemo(size=SHARED_MEMO_SIZE)
        return [self.run(job, memo) for job in jobs]

    def run(self, job: EpisodeJob, memo: OutcomeMemo | None = None) -> dict:
        """Run one episode; never raises (an unexpected error is a failure of kind "error")."""
        from knotlab.core.experiments.episode import run_episode
        from knotlab.core.world.estimate import make_estimator
        from knotlab.core.world.sim import RopeWorld

        t0 = time.perf_counter()
        try:
            world, model_world, start = self._worlds_for(job)
            record = run_episode(
                self.agent_for(job.policy),
                world,
                start,
                task_id=job.task_id,
                seed=job.seed,
                max_steps=job.max_steps,
                observe_noise=job.noise,
                memo=memo,
                model_world=model_world,
                estimator=make_estimator(self.spec.estimator),
            )
            out = record.summary()
            if self.spec.world.per_task:
                out["world_scales"] = {
                    k: round(v, 6) for k, v in self.spec.world.scales_for(job.task_id).items()
                }
        except Exception as exc:  # a long benchmark must outlive one bad task
            log.error("%s on %s crashed: %s", job.policy, job.task_id, traceback.format_exc())
            out = _error_record(job, f"{type(exc).__name__}: {exc}")
            out["wall_s"] = round(time.perf_counter() - t0, 4)
            for w in [*self._worlds.values(), *self._model_worlds.values()]:
                with contextlib.suppress(Exception):  # the world may be broken: start afresh
                    w.close()
            self.world = RopeWorld()
            self._worlds, self._model_worlds = {NOMINAL: self.world}, {}
        # The CPU kind whose numbers this episode is, to the last bit: a folder resumed on
        # another kind can choose other demos at near-ties, and its results count each kind.
        out.update(
            task_index=job.task_index, seed=job.seed, pid=os.getpid(), numeric_kind=numeric_kind()
        )
        if self.node is not None:
            out["node"] = self.node  # which Ray node ran it: per-node throughput
        return out

    def _worlds_for(self, job: EpisodeJob) -> tuple[RopeWorld, RopeWorld | None, np.ndarray]:
        """The job's world, the agent's model world (None: the world itself) and its start rope
        (scaled in xy to the world's rope length where that differs from the task's)."""
        from knotlab.core.world.mismatch import measured_model
        from knotlab.core.world.rope import rope_length, scale_xy_to_length
        from knotlab.core.world.sim import RopeWorld

        spec = self.spec
        physics = spec.world.params_for(job.task_id)
        if physics not in self._worlds:
            self._worlds[physics] = RopeWorld(physics.rope, physics.gripper)
        world = self._worlds[physics]
        start = job.start_nodes_k3
        if physics.rope.length != NOMINAL.rope.length:
            ratio = physics.rope.length / NOMINAL.rope.length
            start = scale_xy_to_length(start, ratio * rope_length(start))
        seen = None
        if spec.agent_model.measures_radius:  # the camera's cloud of the world's rope at rest
            from knotlab.core.world.mismatch import at_rest
            from knotlab.core.world.observation import surface_cloud_of_nodes

            radius = physics.rope.radius
            seen = surface_cloud_of_nodes(at_rest(start, radius), radius)
        model = measured_model(spec.agent_model.params_for(job.task_id), start, seen)
        if physics == model and spec.estimator is EstimatorKind.PERFECT:
            return world, None, start
        if model not in self._model_worlds:
            if len(self._model_worlds) >= _MODEL_WORLDS:  # a combined setting: one per task
                oldest = next(iter(self._model_worlds))
                self._model_worlds.pop(oldest).close()
            self._model_worlds[model] = RopeWorld(model.rope, model.gripper)
        return world, self._model_worlds[model], start

    def close(self) -> None:
        """Release the simulators."""
        for w in [*self._worlds.values(), *self._model_worlds.values()]:
            w.close()


def _ray_node_id() -> str | None:
    """The Ray node this process runs on, when it is a Ray worker (else None)."""
    import sys

    ray = sys.modules.get("ray")  # imported only where Ray runs us: never import it here
    if ray is None or not ray.is_initialized():
        return None
    try:
        return str(ray.get_runtime_context().get_node_id())
    except Exception:  # an old or partial Ray: the node is only a label
        return None


# This process's warm state (pool worker or in-process); Ray actors hold a BenchWorker instead.
_WORKER: PerProcess[BenchWorker] = PerProcess(BenchWorker)


def _init_process(spec: WorkerSpec) -> None:
    _WORKER.reset()
    _WORKER.get(spec)


def _run_in_process(job: EpisodeJob) -> dict:
    return _WORKER.current().run(job)


def _run_group_in_process(jobs: list[EpisodeJob]) -> list[dict]:
    return _WORKER.current().run_group(jobs)


def group_by_task(jobs: Sequence[EpisodeJob]) -> list[list[EpisodeJob]]:
    """The jobs of each task together (task-major order kept): a shared-memo unit of work."""
    groups: dict[str, list[EpisodeJob]] = {}
    for job in jobs:
        groups.setdefault(job.task_id, []).append(job)
    return list(groups.values())


def _run_local(
    jobs: list[EpisodeJob],
    spec: WorkerSpec,
    workers: int | None,
    on_result: Callable[[dict], None],
    progress: bool,
    share: bool = False,
) -> None:
    """Jobs on local worker processes; with ``share``, a task's jobs on one worker together."""
    from knotlab.core.parallel import imap_processes

    if share:
        for _, results in imap_processes(
            _run_group_in_process,
            group_by_task(jobs),
            workers=workers,
            initializer=partial(_init_process, spec),
            desc="bench tasks (shared simulations)",
            progress=progress,
        ):
            for result in results:
                on_result(result)
        return
    for _, result in imap_processes(
        _run_in_process,
        jobs,
        workers=workers,
        initializer=partial(_init_process, spec),
        desc="bench episodes",
        progress=progress,
    ):
        on_result(result)


def _run_ray(
    jobs: list[EpisodeJob],
    spec: WorkerSpec,
    workers: int | None,
    on_result: Callable[[dict], None],
    progress: bool,
    address: str | None = None,
    share: bool = False,
) -> None:
    """Same jobs on Ray actors (one per worker, each holding a BenchWorker); one job at a time
    (with ``share``: one task's jobs at a time, see `BenchWorker.run_group`)."""
    try:
        import ray
    except ImportError as exc:
        raise InvalidInputError(
            "--engine ray needs the ray package: pip install 'ray[default]'"
        ) from exc
    from tqdm import tqdm

    started = False
    if not ray.is_initialized():
        blas = {v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
        kwargs: dict = {"runtime_env": {"env_vars": blas}, "include_dashboard": False}
        if address is None and workers is not None:
            kwargs["num_cpus"] = workers
        # No address: a private local instance ("local"), never an already running cluster
        # that ray.init would otherwise join (and refuse num_cpus for).
        ray.init(address=address or "local", **kwargs)
        started = True
    n_actors = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
    units = group_by_task(jobs) if share else [[job] for job in jobs]
    n_actors = max(1, min(n_actors, len(units)))
    actor_cls = ray.remote(num_cpus=1)(BenchWorker)
    spec_ref = ray.put(spec)
    actors = [actor_cls.remote(spec_ref) for _ in range(n_actors)]
    queue = list(reversed(units))
    pending: dict = {}

    def submit(actor: Any) -> None:  # a Ray actor handle
        if queue:
            unit = queue.pop()
            ref = actor.run_group.remote(unit) if share else actor.run.remote(unit[0])
            pending[ref] = (actor, unit)

    bar = tqdm(total=len(jobs), desc="bench episodes (ray)", disable=not progress)
    try:
        for actor in actors:
            submit(actor)
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            actor, unit = pending.pop(done[0])
            try:
                got = ray.get(done[0])
                results = got if share else [got]
            except ray.exceptions.RayError as exc:  # the actor died: record, replace, go on
                log.error("ray actor failed on %s/%s: %s", unit[0].policy, unit[0].task_id, exc)
                results = [_error_record(job, f"ray: {type(exc).__name__}: {exc}") for job in unit]
                actor = actor_cls.remote(spec_ref)
            for result in results:
                on_result(result)
            bar.update(len(results))
            submit(actor)
    finally:
        bar.close()
        for actor in actors:
            ray.kill(actor)  # type: ignore[arg-type]
        if started:
            ray.shutdown()


def _error_record(job: EpisodeJob, message: str) -> dict:
    from knotlab.core.experiments.episode import EpisodeOutcome

    row = EpisodeOutcome.errored(job.task_id, job.policy, message).to_dict()
    return {**row, "task_index": job.task_index, "seed": job.seed}
