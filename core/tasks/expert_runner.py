"""Running a scripted expert: steps checked by the task's stage, retries and new starts.

Every task's expert plans its steps from the rope it observes; this module runs them the same
way for all: each step starts from ``world.reset(pre_nodes)`` (the read-back rope of the step
before, at rest), so every recorded step replays bit for bit; after each step the task's
``judge`` says whether the rope reached the expected stage (and may measure a frame the later
steps plan from). A rejected step is retried from the same pre-step state with a jittered style;
when a step's tries run out the expert starts over from the start rope with a jittered first
step, at most ``max_restarts`` times. Only accepted tries are recorded.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Generic, TypeVar

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.seeds import generator
from knotlab.core.world.protocol import World
from knotlab.core.world.trajectory import GripperTrajectory

if TYPE_CHECKING:
    from knotlab.core.demos.generation import GenSettings

StyleT = TypeVar("StyleT")
FrameT = TypeVar("FrameT")


@dataclass(frozen=True, eq=False)
class StepRecord(Generic[StyleT]):
    """One executed (accepted) step: the state it started from and what it did."""

    step_index: int
    pre_nodes_k3: np.ndarray
    trajectory: GripperTrajectory
    post_nodes_k3: np.ndarray
    code: str  # Gauss code after the step
    stage_ok: bool
    attempts: int
    style: StyleT


@dataclass(frozen=True, eq=False)
class DemoRun(Generic[StyleT]):
    """The outcome of one expert demonstration from a start rope."""

    start_nodes_k3: np.ndarray
    style: StyleT
    steps: list[StepRecord[StyleT]] = field(default_factory=list)
    knotted: bool = False
    failed_step: int | None = None  # step whose stage stayed wrong after all retries
    wall_time: float = 0.0
    restarts: int = 0  # times the expert started over from the start rope
    failures_by_step: tuple[int, ...] = ()  # rejected tries of each step


@dataclass(frozen=True)
class Verdict(Generic[FrameT]):
    """A task's judgement of one executed step: the rope's crossing code, whether the step is
    accepted, and the frame later steps plan from (unchanged if the step measures none)."""

    code: str
    accepted: bool
    frame: FrameT | None


@dataclass(frozen=True)
class ScriptedExpert(Generic[StyleT, FrameT]):
    """What a task's expert supplies to be run: its steps' planner and judge, its jitter."""

    n_steps: int
    plan: Callable[[int, np.ndarray, StyleT, FrameT | None], GripperTrajectory]
    judge: Callable[[int, np.ndarray, FrameT | None], Verdict[FrameT]]
    jitter: Callable[[StyleT, np.random.Generator, int], StyleT]
    first_step_tries: int | None = None  # tries of the first step (None: max_attempts)
    rng_stream: int = 7  # the seed stream of the jitters

    def run(
        self,
        world: World,
        start_nodes_k3: np.ndarray,
        style: StyleT,
        *,
        seed: int,
        max_attempts: int,
        max_restarts: int,
    ) -> DemoRun[StyleT]:
        """Run the expert from ``start_nodes_k3`` (see the module docstring)."""
        wall0 = time.perf_counter()
        rng = generator(seed, self.rng_stream)
        world.reset(start_nodes_k3)
        start = world.rope_nodes()
        failed: int | None = None
        records: list[StepRecord[StyleT]] = []
        fails_by_step = [0] * self.n_steps
        restart = 0
        for restart in range(max_restarts):
            loop_style = style if restart == 0 else self.jitter(style, rng, 0)
            records = []
            frame: FrameT | None = None
            nodes = start
            failed = None
            for step in range(self.n_steps):
                tries = max_attempts
                if step == 0 and self.first_step_tries is not None:
                    tries = self.first_step_tries
                accepted = None
                for attempt in range(1, tries + 1):
                    step_style = loop_style if attempt == 1 else self.jitter(loop_style, rng, step)
                    out = self._try(world, step, nodes, step_style, frame)
                    if out is not None:
                        traj, post, verdict = out
                        frame = verdict.frame
                        accepted = StepRecord(
                            step, nodes, traj, post, verdict.code, True, attempt, step_style
                        )
                        break
                    fails_by_step[step] += 1
                if accepted is None:
                    failed = step
                    break
                records.append(accepted)
                nodes = accepted.post_nodes_k3
            if failed is None:
                break
        return DemoRun(
            start_nodes_k3=np.asarray(start_nodes_k3, dtype=float),
            style=style,
            steps=records,
            knotted=failed is None,
            failed_step=failed,
            wall_time=time.perf_counter() - wall0,
            restarts=restart,
            failures_by_step=tuple(fails_by_step),
        )

    def _try(
        self, world: World, step: int, pre: np.ndarray, style: StyleT, frame: FrameT | None
    ) -> tuple[GripperTrajectory, np.ndarray, Verdict[FrameT]] | None:
        """Execute one planned step from ``reset(pre)``; None unless the judge accepts it."""
        world.reset(pre)
        try:
            traj = self.plan(step, pre, style, frame)
        except InvalidInputError:
            return None
        result = world.execute(traj)
        post = world.rope_nodes()
        if not result.ok or not np.all(np.isfinite(post)):
            return None
        verdict = self.judge(step, post, frame)
        return (traj, post, verdict) if verdict.accepted else None


def demonstrate_from_seed(
    world: World,
    settings: GenSettings,
    seed: int,
    *,
    sample_style: Callable[[np.random.Generator, float], StyleT],
    run_expert: Callable[..., DemoRun[StyleT]],
) -> DemoRun[StyleT]:
    """What every task's ``demonstrate`` does: a gently curved start rope, then an expert style,
    both drawn from ``seed`` in that order, then the expert with the settings' retries."""
    from knotlab.core.tasks.expert_moves import sample_start_rope

    rng = np.random.default_rng(seed)
    start = sample_start_rope(
        rng,
        bend_amplitude=settings.bend_amplitude,
        max_rotation=settings.max_rotation,
        max_translation=settings.max_translation,
    )
    style = sample_style(rng, settings.mirror_prob)
    return run_expert(
        world,
        start,
        style,
        seed=seed,
        max_attempts=settings.max_attempts,
        max_restarts=settings.max_restarts,
    )


__all__ = ["DemoRun", "ScriptedExpert", "StepRecord", "Verdict", "demonstrate_from_seed"]
