"""Simulated outcomes kept for reuse: a search (and the policies of one task) simulates an
expansion once.

Restoring a snapshot and executing is bit-identical to the run that made the snapshot
(`RopeWorld`), and the transfer is a pure function of the cloud and demo, so an outcome stored
under (world, transferer, state digest, cloud digest, action) is exactly what simulating it again
would give.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.arrays import cloud_digest
from knotlab.core.execution.apply import ActionOutcome, apply_demo
from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.tasks import Task
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.protocol import World

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.sim import SimSnapshot


def snapshot_digest(snapshot: SimSnapshot) -> str:
    """sha1 of a simulator snapshot's arrays and time: equal digests, the same world state."""
    digest = hashlib.sha1(repr(snapshot.sim_time).encode())
    for name in ("positions_l3", "quaternions_l4", "linear_velocities_l3", "angular_velocities_l3"):
        digest.update(np.ascontiguousarray(getattr(snapshot, name), dtype=np.float64).tobytes())
    return digest.hexdigest()


class OutcomeMemo:
    """Simulated expansions by (world, transferer, state, cloud, action), least recent dropped.

    Restoring a snapshot and executing is bit-identical to the run that made the snapshot
    (`RopeWorld`), and the transfer is a pure function of the cloud and demo, so an expansion
    seen before has exactly the outcome it had: la2x5 simulates the chosen child's best
    children, and the next decision starts from that child and would simulate them again.
    """

    def __init__(self, size: int = 64) -> None:
        self.size = size
        self._items: OrderedDict[tuple, ActionOutcome] = OrderedDict()
        self.hits = 0

    @staticmethod
    def key(
        world: World, transferer: DemoTransferer, snapshot_key: str, cloud_key: str, action: int
    ) -> tuple:
        """The memo key of one expansion."""
        return (id(world), id(transferer), snapshot_key, cloud_key, int(action))

    def get(self, key: tuple) -> ActionOutcome | None:
        """The stored outcome, or None."""
        out = self._items.get(key)
        if out is not None:
            self.hits += 1
            self._items.move_to_end(key)
        return out

    def put(self, key: tuple, outcome: ActionOutcome) -> None:
        """Store an outcome (dropping the least recent past ``size``)."""
        self._items[key] = outcome
        self._items.move_to_end(key)
        while len(self._items) > self.size:
            self._items.popitem(last=False)


def execute_with_memo(
    memo: OutcomeMemo | None,
    world: World,
    transferer: DemoTransferer,
    cloud_n3: np.ndarray,
    action: int,
    state_key: str | None = None,
    *,
    task: Task | None = None,
    frame_dt: float | None = None,
) -> ActionOutcome:
    """`apply_demo`, through ``memo`` when one is given; the world ends in the after-state.

    A stored outcome is restored (`snapshot_after`), not simulated: the same state as executing
    it (see `OutcomeMemo`). ``state_key``: the world's snapshot digest, if the caller has it.
    ``frame_dt``: the execution is also recorded every ``frame_dt`` s (`outcome.execution.frames`;
    recording reads poses only, so the outcome is the same); a stored outcome without such
    frames is executed again.
    """
    if memo is None:
        return apply_demo(
            world, transferer, cloud_n3, action, task=task, frames=_recorder(frame_dt)
        )
    state = state_key if state_key is not None else snapshot_digest(world.snapshot())
    key = OutcomeMemo.key(world, transferer, state, cloud_digest(cloud_n3), action)
    outcome = memo.get(key)
    if outcome is not None and _has_frames(outcome, frame_dt):
        world.restore(outcome.snapshot_after)
        return outcome
    outcome = apply_demo(world, transferer, cloud_n3, action, task=task, frames=_recorder(frame_dt))
    memo.put(key, outcome)
    return outcome


def _recorder(frame_dt: float | None) -> FrameRecorder | None:
    return None if frame_dt is None else FrameRecorder(frame_dt)


def _has_frames(outcome: ActionOutcome, frame_dt: float | None) -> bool:
    """Whether a stored outcome carries what the caller asks: frames every ``frame_dt`` s."""
    if frame_dt is None or outcome.execution is None:
        return True
    frames = outcome.execution.frames
    if frames is None or len(frames) < 2:
        return False
    return bool(abs(frames.times_f[1] - frame_dt) < 0.5 * frame_dt)
