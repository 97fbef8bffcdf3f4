"""Labels from a search policy's own episodes (expert iteration).

The oracle labels a state with the cheapest demo in registration-cost order that can still reach
the goal; a lookahead policy ranks demos by simulating them and valuing what follows with the
model. An episode of the lookahead that reaches the goal is a demonstration: each state it saw
and the demo it chose become a labelled step, so a model fitted on them imitates the search
(the search improves on the model's one-step choice; the new model learns that improvement).
An episode that misses the goal, or has a step that failed, is no demonstration and gives none.

The search's first level (each root candidate simulated once from the state) also says which
candidates did not advance the task's stage; as tries they ask the learner to rank those below
the choice by a margin floor, while candidates that advanced stay ordinary margin rows (the
search ranked them below its choice by what followed, which is the point of these labels).

Labels where the policy goes, with the search as the expert (DAgger with a search expert): roll
a learned policy (greedy) out from the start, and from every state it reaches after the start
play the search to the goal with the steps that remain; each search episode that reaches the goal
cleanly is a labelled execution beginning in the state the policy reached, and records (as the
oracle's policy-state labels do) which policy, model and round reached it.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.demos.tasks import RopeTask
from knotlab.core.experiments.episode import EpisodeRecord, run_episode
from knotlab.core.experiments.policy_states import reached_by, roll_out
from knotlab.core.machine import NUMERIC_KIND_KEY, numeric_kind
from knotlab.core.outcomes import StepOutcome
from knotlab.core.parallel import PerProcess
from knotlab.core.selection.labels import REACHED_BY, LabelledExecution, LabelledStep
from knotlab.core.selection.tries import StateTries, TriedDemo

if TYPE_CHECKING:
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

SHOWN_CANDIDATES = 5  # the candidates a label records as shown: the search's top scores


def execution_from_episode(
    record: EpisodeRecord,
    keys: Sequence[str],
    *,
    execution_id: str,
    labeller: str,
    model_hash: str,
    library_hash: str,
    metadata: dict | None = None,
) -> LabelledExecution | None:
    """The episode as a labelled execution, or None when it is no demonstration (no goal, or a
    step that failed)."""
    if not record.success or not all(
        s.outcome in (StepOutcome.PROGRESSED, StepOutcome.KNOT) for s in record.steps
    ):
        return None
    steps = []
    for s in record.steps:
        # A goal found by the search scores +inf and a dead branch -inf; a label stores finite
        # float32 scores, so they become the largest and smallest float32.
        big = float(np.finfo(np.float32).max)
        scores = np.nan_to_num(np.asarray(s.scores_a, dtype=float), posinf=big, neginf=-big)
        top = np.argsort(-scores, kind="stable")[:SHOWN_CANDIDATES]
        steps.append(
            LabelledStep(
                s.step_index,
                s.cloud_n3,
                s.chosen_key,
                StepOutcome.KNOT if s.knot else StepOutcome.PROGRESSED,
                s.nodes_before_k3,
                tuple(keys[int(a)] for a in top),
                scores[top],
                model_hash,
            )
        )
    return LabelledExecution(
        execution_id=execution_id,
        source="oracle",  # a simulated expert, as the oracle; the labeller names the search
        labeller=labeller,
        steps=tuple(steps),
        ended_in_knot=True,
        task_id=record.task_id,
        library_hash=library_hash,
        metadata=dict(metadata or {}),
    )


def root_tries(info: dict, keys: Sequence[str]) -> tuple[TriedDemo, ...]:
    """The search tree's first level (from a lookahead decision's ``info``): what each root
    candidate did when simulated once from the state."""
    return tuple(
        TriedDemo(keys[int(n["action"])], int(n["stage"]), bool(n["knot"]), n["failure"])
        for n in info.get("tree", ())
        if n["level"] == 1
    )


def floor_tries(
    execution_id: str, stages_before: Sequence[int], roots: Sequence[Sequence[TriedDemo]]
) -> list[StateTries]:
    """Per step, the root candidates that did not advance from the stage of the state the step
    began in (``stages_before``: the task's stage of each labelled state's rope)."""
    out = []
    kind = numeric_kind()
    for step, (stage_before, tried) in enumerate(zip(stages_before, roots, strict=True)):
        full = StateTries(execution_id, step, int(stage_before), tuple(tried))
        kept = tuple(t for t in full.tried if not full.advanced(t))
        out.append(StateTries(execution_id, step, int(stage_before), kept, kind))
    return out


def search_execution_id(policy: str, task_id: str) -> str:
    """The id of one start's search execution."""
    return f"search-{policy}-{task_id}"


@dataclass(frozen=True)
class SearchLabelJob:
    """One training start to play the search from (or, with ``from_policy``, to roll the policy
    out from and let the search label the states it reaches)."""

    library_path: str
    model_path: str
    policy: str
    start: RopeTask
    from_policy: str | None = None
    policy_model_path: str | None = None
    round_index: int = 1


@dataclass(frozen=True)
class SearchLabelResult:
    """One start's search episode: its execution (no steps when it is no demonstration), the
    floor tries of its states, and what the episode did."""

    task_id: str
    execution: LabelledExecution
    tries: tuple[StateTries, ...]
    knot: bool
    chosen: tuple[str, ...]
    wall_s: float


def _search_label(
    agent: Agent, record: EpisodeRecord, eid: str, task_id: str, meta: dict
) -> tuple[LabelledExecution, tuple[StateTries, ...]]:
    """The episode's labelled execution (no steps when it is no demonstration, so a resumed run
    does not replay it) and its states' floor tries."""
    keys = agent.library.keys
    assert agent.model is not None  # a search values its leaves with the model
    model_hash = agent.model.content_hash()
    meta = {
        **meta,
        "labelled_by": {"policy": agent.name, "model": model_hash},
        "search_knotted": bool(record.success),
        "search_chosen": [s.chosen_key for s in record.steps],
        NUMERIC_KIND_KEY: numeric_kind(),
    }
    execution = execution_from_episode(
        record,
        keys,
        execution_id=eid,
        labeller=f"search-{agent.name}",
        model_hash=model_hash,
        library_hash=agent.library.content_hash(),
        metadata=meta,
    )
    if execution is None:
        empty = LabelledExecution(
            eid,
            "oracle",
            f"search-{agent.name}",
            (),
            False,
            task_id=task_id,
            library_hash=agent.library.content_hash(),
            metadata=meta,
        )
        return empty, ()
    before = [agent.task.stage(s.rope_nodes_k3).stage for s in execution.steps]
    roots = [root_tries(s.info, keys) for s in record.steps]
    return execution, tuple(floor_tries(eid, before, roots))


def label_with_search(agent: Agent, world: RopeWorld, start: RopeTask) -> SearchLabelResult:
    """Play ``agent``'s search from the start; a knotted clean episode is the label."""
    t0 = time.perf_counter()
    record = agent.run_episode(world, start)
    eid = search_execution_id(agent.name, start.task_id)
    execution, tries = _search_label(agent, record, eid, start.task_id, {})
    return SearchLabelResult(
        start.task_id,
        execution,
        tries,
        bool(record.success),
        tuple(s.chosen_key for s in record.steps),
        time.perf_counter() - t0,
    )


def policy_search_prefix(search: str, policy: str, round_index: int, task_id: str) -> str:
    """The execution-id prefix of one start's policy states labelled by the search."""
    return f"{search_execution_id(search, '')}{policy}-r{round_index}-{task_id}-"


@dataclass(frozen=True)
class PolicySearchResult:
    """One start's rollout of the policy and the search's labels of the states it reached."""

    task_id: str
    executions: tuple[LabelledExecution, ...]
    tries: tuple[StateTries, ...]
    rollout_knot: bool
    chosen: tuple[str, ...]
    wall_s: float


def label_policy_states_with_search(
    policy_agent: Agent,
    search_agent: Agent,
    world: RopeWorld,
    start: RopeTask,
    *,
    round_index: int,
) -> PolicySearchResult:
    """Roll ``policy_agent`` out from the start; from each state it reaches after the start, the
    search plays to the goal with the steps left, and its clean knotted episode is the label."""
    t0 = time.perf_counter()
    limit = policy_agent.task.step_limit
    rollout = roll_out(policy_agent, world, start.start_nodes_k3)
    chosen = list(rollout.chosen)
    reached = reached_by(policy_agent, round_index, start.task_id, start.start_nodes_k3)
    prefix = policy_search_prefix(search_agent.name, policy_agent.name, round_index, start.task_id)
    executions: list[LabelledExecution] = []
    tries: list[StateTries] = []
    for step, snapshot, nodes in rollout.visited:
        task_id = f"{start.task_id}@{policy_agent.name}-r{round_index}-t{step}"
        record = run_episode(
            search_agent,
            world,
            nodes,
            task_id=task_id,
            seed=start.seed,
            max_steps=limit - step,
            start_snapshot=snapshot,
        )
        meta = {REACHED_BY: {**reached, "step": step, "chosen_before": chosen[:step]}}
        execution, state_tries = _search_label(
            search_agent, record, f"{prefix}t{step}", task_id, meta
        )
        executions.append(execution)
        tries.extend(state_tries)
    return PolicySearchResult(
        start.task_id,
        tuple(executions),
        tuple(tries),
        rollout.knot,
        rollout.chosen,
        time.perf_counter() - t0,
    )


def _build(
    key: tuple[str, str, str, str | None, str | None],
) -> tuple[RopeWorld, Agent, Agent | None]:
    """A world, the search's agent and (for policy states) the rolled-out policy's, per process."""
    from knotlab.core.agent import Agent
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.world.sim import RopeWorld

    library_path, model_path, policy, from_policy, policy_model_path = key
    library = DemoLibrary.load(library_path)
    search = Agent(library, QModel.load(Path(model_path)), policy)
    rolled = None
    if from_policy is not None and policy_model_path is not None:
        rolled = Agent(library, QModel.load(Path(policy_model_path)), from_policy)
    return RopeWorld(), search, rolled


_TOOLS = PerProcess(_build)


def _job(job: SearchLabelJob) -> SearchLabelResult | PolicySearchResult:
    key = (job.library_path, job.model_path, job.policy, job.from_policy, job.policy_model_path)
    world, agent, policy_agent = _TOOLS.get(key)
    if policy_agent is None:
        return label_with_search(agent, world, job.start)
    return label_policy_states_with_search(
        policy_agent, agent, world, job.start, round_index=job.round_index
    )


def label_search_tasks(
    library_path: str | Path,
    model_path: str | Path,
    tasks: Iterable[RopeTask],
    *,
    policy: str,
    workers: int | None = None,
    progress: bool = True,
) -> Iterator[SearchLabelResult]:
    """Yield each start's result (in completion order), over local processes."""
    from knotlab.core.parallel import imap_processes

    jobs = [SearchLabelJob(str(library_path), str(model_path), policy, t) for t in tasks]
    desc = f"{policy} labels"
    for _, result in imap_processes(_job, jobs, workers=workers, desc=desc, progress=progress):
        assert isinstance(result, SearchLabelResult)
        yield result


def label_policy_state_search_tasks(
    library_path: str | Path,
    model_path: str | Path,
    policy_model_path: str | Path,
    tasks: Iterable[RopeTask],
    *,
    search: str,
    from_policy: str = "greedy",
    round_index: int = 1,
    workers: int | None = None,
    progress: bool = True,
) -> Iterator[PolicySearchResult]:
    """Yield each start's policy states labelled by the search (completion order)."""
    from knotlab.core.parallel import imap_processes

    jobs = [
        SearchLabelJob(
            str(library_path),
            str(model_path),
            search,
            t,
            from_policy,
            str(policy_model_path),
            round_index,
        )
        for t in tasks
    ]
    desc = f"{from_policy} states labelled by {search}, round {round_index}"
    for _, result in imap_processes(_job, jobs, workers=workers, desc=desc, progress=progress):
        assert isinstance(result, PolicySearchResult)
        yield result
