"""Labels where the policy goes: the oracle labels the states a learned policy reaches.

Learning Q only from the expert's own solved episodes leaves the states the learned policy
drifts into unlabelled (compounding error); DAgger's remedy is to roll the current policy out
and ask the expert in the states it visits. Here, for one training start:

1. roll out ``policy`` (greedy, with the current model) from the start, to the goal or the step
   limit, snapshotting the world before each step;
2. for every visited state after the start (the start itself is labelled by the oracle's own
   execution), run the oracle's bounded search from that state with the steps that remain:
   its steps become a labelled execution that begins there; a state from which no knot can be
   tied in time (search exhaustive) is a dead end.

Each execution records in its metadata what reached its first state (``reached_by``: policy,
model hash, round, step, start task and rope hash), so a round is reproducible and auditable,
and the labels files carry it. Execution ids: ``policy-<policy>-r<round>-<task>-t<step>``.
Shape suffixes: k = rope nodes.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.experiments.labeller import OracleParams, oracle_from, start_rope_hash
from knotlab.core.machine import NUMERIC_KIND_KEY, numeric_kind
from knotlab.core.outcomes import StepOutcome
from knotlab.core.parallel import PerProcess
from knotlab.core.selection.labels import REACHED_BY, LabelledExecution

if TYPE_CHECKING:
    from knotlab.core.agent import Agent
    from knotlab.core.demos.tasks import RopeTask
    from knotlab.core.world.sim import RopeWorld, SimSnapshot

DEFAULT_ORACLE = OracleParams()


def policy_execution_prefix(policy: str, round_index: int, task_id: str) -> str:
    """The execution-id prefix of one start's policy states in one round."""
    return f"policy-{policy}-r{round_index}-{task_id}-"


@dataclass(frozen=True)
class PolicyStateJob:
    """One training start to roll out and label."""

    library_path: str
    model_path: str
    task_id: str
    start_nodes_k3: np.ndarray
    round_index: int
    policy: str = "greedy"
    params: OracleParams = DEFAULT_ORACLE


@dataclass(frozen=True)
class PolicyStateResult:
    """The executions labelled from one start's rollout, and what the rollout did."""

    task_id: str
    executions: tuple[LabelledExecution, ...]
    rollout_knot: bool
    rollout_steps: int
    chosen: tuple[str, ...]
    simulations: int
    wall_s: float


@dataclass(frozen=True)
class Rollout:
    """A policy's episode from a start: the states it reached after the start (step index, full
    simulator snapshot, rope nodes), the demos it chose, and whether it tied the knot."""

    visited: tuple[tuple[int, SimSnapshot, np.ndarray], ...]
    chosen: tuple[str, ...]
    knot: bool


def roll_out(policy_agent: Agent, world: RopeWorld, start_nodes_k3: np.ndarray) -> Rollout:
    """Play the policy from the start to the goal, an explosion or the step limit."""
    world.reset(start_nodes_k3)
    visited = []
    chosen: list[str] = []
    knot = False
    for step in range(policy_agent.task.step_limit):
        if step > 0:
            visited.append((step, world.snapshot(), world.rope_nodes()))
        decision = policy_agent.choose(world, step_index=step)
        outcome = policy_agent.act(world, decision.action)
        chosen.append(policy_agent.library.keys[decision.action])
        if outcome.knot:
            knot = True
            break
        if outcome.exploded:
            break
    return Rollout(tuple(visited), tuple(chosen), knot)


def reached_by(
    policy_agent: Agent, round_index: int, task_id: str, start_nodes_k3: np.ndarray
) -> dict:
    """What reached a rollout's states: the policy, its model, the round and the start."""
    model = policy_agent.model
    return {
        "policy": policy_agent.name,
        "model": None if model is None else model.content_hash(),
        "round": round_index,
        "start_task_id": task_id,
        "start_rope_hash": start_rope_hash(start_nodes_k3),
    }


def label_policy_states(
    policy_agent: Agent,
    oracle_agent: Agent,
    world: RopeWorld,
    task_id: str,
    start_nodes_k3: np.ndarray,
    *,
    round_index: int,
    params: OracleParams = DEFAULT_ORACLE,
) -> PolicyStateResult:
    """Roll ``policy_agent`` out from the start; label each visited state with the oracle."""
    t0 = time.perf_counter()
    limit = policy_agent.task.step_limit
    rollout = roll_out(policy_agent, world, start_nodes_k3)
    chosen = list(rollout.chosen)
    reached = reached_by(policy_agent, round_index, task_id, start_nodes_k3)
    executions = []
    sims = 0
    for step, snapshot, _ in rollout.visited:
        steps, dead, used, exhausted = oracle_from(
            oracle_agent, world, snapshot, steps_left=limit - step, params=params
        )
        sims += used
        prefix = policy_execution_prefix(policy_agent.name, round_index, task_id)
        executions.append(
            LabelledExecution(
                execution_id=f"{prefix}t{step}",
                source="oracle",
                labeller="oracle",
                steps=tuple(steps),
                ended_in_knot=bool(steps) and steps[-1].outcome == StepOutcome.KNOT,
                dead_ends=tuple(dead),
                task_id=f"{task_id}@{policy_agent.name}-r{round_index}-t{step}",
                library_hash=oracle_agent.featurizer.library_hash,
                metadata={
                    REACHED_BY: {**reached, "step": step, "chosen_before": chosen[:step]},
                    "simulations": used,
                    "budget_exhausted": exhausted,
                    "candidates": params.candidates,
                    "sim_budget": params.sim_budget,
                    NUMERIC_KIND_KEY: numeric_kind(),
                },
            )
        )
    return PolicyStateResult(
        task_id,
        tuple(executions),
        rollout.knot,
        len(chosen),
        tuple(chosen),
        sims,
        time.perf_counter() - t0,
    )


def _build(key: tuple[str, str, str]) -> tuple[RopeWorld, Agent, Agent]:
    """A world, the policy's agent and the oracle's (nearest-neighbour) agent, per process."""
    from knotlab.core.agent import Agent
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.world.sim import RopeWorld

    library_path, model_path, policy = key
    library = DemoLibrary.load(library_path)
    oracle = Agent(library)
    return RopeWorld(), oracle.with_model(QModel.load(Path(model_path)), policy), oracle


_TOOLS = PerProcess(_build)


def _job(job: PolicyStateJob) -> PolicyStateResult:
    world, policy_agent, oracle_agent = _TOOLS.get((job.library_path, job.model_path, job.policy))
    return label_policy_states(
        policy_agent,
        oracle_agent,
        world,
        job.task_id,
        job.start_nodes_k3,
        round_index=job.round_index,
        params=job.params,
    )


def label_policy_state_tasks(
    library_path: str | Path,
    model_path: str | Path,
    tasks: Iterable[RopeTask],
    *,
    round_index: int,
    policy: str = "greedy",
    params: OracleParams = DEFAULT_ORACLE,
    workers: int | None = None,
    progress: bool = True,
) -> Iterator[PolicyStateResult]:
    """Yield each start's result (in completion order), over local processes."""
    from knotlab.core.parallel import imap_processes

    jobs = [
        PolicyStateJob(
            str(library_path),
            str(model_path),
            t.task_id,
            t.start_nodes_k3,
            round_index,
            policy,
            params,
        )
        for t in tasks
    ]
    desc = f"{policy} states, round {round_index}"
    for _, result in imap_processes(_job, jobs, workers=workers, desc=desc, progress=progress):
        yield result
