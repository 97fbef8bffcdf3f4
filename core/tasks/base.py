"""What makes a task a task: the `Task` protocol and the records it hands out.

Everything task specific sits behind this protocol: the success test, the stage function and its
stage names, the scripted expert, the step limit, the perturbation levels of its start sets and
the files it ships. The rest of core (registration, features, policies, episodes) is
task-independent and reaches the task only through it.
Shape suffix: k = rope nodes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Protocol, runtime_checkable

import numpy as np

from knotlab.core.errors import InvalidInputError

if TYPE_CHECKING:  # the expert drives the simulator: only for the checker
    from knotlab.core.demos.generation import GenSettings
    from knotlab.core.demos.tasks import TaskSet
    from knotlab.core.world.sim import RopeWorld
    from knotlab.core.world.trajectory import GripperTrajectory

Split = Literal["train", "test"]


@dataclass(frozen=True)
class StageReading:
    """The rope's progress toward the task's goal: a stage number (higher = further), the
    crossing code it was read from, and whether the goal (the knot) is reached."""

    stage: int
    code: str
    success: bool


@dataclass(frozen=True)
class PerturbationLevel:
    """A named start-state distribution: demo starts perturbed by a tent field of size ``rho``."""

    name: str
    rho_m: float
    seed: int
    n_centres: int = 7


@dataclass(frozen=True)
class TaskFiles:
    """The files a task ships, as names inside its package's ``data`` folder."""

    package: str  # the task's Python package, e.g. knotlab.core.tasks.overhand
    library: str = "demos_default.npz"
    model: str = "model_default.npz"
    task_set_pattern: str = "tasks_{level}_{split}.npz"
    # Start scans are per CPU kind: the app uses a summary only where it has the bits a scan
    # on this machine would give (core.machine.vector_width names the kind).
    scans_pattern: str = "scans_{level}_{split}_{kind}.npz"

    def path(self, name: str) -> Path:
        """A shipped file's path on disk (installed as package data, read through
        importlib.resources, so a non-editable install finds it too)."""
        ref = resources.files(self.package).joinpath("data", name)
        return Path(str(ref))

    @property
    def library_path(self) -> Path:
        """The shipped demonstration library."""
        return self.path(self.library)

    @property
    def model_path(self) -> Path:
        """The shipped default Q-model."""
        return self.path(self.model)

    def task_set_path(self, level: str, split: str) -> Path:
        """The shipped task set of one perturbation level and split."""
        return self.path(self.task_set_pattern.format(level=level, split=split))

    def scans_path(self, level: str, split: str, kind: str | None = None) -> Path:
        """Precomputed library-scan summaries of a task set's start clouds, made on CPUs of
        ``kind`` (default: this machine's; may be absent)."""
        from knotlab.core.machine import vector_width

        kind = (kind or vector_width()).replace(" ", "_")
        return self.path(self.scans_pattern.format(level=level, split=split, kind=kind))

    def load_task_set(self, level: str, split: str) -> TaskSet:
        """The shipped start ropes of one level and split (e.g. main, test)."""
        from knotlab.core.demos.tasks import TaskSet

        return TaskSet.load(self.task_set_path(level, split))


@runtime_checkable
class Task(Protocol):
    """A rope-manipulation task: its goal, progress, expert, limits and shipped files."""

    name: str
    description: str
    step_limit: int  # steps an episode may take: the expert's usual count + 2
    expert_steps: int  # steps the scripted expert takes
    stage_names: tuple[str, ...]  # index = stage number
    levels: Mapping[str, PerturbationLevel]
    files: TaskFiles
    # Published success rates of policies on this task, by policy name (the paper's Table I for
    # the overhand knot); empty when there are none. Reports draw them beside ours.
    reference_rates: Mapping[str, float]

    def stage(self, nodes_k3: np.ndarray) -> StageReading:
        """The rope's stage (and whether the goal is reached) from its node positions."""
        ...

    def is_success(self, nodes_k3: np.ndarray) -> bool:
        """True when the rope is in the goal configuration (a real knot, by its invariant)."""
        ...

    def demonstrate(self, world: RopeWorld, settings: GenSettings, seed: int) -> ExpertRun:
        """Draw a start rope and an expert style from ``seed`` and run the scripted expert."""
        ...

    def run_expert(
        self,
        world: RopeWorld,
        start_nodes_k3: np.ndarray,
        *,
        mirrored: bool,
        seed: int,
        max_attempts: int,
        max_restarts: int,
    ) -> ExpertRun:
        """The scripted expert with its nominal style (or that style's mirror image) from a
        given start rope; ``seed`` seeds its retries."""
        ...


class ExpertStep(Protocol):
    """One accepted expert step: the rope before and after and the trajectory between."""

    step_index: int
    pre_nodes_k3: np.ndarray
    trajectory: GripperTrajectory
    post_nodes_k3: np.ndarray
    code: str
    attempts: int
    style: _Style


class ExpertRun(Protocol):
    """A scripted expert's attempt at the task from one start rope."""

    start_nodes_k3: np.ndarray
    steps: Sequence[ExpertStep]
    knotted: bool  # the goal was reached
    failed_step: int | None
    wall_time: float
    restarts: int
    failures_by_step: tuple[int, ...]  # rejected tries of each step
    style: _Style


class _Style(Protocol):
    def to_dict(self) -> dict[str, object]:
        """The style as JSON-able numbers (stored with each demo)."""
        ...


def level_of(task: Task, level: str) -> PerturbationLevel:
    """The named perturbation level of ``task``; a one-line error names the known ones."""
    try:
        return task.levels[level]
    except KeyError:
        known = ", ".join(task.levels)
        raise InvalidInputError(
            f"task {task.name!r} has no perturbation level {level!r}; known: {known}"
        ) from None


def check_task_of(kind: str, recorded: object, task: Task) -> None:
    """Refuse a file made for another task (files without a task record are the overhand
    knot's: they were made before a second task could exist)."""
    name = DEFAULT_TASK if recorded is None else str(recorded)
    if name != task.name:
        raise InvalidInputError(
            f"the {kind} was made for task {name!r}, not {task.name!r}: use the {task.name} "
            f"task's {kind} or pass --task {name}"
        )


DEFAULT_TASK = "overhand"
