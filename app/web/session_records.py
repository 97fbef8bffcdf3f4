"""The labelling session's records and vocabularies: its phases, a drive step's outcome, the
candidates it shows, a try's result and the view the GUI draws (plain data, no viser calls).

Shape suffixes: g = grippers, t = waypoints, k = rope nodes, n = cloud points.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.failures import FailureKind
from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.ranking import RankedDemo
from knotlab.core.world.frames import ExecutionFrames

# The key that stops the model where it is (not S: viser's camera moves on W, A, S, D, Q, E).
STOP_MODEL_KEY = "X"


class Phase(StrEnum):
    """Where a session is in the labelling protocol."""

    CHOOSING = "choosing"  # candidates shown, pick one and try it
    TRYING = "trying"  # the simulator is executing the selected candidate
    MODEL = "model"  # the model's own choices move the rope until one fails (or it is stopped)
    JUDGING = "judging"  # the result is shown: accept, reject or dead end
    NO_STARTS = "no_starts"  # every training start is labelled or claimed
    CLOSED = "closed"


class DriveOutcome(StrEnum):
    """What one step of the model driving the rope led to."""

    CONTINUES = "continues"  # the choice advanced the rope: the model chooses again
    HANDED_OVER = "handed_over"  # its choice failed, or it was stopped: the expert labels here
    TIED = "tied"  # the model tied the knot from this start: nothing to label; next start
    STOPPED = "stopped"  # the session left the MODEL phase meanwhile (closed, taken over)


class SessionError(Exception):
    """An action that the session's phase does not allow (shown to the expert, not a crash)."""


@dataclass(frozen=True, eq=False)
class Candidate:
    """A ranked demo with its gripper trajectory warped onto the current scene, for drawing."""

    ranked: RankedDemo
    demo_step: int  # which step of its own demonstration the demo segment was
    positions_gt3: np.ndarray  # warped through the scan's f (the executed one is exact)
    closed_gt: np.ndarray

    @property
    def grasp_points(self) -> list[np.ndarray]:
        """Where a gripper closes (one point per close), both grippers."""
        return _switch_points(self.positions_gt3, self.closed_gt, closing=True)

    @property
    def release_points(self) -> list[np.ndarray]:
        """Where a gripper opens after holding."""
        return _switch_points(self.positions_gt3, self.closed_gt, closing=False)


def _switch_points(pos_gt3: np.ndarray, closed_gt: np.ndarray, *, closing: bool) -> list:
    out = []
    for g in range(2):
        flags = closed_gt[g].astype(int)
        change = np.flatnonzero(np.diff(np.concatenate([[0], flags])) == (1 if closing else -1))
        out += [pos_gt3[g, t] for t in change]
    return out


@dataclass(frozen=True, eq=False)
class TryResult:
    """What trying a candidate did: the executed trajectory, frames and outcome."""

    rank: int
    demo_key: str
    outcome: ActionOutcome
    frames: ExecutionFrames | None
    word: StepOutcome | FailureKind  # PROGRESSED, KNOT, or the try's failure kind
    cloud_after_n3: np.ndarray | None
    wall_s: float
    stage_before: int = 0  # the task's stage of the state the try started from
    stage_names: tuple[str, ...] = ()  # the task's names of its stages

    @property
    def summary(self) -> str:
        """What the try did, honestly: the stage reached (with its crossing code) and whether
        that is further than before, or the failure."""
        if self.word not in (StepOutcome.PROGRESSED, StepOutcome.KNOT):
            return str(getattr(self.word, "value", self.word))
        names = self.stage_names
        after = int(self.outcome.stage)

        def name(stage: int) -> str:
            return names[stage] if 0 <= stage < len(names) else f"stage {stage}"

        code = f" ({self.outcome.gauss_code or 'no crossings'})"
        if self.outcome.knot:
            return f"{name(after)}{code}"
        if after > self.stage_before:
            return f"{name(after)}{code}: advanced from {name(self.stage_before)}"
        if after == self.stage_before:
            return f"nothing gained: still {name(after)}{code}"
        return f"went back to {name(after)}{code} from {name(self.stage_before)}"

    @property
    def stage_reached(self) -> str:
        """The name of the task's stage the rope is in after the try."""
        stage, names = int(self.outcome.stage), self.stage_names
        return names[stage] if 0 <= stage < len(names) else f"stage {stage}"

    @property
    def acceptable(self) -> bool:
        """Only an execution that ran may be accepted (a misgrasp or blow-up can be rejected)."""
        return self.word in (StepOutcome.PROGRESSED, StepOutcome.KNOT)


@dataclass
class SessionView:
    """Everything the GUI and scene draw for a session (a consistent snapshot)."""

    phase: Phase
    labeller: str
    task_id: str | None
    step_index: int
    max_steps: int
    rope_nodes_k3: np.ndarray | None
    cloud_n3: np.ndarray | None
    candidates: list[Candidate]
    selected: int | None  # rank
    rejected: frozenset[int]  # ranks greyed out (rejected or marked dead ends)
    model: str
    last_try: TryResult | None
    message: str = ""
    rank_s: float = 0.0
    history: list[str] = field(default_factory=list)
    dead_ends: frozenset[int] = frozenset()  # ranks whose try was stored as a dead end
    first_step: int = 0  # the rollout step this episode's first state is at (model mode)
    model_mode: bool = False
    model_failed: int | None = None  # the rank of the model's choice that failed in this state
    goal: str = ""  # the task's goal in words (e.g. "tie an overhand knot ...")

    @property
    def rollout_step(self) -> int:
        """The state's step in the task's rollout (0: its start), across a model's drive."""
        return self.first_step + self.step_index

    @property
    def step_limit(self) -> int:
        """The task's step limit for the whole rollout."""
        return self.first_step + self.max_steps
