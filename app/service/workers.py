"""The decision workers of `knotlab serve`: one Agent per process, requests answered whole.

Every worker process loads the library and model once (`ServiceConfig`), pins BLAS to one thread
and keeps its own registration caches and, for the policies that simulate, its own rope world. A
request is one job on one worker from start to end, so concurrent requests never share mutable
state; the results come back as plain records (`RankResult`, `ChooseResult`) that the HTTP layer
turns into JSON.
Shape suffixes: n = cloud points, k = rope nodes, a = demos.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from knotlab.core.agent import Agent, Candidate
from knotlab.core.arrays import cloud_digest, points_n3
from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.policies import policy_config
from knotlab.core.world.protocol import World

MIN_CLOUD_POINTS = 10  # registration needs a rope-shaped cloud, not a handful of points


@dataclass(frozen=True)
class ServiceConfig:
    """What every worker loads: the library, the model (None: nearest neighbour) and the task."""

    library_path: Path
    model_path: Path | None
    task: str
    top_k: int = 5


@dataclass(frozen=True)
class RankResult:
    """The ranked candidates of one cloud, and where and how fast they were computed."""

    candidates: tuple[Candidate, ...]
    elapsed_s: float
    worker_pid: int
    cloud_digest: str


@dataclass(frozen=True)
class ChooseResult:
    """A policy's choice for one state: the chosen candidate and the best few scores."""

    policy: str
    chosen: Candidate
    top_scores: tuple[tuple[str, float], ...]  # (demo key, score), best first
    search_s: float | None
    elapsed_s: float
    worker_pid: int
    cloud_digest: str


_agent: Agent | None = None
_agents: dict[str, Agent] = {}
_world: World | None = None


def load_agent(config: ServiceConfig) -> Agent:
    """The agent a worker decides with (also used in-process by the HTTP layer's checks)."""
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.selection.qmodel import QModel

    library = DemoLibrary.load(config.library_path)
    model = QModel.load(config.model_path) if config.model_path is not None else None
    policy = "greedy" if model is not None else "nn"
    return Agent(library, model, policy, task=config.task, top_k=config.top_k)


def init_worker(config: ServiceConfig) -> None:
    """Process initializer: one BLAS thread, the agent loaded and its kernels compiled."""
    global _agent
    from knotlab.core.parallel import single_thread_blas

    single_thread_blas()
    _agent = load_agent(config)
    cloud = _agent.library[0].pre_cloud_n3
    _agent.rank(cloud, 1)  # compile and warm the scan and transfer before the first request


def ready(delay_s: float) -> int:
    """A warm-up job: hold this worker briefly so the next one is started too; its pid."""
    time.sleep(delay_s)
    return os.getpid()


def _worker_agent(policy: str | None = None) -> Agent:
    if _agent is None:
        raise RuntimeError("worker used before init_worker")
    if policy is None:
        return _agent
    name = policy_config(policy).name  # one-line error for a name that is not a policy
    if name not in _agents:
        _agents[name] = _agent.with_policy(name)
    return _agents[name]


def _cloud(cloud: list) -> np.ndarray:
    return points_n3("cloud", np.asarray(cloud, dtype=float), MIN_CLOUD_POINTS)


def rank_job(cloud: list, top_k: int, transfer: bool) -> RankResult:
    """Rank the library's demos for one cloud."""
    t0 = time.perf_counter()
    agent = _worker_agent()
    cloud_n3 = _cloud(cloud)
    if top_k > len(agent.library):
        top_k = len(agent.library)
    ranked = agent.rank(cloud_n3, top_k, transfer=transfer)
    return RankResult(tuple(ranked), time.perf_counter() - t0, os.getpid(), cloud_digest(cloud_n3))


def choose_job(policy: str, cloud: list, rope_nodes: list | None, step_index: int) -> ChooseResult:
    """A policy's choice; the policies that simulate need the rope-state estimate."""
    t0 = time.perf_counter()
    agent = _worker_agent(policy)
    cloud_n3 = _cloud(cloud)
    world = None
    if agent.config.simulates:
        if rope_nodes is None:
            raise InvalidInputError(
                f"rope_nodes: policy {agent.name!r} simulates candidate executions, so it "
                "needs the rope-state estimate (K x 3 metres); nn and greedy need only the cloud"
            )
        world = _simulator(points_n3("rope_nodes", np.asarray(rope_nodes, dtype=float), 3))
    steps_left = agent.task.step_limit - step_index
    if steps_left < 1:
        raise InvalidInputError(
            f"step_index: {step_index} is past the task's step limit {agent.task.step_limit}"
        )
    decision = agent.choose(world, cloud_n3=cloud_n3, step_index=step_index)
    scores = np.asarray(decision.scores_a, dtype=float)
    order = np.argsort(-np.where(np.isfinite(scores), scores, -np.inf), kind="stable")[:10]
    chosen = _candidate(agent, cloud_n3, decision.action, scores)
    search = decision.info.get("search_s")
    return ChooseResult(
        agent.name,
        chosen,
        tuple((agent.library.keys[a], float(scores[a])) for a in order),
        None if search is None else float(search),
        time.perf_counter() - t0,
        os.getpid(),
        cloud_digest(cloud_n3),
    )


def _simulator(nodes_k3: np.ndarray) -> World:
    """This worker's rope world (made on first use), reset to the estimated rope state."""
    global _world
    from knotlab.core.world.sim import RopeWorld

    if _world is None:
        _world = RopeWorld()
    try:
        _world.reset(nodes_k3)
    except InvalidInputError as exc:
        raise InvalidInputError(f"rope_nodes: {exc}") from None
    return _world


def _candidate(agent: Agent, cloud_n3: np.ndarray, action: int, scores: np.ndarray) -> Candidate:
    """The chosen demo: the policy's own score (Q for greedy, a backed-up value for lookahead,
    a stage for the oracle, minus the cost for nn), and Q itself whenever there is a model."""
    scan = agent.scan(cloud_n3)
    plan = agent.transferer.plan(cloud_n3, int(action))
    q = None if agent.model is None else float(agent.scores(cloud_n3)[action])
    return Candidate(
        rank=1,
        demo_index=int(action),
        demo_key=agent.library.keys[action],
        score=float(scores[action]),
        q=q,
        nn_cost=float(np.asarray(scan.nn_cost_a)[action]),
        trajectory=plan.trajectory,
        failure=plan.failure,
    )
