"""Try the cheapest candidates of each labelled state once in simulation (core.selection.tries).

Each state is rebuilt at rest from the rope nodes its label stored, and each of the ``top``
candidates the expert was shown (registration-cost order) is transferred and executed from it.
The same rope nodes give the same outcomes on one machine (the simulator is deterministic);
96 % of the oracle's own choices advance again when replayed this way on the main labels.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence, Set
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.machine import numeric_kind
from knotlab.core.parallel import PerProcess, imap_processes
from knotlab.core.selection.labels import LabelledExecution
from knotlab.core.selection.tries import StateTries, TriedDemo


@dataclass(frozen=True, eq=False)
class TryJob:
    """One labelled state: its rope, its cloud and the demos to try from it."""

    execution_id: str
    step_index: int
    nodes_k3: np.ndarray
    cloud_n3: np.ndarray
    candidates: tuple[str, ...]


def try_jobs(
    executions: Sequence[LabelledExecution],
    top: int,
    done: Set[tuple[str, int]] = frozenset(),
) -> list[TryJob]:
    """A job per labelled state not in ``done`` that stored its rope and the candidates shown."""
    jobs = []
    for ex in executions:
        for step in ex.steps:
            key = (ex.execution_id, step.step_index)
            if key in done or step.rope_nodes_k3 is None or not step.candidates:
                continue
            jobs.append(
                TryJob(*key, step.rope_nodes_k3, step.cloud_n3, tuple(step.candidates[:top]))
            )
    return jobs


def check_tries_match(
    tries: Mapping[tuple[str, int], StateTries],
    executions: Sequence[LabelledExecution],
    top: int,
    *,
    where: str | Path,
) -> None:
    """Raise InvalidInputError (one line) unless every state in ``tries`` is a labelled state of
    ``executions`` whose ``top`` first candidates are the demos tried: tries made from these
    labels with this ``top``, that a run may resume."""
    shown = {
        (ex.execution_id, step.step_index): tuple(step.candidates[:top])
        for ex in executions
        for step in ex.steps
    }
    for key, rec in tries.items():
        if key not in shown:
            raise InvalidInputError(
                f"{where}: holds tries of {key[0]} step {key[1]}, which is not a labelled state "
                "of these --labels: it was made from other labels; use a new --out"
            )
        tried = tuple(t.demo for t in rec.tried)
        if tried != shown[key]:
            raise InvalidInputError(
                f"{where}: {key[0]} step {key[1]} tried {', '.join(tried)} but these --labels "
                f"with --top {top} give {', '.join(shown[key]) or 'no candidates'}: made from "
                "other labels or another --top; use a new --out"
            )


class _Trier:
    """A worker's simulator and agent (it only acts: the candidates come with the job)."""

    def __init__(self, library: DemoLibrary) -> None:
        from knotlab.core.agent import Agent
        from knotlab.core.parallel import single_thread_blas
        from knotlab.core.world.sim import RopeWorld

        single_thread_blas()
        self.world = RopeWorld()
        self.agent = Agent(library)

    def run(self, job: TryJob) -> StateTries:
        """Each candidate of the job executed once from the labelled state at rest."""
        self.world.reset(job.nodes_k3)
        start = self.world.snapshot()
        before = self.agent.task.stage(self.world.rope_nodes()).stage
        tried = []
        for key in job.candidates:
            self.world.restore(start)
            out = self.agent.act(self.world, key, cloud_n3=job.cloud_n3)
            tried.append(TriedDemo(key, int(out.stage), bool(out.knot), out.failure))
        return StateTries(job.execution_id, job.step_index, before, tuple(tried), numeric_kind())


_TRIER: PerProcess[_Trier] = PerProcess(_Trier)


def _init(library: DemoLibrary) -> None:
    _TRIER.reset()
    _TRIER.get(library)


def _run(job: TryJob) -> StateTries:
    return _TRIER.current().run(job)


def try_candidates(
    jobs: Sequence[TryJob], library: DemoLibrary, *, workers: int | None = None,
    progress: bool = True,
) -> Iterator[StateTries]:  # fmt: skip
    """Each job's tries as it finishes (over ``workers`` processes; order not kept)."""
    for _, rec in imap_processes(
        _run, list(jobs), workers=workers, initializer=partial(_init, library),
        desc="trying candidates", progress=progress,
    ):  # fmt: skip
        yield rec
