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
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.demos.tasks import RopeTask
from knotlab.core.experiments.episode import EpisodeRecord
from knotlab.core.outcomes import StepOutcome
from knotlab.core.parallel import PerProcess
from knotlab.core.selection.labels import LabelledExecution, LabelledStep
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
    for step, (stage_before, tried) in enumerate(zip(stages_before, roots, strict=True)):
        full = StateTries(execution_id, step, int(stage_before), tuple(tried))
        kept = tuple(t for t in full.tried if not full.advanced(t))
        out.append(StateTries(execution_id, step, int(stage_before), kept))
    return out


def search_execution_id(policy: str, task_id: str) -> str:
    """The id of one start's search execution."""
    return f"search-{policy}-{task_id}"


@dataclass(frozen=True)
class SearchLabelJob:
    """One training start to play the search from."""

    library_path: str
    model_path: str
    policy: str
    start: RopeTask


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


def label_with_search(agent: Agent, world: RopeWorld, start: RopeTask) -> SearchLabelResult:
    """Play ``agent``'s search from the start; a knotted clean episode is the label."""
    t0 = time.perf_counter()
    record = agent.run_episode(world, start)
    keys = agent.library.keys
    assert agent.model is not None  # a search values its leaves with the model
    model_hash = agent.model.content_hash()
    eid = search_execution_id(agent.name, start.task_id)
    meta = {
        "labelled_by": {"policy": agent.name, "model": model_hash},
        "search_knotted": bool(record.success),
        "search_chosen": [s.chosen_key for s in record.steps],
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
    tries: tuple[StateTries, ...] = ()
    if execution is None:  # recorded without steps, so a resumed run does not replay it
        execution = LabelledExecution(
            eid,
            "oracle",
            f"search-{agent.name}",
            (),
            False,
            task_id=start.task_id,
            library_hash=agent.library.content_hash(),
            metadata=meta,
        )
    else:
        before = [agent.task.stage(s.rope_nodes_k3).stage for s in execution.steps]
        roots = [root_tries(s.info, keys) for s in record.steps]
        tries = tuple(floor_tries(eid, before, roots))
    return SearchLabelResult(
        start.task_id,
        execution,
        tries,
        bool(record.success),
        tuple(s.chosen_key for s in record.steps),
        time.perf_counter() - t0,
    )


def _build(key: tuple[str, str, str]) -> tuple[RopeWorld, Agent]:
    from knotlab.core.agent import Agent
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.world.sim import RopeWorld

    library_path, model_path, policy = key
    library = DemoLibrary.load(library_path)
    return RopeWorld(), Agent(library, QModel.load(Path(model_path)), policy)


_TOOLS = PerProcess(_build)


def _job(job: SearchLabelJob) -> SearchLabelResult:
    world, agent = _TOOLS.get((job.library_path, job.model_path, job.policy))
    return label_with_search(agent, world, job.start)


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
        yield result
