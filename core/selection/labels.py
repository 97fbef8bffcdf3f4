"""Labelled executions: the one record format shared by oracle labels and human (web app) labels.

An *execution* is an expert-guided run from one start state: the sequence of states the expert
saw and the demo it chose in each, plus any dead-end states it met on the way. The learner turns
consecutive steps into Bellman constraints, each chosen demo into margin constraints, the step
that produced a knot into a goal constraint and every dead end into a value bound.
Shape suffixes: n = cloud points, k = rope nodes, c = candidates shown.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from knotlab.core.arrays import optional_points_n3, points_n3
from knotlab.core.errors import InvalidInputError
from knotlab.core.outcomes import STEP_OUTCOMES, StepOutcome

OUTCOMES: tuple[str, ...] = STEP_OUTCOMES  # the stored strings, in StepOutcome order
# Execution metadata: how the execution's first state was reached when a policy's rollout led
# there (policy, model, start task and rope hash, step, demos chosen before); absent when the
# execution begins at its task's start.
REACHED_BY = "reached_by"
LabelSource = Literal["oracle", "human"]


@dataclass(frozen=True, eq=False)
class LabelledStep:
    """One expert decision: the state seen, the demo chosen and what executing it did."""

    step_index: int
    cloud_n3: np.ndarray  # observed cloud before the step (what features are computed from)
    chosen_demo: str  # stable DemoLibrary key, e.g. "s012-t1"
    outcome: StepOutcome  # (a stored string is read as its member)
    rope_nodes_k3: np.ndarray | None = None  # simulator state, when known
    candidates: tuple[str, ...] = ()  # demo keys shown to the expert, in display order
    candidate_scores_c: np.ndarray | None = None  # scores shown (Q or registration cost)
    model_version: str | None = None  # model that ranked the candidates, if any

    def __post_init__(self) -> None:
        if self.step_index < 0:
            raise InvalidInputError(f"step_index must be >= 0, got {self.step_index}")
        if self.outcome not in OUTCOMES:
            raise InvalidInputError(f"outcome must be one of {OUTCOMES}, got {self.outcome!r}")
        object.__setattr__(self, "outcome", StepOutcome(self.outcome))
        if not isinstance(self.chosen_demo, str) or not self.chosen_demo:
            raise InvalidInputError("chosen_demo must be a non-empty demo key")
        object.__setattr__(self, "cloud_n3", points_n3("cloud_n3", self.cloud_n3))
        object.__setattr__(
            self, "rope_nodes_k3", optional_points_n3("rope_nodes_k3", self.rope_nodes_k3)
        )
        object.__setattr__(self, "candidates", tuple(self.candidates))
        if self.candidate_scores_c is not None:
            scores = np.asarray(self.candidate_scores_c, dtype=float)
            if scores.shape != (len(self.candidates),):
                raise InvalidInputError(
                    f"candidate_scores_c must have shape ({len(self.candidates)},), "
                    f"got {scores.shape}"
                )
            object.__setattr__(self, "candidate_scores_c", scores)


@dataclass(frozen=True, eq=False)
class DeadEndState:
    """A state from which the expert judged a knot can no longer be tied in time."""

    cloud_n3: np.ndarray
    rope_nodes_k3: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "cloud_n3", points_n3("cloud_n3", self.cloud_n3))
        object.__setattr__(
            self, "rope_nodes_k3", optional_points_n3("rope_nodes_k3", self.rope_nodes_k3)
        )


@dataclass(frozen=True, eq=False)
class LabelledExecution:
    """An expert-guided execution from one start: ordered steps plus dead ends met on the way."""

    execution_id: str
    source: LabelSource
    labeller: str
    steps: tuple[LabelledStep, ...]
    ended_in_knot: bool
    dead_ends: tuple[DeadEndState, ...] = ()
    task_id: str | None = None
    library_hash: str | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.source not in ("oracle", "human"):
            raise InvalidInputError(f"source must be 'oracle' or 'human', got {self.source!r}")
        steps = tuple(self.steps)
        for i, step in enumerate(steps):
            if step.step_index != i:
                raise InvalidInputError(
                    f"execution {self.execution_id!r}: step {i} has step_index {step.step_index}"
                )
        if self.ended_in_knot and (not steps or steps[-1].outcome != StepOutcome.KNOT):
            raise InvalidInputError(
                f"execution {self.execution_id!r} ended_in_knot but its last step is not a knot"
            )
        object.__setattr__(self, "steps", steps)
        object.__setattr__(self, "dead_ends", tuple(self.dead_ends))
