"""One search expansion (simulate a demo from a state, value the child) and who runs them.

The lookahead simulates, level by level, the best (state, demo) pairs of its beam. Every
expansion is `expand`: restore the state, transfer and execute the demo, and (unless the child
is past the search's horizon or the simulation broke) observe the child and score every demo
there. A runner decides where that happens:

* `SequentialRunner`: in this process, one at a time, lazily, so the caller can stop at the
  first knot without simulating the rest (the bench: it parallelises over episodes instead);
* a process pool (the app's `SimPool`): every expansion of a level at once, results handed back
  in the level's order, so the search picks exactly what the sequential one would. Such a
  runner also takes the next level's expansions early (`prefetch`) once they are certain, so a
  worker that would wait for the level's last result starts on the next level instead.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from knotlab.core.execution.apply import ActionOutcome, apply_demo
from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.ranking import demo_scores
from knotlab.core.world.protocol import World

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.sim import SimSnapshot


@dataclass(frozen=True, eq=False)
class ExpansionJob:
    """Simulate demo ``action`` from ``snapshot`` (observed as ``cloud_n3``); value the child?"""

    snapshot: SimSnapshot
    cloud_n3: np.ndarray
    action: int
    value_child: bool


@dataclass(frozen=True, eq=False)
class ExpansionResult:
    """The action's outcome and, when valued, the child's cloud and every demo's score there."""

    outcome: ActionOutcome
    child_cloud_n3: np.ndarray | None
    child_q_a: np.ndarray | None


def child_is_valued(outcome: ActionOutcome) -> bool:
    """A child worth a scan: the simulation neither blew up nor left non-finite nodes."""
    return not outcome.exploded and bool(np.all(np.isfinite(outcome.nodes_after_k3)))


def value_child(
    world: World, featurizer: LibraryFeaturizer, model: QModel
) -> tuple[np.ndarray, np.ndarray]:
    """The world's current rope observed, and every demo's Q there (-inf where unusable)."""
    cloud = featurizer.observe(world)
    phi, scan = featurizer.features(cloud)
    return cloud, demo_scores(scan, phi, model)


def expand(
    world: World,
    transferer: DemoTransferer,
    featurizer: LibraryFeaturizer,
    model: QModel,
    job: ExpansionJob,
) -> ExpansionResult:
    """Run one expansion in ``world`` (left in the child's state)."""
    world.restore(job.snapshot)
    outcome = apply_demo(world, transferer, job.cloud_n3, job.action)
    if job.value_child and not outcome.knot and child_is_valued(outcome):
        cloud, q = value_child(world, featurizer, model)
        return ExpansionResult(outcome, cloud, q)
    return ExpansionResult(outcome, None, None)


class ExpansionRunner(Protocol):
    """Runs a level's expansions; yields their results in the order of ``jobs``."""

    speculates: bool  # worth telling it the next level's certain expansions early

    def prefetch(self, model: QModel, jobs: Sequence[ExpansionJob]) -> None:
        """Start expansions a later `run` will ask for (the same job objects)."""
        ...

    def drop_prefetched(self) -> None:
        """Forget (and cancel where possible) prefetched expansions nobody asked for."""
        ...

    def run(
        self,
        world: World,
        transferer: DemoTransferer,
        featurizer: LibraryFeaturizer,
        model: QModel,
        jobs: Sequence[ExpansionJob],
    ) -> Iterator[ExpansionResult]:
        """One result per job, in order (lazily where the runner can)."""
        ...


class SequentialRunner:
    """Expansions one after another in the caller's world, computed only when asked for."""

    speculates = False

    def prefetch(self, model: QModel, jobs: Sequence[ExpansionJob]) -> None:
        """Nothing to start early: one process, lazily."""

    def drop_prefetched(self) -> None:
        """Nothing prefetched."""

    def run(
        self,
        world: World,
        transferer: DemoTransferer,
        featurizer: LibraryFeaturizer,
        model: QModel,
        jobs: Sequence[ExpansionJob],
    ) -> Iterator[ExpansionResult]:
        """Yield each job's result as it is simulated."""
        for job in jobs:
            yield expand(world, transferer, featurizer, model, job)
