"""Why an action or an episode failed: one vocabulary, set where the failure happens.

The simulator sets MISGRASP and EXPLODED on its `ExecutionResult`, the transfer planner sets
REGISTRATION on a `TransferPlan` (registration or warp failed), and the episode runner adds
NO_KNOT (steps ran out) and ERROR (a numerical error inside a step, or a crash). Results files
store the value strings, so the names below are part of the file format.
"""

from __future__ import annotations

from enum import StrEnum


class FailureKind(StrEnum):
    """Kinds of failure, as stored in results files."""

    NO_KNOT = "no_knot"  # ran out of steps
    MISGRASP = "misgrasp"  # a gripper closed on nothing
    REGISTRATION = "registration"  # registration or trajectory warping failed
    EXPLODED = "exploded"  # the simulation blew up or the rope over-stretched
    ERROR = "error"  # a numerical error inside a step, or a crash

    @property
    def ends_episode(self) -> bool:
        """True when the world cannot go on after this failure."""
        return self in (FailureKind.REGISTRATION, FailureKind.EXPLODED, FailureKind.ERROR)
