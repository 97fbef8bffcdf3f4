"""Act: transfer a chosen demo onto the scene, execute it in a world, read the task's stage.

This is the step from a chosen demo to the next state: `apply_demo` plans the exact transfer
(`DemoTransferer`), executes the warped trajectory in the world (when there is one), and reads the
rope's stage and success through the task, so nothing here knows which knot is being tied.
Shape suffixes: n = cloud points, k = rope nodes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.failures import FailureKind
from knotlab.core.registration.planner import DemoTransferer, TransferPlan
from knotlab.core.tasks import Task, get_task
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.protocol import World

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.sim import ExecutionResult, SimSnapshot


@dataclass(frozen=True, eq=False)
class ActionOutcome:
    """What executing one transferred demo did to the world."""

    plan: TransferPlan
    execution: ExecutionResult | None  # None when nothing was executed
    nodes_after_k3: np.ndarray
    knot: bool  # the task's goal reached (for the knot-tying tasks: a real knot)
    stage: int  # the task's stage number (higher = further along)
    gauss_code: str
    snapshot_after: SimSnapshot

    @property
    def failure(self) -> str | None:
        """Why this action failed outright (registration, misgrasp, explosion), else None."""
        if not self.plan.ok:
            return self.plan.failure
        if self.execution is not None and not self.execution.ok:
            return self.execution.failure
        return None

    @property
    def failure_kind(self) -> FailureKind | None:
        """The kind of :attr:`failure` as set where it happened (planner or simulator)."""
        if not self.plan.ok:
            return self.plan.failure_kind
        if self.execution is not None:
            return self.execution.failure_kind
        return None

    @property
    def exploded(self) -> bool:
        """The simulation blew up: the world cannot continue from here."""
        return self.failure_kind is FailureKind.EXPLODED


def task_of(transferer: DemoTransferer) -> Task:
    """The task the transferer's library performs (what its outcomes are judged by)."""
    return get_task(transferer.library.task)


def apply_demo(
    world: World,
    transferer: DemoTransferer,
    cloud_n3: np.ndarray,
    demo_index: int,
    frames: FrameRecorder | None = None,
    *,
    task: Task | None = None,
) -> ActionOutcome:
    """Plan demo ``demo_index`` onto the cloud, execute it in ``world``, read the stage.

    ``task`` judges the result (default: the task the library records). A ``frames`` recorder
    records the execution for animation (``outcome.execution.frames``).
    """
    task = task if task is not None else task_of(transferer)
    plan = transferer.plan(cloud_n3, demo_index)
    execution = None
    if plan.ok:
        assert plan.trajectory is not None
        t0 = time.perf_counter()
        execution = world.execute(plan.trajectory, frames=frames)
        plan.timings["execute_s"] = time.perf_counter() - t0
    nodes = world.rope_nodes()
    reading = task.stage(nodes)
    return ActionOutcome(
        plan, execution, nodes, reading.success, reading.stage, reading.code, world.snapshot()
    )
