"""`World`: what policies, episodes, the labeller and the agent call on a simulated rope world.

`RopeWorld` (core/world/sim.py) is the one implementation; code that is handed a world types it
as `World`, so it needs neither pybullet nor the simulator module (mypy checks that a RopeWorld
passed in satisfies it). Code that makes its own world (a bench worker, a replay) still builds a
`RopeWorld`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, cast

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    import numpy as np

    from knotlab.core.world.frames import FrameRecorder
    from knotlab.core.world.sim import ExecutionResult, RopeParams, SimSnapshot
    from knotlab.core.world.trajectory import GripperTrajectory


class World(Protocol):
    """A rope on a table with two grippers: reset, snapshot/restore, execute and observe."""

    @property
    def params(self) -> RopeParams:
        """The rope's physical parameters (radius, length, links)."""
        ...

    def reset(self, rope_nodes_k3: np.ndarray) -> None:
        """Place the rope at rest along the given polyline."""
        ...

    def snapshot(self) -> SimSnapshot:
        """The current full state (a plain, picklable record)."""
        ...

    def restore(self, snapshot: SimSnapshot) -> None:
        """Return to a snapshot; what follows is bit-identical to the run that made it."""
        ...

    def rope_nodes(self) -> np.ndarray:
        """Rope node positions (K, 3)."""
        ...

    def execute(
        self,
        traj: GripperTrajectory,
        settle_time: float | None = None,
        frames: FrameRecorder | None = None,
    ) -> ExecutionResult:
        """Move the grippers along ``traj`` (grasping and releasing), then settle."""
        ...

    def observe(
        self,
        noise: float = 0.0,
        seed: int | None = None,
        max_points: int = 150,
        voxel: float = 0.025,
    ) -> np.ndarray:
        """Point cloud (N, 3) on the rope's upper surface."""
        ...


class _NoWorld:
    """Stands for the world in a decision made from a cloud alone; any use is a clear error."""

    def __getattr__(self, name: str) -> object:
        from knotlab.core.errors import InvalidInputError

        raise InvalidInputError(
            f"this decision was made from a cloud alone: there is no world to {name} "
            "(a policy that simulates needs a rope-state estimate)"
        )


# A policy that does not simulate never touches its context's world; this one says so if it did.
NO_WORLD = cast(World, _NoWorld())
