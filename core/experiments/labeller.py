"""Expert labels without a human: an oracle that plays the expert as the original labelling did.

The expert was shown candidates in registration-cost order and accepted the first that looked like
progress (docs/reference/original_system.md, 'Labelling protocol'). Our oracle makes "looks like
progress" precise with a bounded search in simulation: in each state it tries the ``candidates``
lowest-cost demos in cost order and accepts the first whose outcome still lets a knot be tied
within the remaining steps, decided by the same search from the outcome (depth-first, at most
``sim_budget`` simulated actions per task).

- The search first follows outcomes that advance the topological stage (loop, loop over tail,
  knot); outcomes that keep the stage are tried only while the remaining steps leave slack, and
  regressions, misgrasps and blow-ups are rejected (a misgrasp was skipped automatically by the
  original labelling too).
- A rejected outcome whose own search was exhausted (every candidate tried, not cut off by the
  budget) cannot lead to a knot in time: it is recorded as a dead-end state.
- Tasks the search cannot solve produce no steps (the original discarded them), but any dead ends
  found on the way are kept: they are labels too.

A task is its start rope, not only its id: each execution records its start rope's hash (metadata
``start_rope_hash``), and `labelled_task_ids` counts a task as labelled only when the stored
execution of its id started from the same rope (the hash, or for executions made before it was
recorded, the first step's rope nodes); a stored task id with another rope is refused.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.hashing import ContentHash
from knotlab.core.machine import NUMERIC_KIND_KEY, numeric_kind
from knotlab.core.outcomes import StepOutcome
from knotlab.core.parallel import PerProcess
from knotlab.core.selection.labels import DeadEndState, LabelledExecution, LabelledStep
from knotlab.core.world.protocol import World

if TYPE_CHECKING:  # the agent and the simulator: only for the checker
    from knotlab.core.agent import Agent
    from knotlab.core.demos.tasks import RopeTask
    from knotlab.core.execution.apply import ActionOutcome
    from knotlab.core.world.sim import RopeWorld, SimSnapshot


START_HASH_KEY = "start_rope_hash"  # execution metadata: the hash of the task's start rope
# A stored first-step rope within this of the task's start nodes (metres, any node and axis) is
# the same start: the simulator's reset resamples and lifts the rope, and the store keeps float32
# (0.17 mm at most on the 300 main-level training starts); another rope differs by centimetres.
START_TOLERANCE_M = 1e-3


def oracle_execution_id(task_id: str) -> str:
    """The id of the oracle's execution of one task."""
    return f"oracle-{task_id}"


def start_rope_hash(nodes_k3: np.ndarray) -> str:
    """The content hash of a start rope (its nodes as float64)."""
    nodes = np.asarray(nodes_k3, dtype=np.float64)
    return ContentHash().tagged_array("start_nodes_k3", nodes).hexdigest()


def _start_difference(execution: LabelledExecution, nodes_k3: np.ndarray) -> str | None:
    """How the start rope ``execution`` was made from differs from ``nodes_k3`` (None: the
    same, or nothing stored to tell)."""
    stored_hash = execution.metadata.get(START_HASH_KEY)
    if stored_hash is not None:
        now = start_rope_hash(nodes_k3)
        return None if stored_hash == now else f"start rope hash {stored_hash}, now {now}"
    first = execution.steps[0].rope_nodes_k3 if execution.steps else None
    if first is None:
        return None  # made before the hash was recorded and no step stored its rope
    nodes = np.asarray(nodes_k3, dtype=float)
    if first.shape != nodes.shape:
        return f"{len(first)} stored rope nodes, {len(nodes)} now"
    gap = float(np.max(np.abs(first - nodes)))
    return None if gap <= START_TOLERANCE_M else f"nodes up to {gap * 1000:.1f} mm apart"


def labelled_task_ids(
    tasks: Sequence[RopeTask], executions: Iterable[LabelledExecution], *, where: str
) -> set[str]:
    """Ids of ``tasks`` the oracle has labelled already: a stored oracle execution of the id that
    started from the same rope. One of another rope raises InvalidInputError (one line naming
    the task id): the same id with a different rope is another task, not one to skip."""
    stored = {e.execution_id: e for e in executions}
    done: set[str] = set()
    for task in tasks:
        execution = stored.get(oracle_execution_id(task.task_id))
        if execution is None:
            continue
        differs = _start_difference(execution, task.start_nodes_k3)
        if differs is not None:
            raise InvalidInputError(
                f"task {task.task_id} is already labelled in {where}, but the ropes differ "
                f"({differs}): this task set is not the one labelled there; label it into "
                "another --db"
            )
        done.add(task.task_id)
    return done


@dataclass(frozen=True)
class OracleParams:
    """Settings of the oracle labeller's bounded search."""

    candidates: int = 10  # lowest-cost demos tried per state (the original's MAX_ACTIONS_TO_TRY)
    max_steps: int | None = None  # None: the task's step limit
    sim_budget: int = 60  # simulated actions per task, all branches together


@dataclass
class OracleResult:
    """One labelled task: the execution (maybe without steps), and what the search cost."""

    execution: LabelledExecution
    simulations: int
    wall_s: float
    solved: bool
    budget_exhausted: bool


@dataclass
class _Search:
    world: World
    agent: Agent
    params: OracleParams
    sims: int = 0
    exhausted: bool = False
    dead_ends: list[DeadEndState] = field(default_factory=list)

    def solve(
        self,
        snapshot: SimSnapshot,
        cloud_n3: np.ndarray,
        nodes_k3: np.ndarray,
        stage: int,
        steps_left: int,
    ) -> tuple[list[LabelledStep] | None, bool]:
        """Steps to a knot within ``steps_left`` from this state, or None; and if exhaustive."""
        scan = self.agent.scan(cloud_n3)
        cost = np.where(scan.ok_a, scan.nn_cost_a, np.inf)
        order = [int(a) for a in np.argsort(cost, kind="stable")[: self.params.candidates]]
        order = [a for a in order if np.isfinite(cost[a])]
        keys = self.agent.library.keys
        goal_stage = len(self.agent.task.stage_names) - 1
        shown = tuple(keys[a] for a in order)
        shown_scores = np.array([cost[a] for a in order])
        deferred = []  # outcomes that kept the stage: tried only if nothing advances
        complete = True
        for a in order:
            if self.sims >= self.params.sim_budget:
                self.exhausted = True
                return None, False
            self.world.restore(snapshot)
            outcome = self.agent.act(self.world, a, cloud_n3=cloud_n3)
            self.sims += 1

            def step(label: StepOutcome, a: int = a) -> LabelledStep:
                return LabelledStep(0, cloud_n3, keys[a], label, nodes_k3, shown, shown_scores)

            if outcome.knot:
                return [step(StepOutcome.KNOT)], True
            if outcome.failure is not None:
                continue
            if outcome.stage > stage and steps_left > 1:
                result, exhaustive = self._descend(outcome, steps_left)
                if result is not None:
                    return [step(StepOutcome.PROGRESSED), *result], True
                complete &= exhaustive
            elif outcome.stage == stage and steps_left - 1 > goal_stage - stage:
                deferred.append((a, outcome))
        for a, outcome in deferred:
            result, exhaustive = self._descend(outcome, steps_left)
            if result is not None:
                step_ = LabelledStep(
                    0, cloud_n3, keys[a], StepOutcome.PROGRESSED, nodes_k3, shown, shown_scores
                )
                return [step_, *result], True
            complete &= exhaustive
        return None, complete

    def _descend(
        self, outcome: ActionOutcome, steps_left: int
    ) -> tuple[list[LabelledStep] | None, bool]:
        self.world.restore(outcome.snapshot_after)
        child_cloud = self.agent.observe(self.world)
        nodes = outcome.nodes_after_k3
        result, exhaustive = self.solve(
            outcome.snapshot_after, child_cloud, nodes, outcome.stage, steps_left - 1
        )
        if result is None and exhaustive:
            self.dead_ends.append(DeadEndState(child_cloud, nodes))
        return result, exhaustive


def oracle_from(
    agent: Agent,
    world: World,
    snapshot: SimSnapshot,
    *,
    steps_left: int,
    params: OracleParams = OracleParams(),
) -> tuple[list[LabelledStep], list[DeadEndState], int, bool]:
    """The oracle's search from a state in the middle of an episode (restored from
    ``snapshot``): its steps to the goal within ``steps_left`` (empty: none found), the dead
    ends met (the state itself when the search was exhaustive and found nothing), simulations
    used and whether the budget ran out. Step indices count from this state."""
    world.restore(snapshot)
    cloud = agent.observe(world)
    nodes = world.rope_nodes()
    stage = agent.task.stage(nodes).stage
    search = _Search(world, agent, params)
    steps, exhaustive = search.solve(snapshot, cloud, nodes, stage, steps_left)
    dead = list(search.dead_ends)
    if steps is None and exhaustive:
        dead.append(DeadEndState(cloud, nodes))
    return list(_numbered(steps or [])), dead, search.sims, search.exhausted


def _numbered(steps: Sequence[LabelledStep]) -> tuple[LabelledStep, ...]:
    """The search's steps with their indices in the execution (0, 1, ...)."""
    return tuple(dataclasses.replace(s, step_index=i) for i, s in enumerate(steps))


def label_task(
    agent: Agent,
    world: World,
    start_nodes_k3: np.ndarray,
    *,
    task_id: str,
    params: OracleParams = OracleParams(),
) -> OracleResult:
    """Label one start state with the oracle expert; returns the execution it produced."""
    t0 = time.perf_counter()
    world.reset(start_nodes_k3)
    snapshot = world.snapshot()
    cloud = agent.observe(world)
    nodes = world.rope_nodes()
    stage = agent.task.stage(nodes).stage
    search = _Search(world, agent, params)
    max_steps = agent.task.step_limit if params.max_steps is None else params.max_steps
    steps, _ = search.solve(snapshot, cloud, nodes, stage, max_steps)
    labelled = _numbered(steps or [])
    execution = LabelledExecution(
        execution_id=oracle_execution_id(task_id),
        source="oracle",
        labeller="oracle",
        steps=labelled,
        ended_in_knot=bool(labelled) and labelled[-1].outcome == StepOutcome.KNOT,
        dead_ends=tuple(search.dead_ends),
        task_id=task_id,
        library_hash=agent.featurizer.library_hash,
        metadata={
            "simulations": search.sims,
            "candidates": params.candidates,
            "sim_budget": params.sim_budget,
            "budget_exhausted": search.exhausted,
            START_HASH_KEY: start_rope_hash(start_nodes_k3),
            NUMERIC_KIND_KEY: numeric_kind(),
        },
    )
    return OracleResult(
        execution, search.sims, time.perf_counter() - t0, bool(labelled), search.exhausted
    )


@dataclass(frozen=True)
class _LabelJob:
    library_path: str
    task_id: str
    start_nodes_k3: np.ndarray
    params: OracleParams


def _build_tools(library_path: str) -> tuple[RopeWorld, Agent]:
    """A world and a nearest-neighbour agent on one library (built once per worker process)."""
    from knotlab.core.agent import Agent
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.world.sim import RopeWorld

    return RopeWorld(), Agent(DemoLibrary.load(library_path))


_TOOLS = PerProcess(_build_tools)  # per process: library path -> (world, agent)


def _label_job(job: _LabelJob) -> OracleResult:
    world, agent = _TOOLS.get(job.library_path)
    return label_task(agent, world, job.start_nodes_k3, task_id=job.task_id, params=job.params)


def oracle_label_tasks(
    library_path: str,
    tasks: Iterable[RopeTask],
    *,
    params: OracleParams = OracleParams(),
    workers: int | None = None,
    progress: bool = True,
) -> Iterator[OracleResult]:
    """Yield an OracleResult per task (in completion order), labelling over local processes."""
    from knotlab.core.parallel import imap_processes

    jobs = [_LabelJob(str(library_path), t.task_id, t.start_nodes_k3, params) for t in tasks]
    for _, result in imap_processes(
        _label_job, jobs, workers=workers, desc="oracle labelling", progress=progress
    ):
        yield result
