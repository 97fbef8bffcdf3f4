"""The `Task` methods every knot-tying task writes the same way, given where its parts live.

A knot task reads its stage from the rope's crossing code, tests success by a knot invariant and
runs a scripted expert through `expert_runner`; only the functions differ. A task dataclass
inherits `KnotTaskMethods` and answers `parts()` with those functions, imported there and not at
module import (they import the simulator, which `get_task` must not pay for).
Shape suffix: k = rope nodes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING, Any

import numpy as np

from knotlab.core.tasks.base import StageReading

if TYPE_CHECKING:
    from knotlab.core.demos.generation import GenSettings
    from knotlab.core.tasks.expert_runner import DemoRun
    from knotlab.core.world.sim import RopeWorld


@dataclass(frozen=True)
class KnotTaskParts:
    """A knot task's own functions: its stages, its goal test and its scripted expert.

    ``stage_enum`` must have ``OTHER`` (0) and ``KNOT`` (the goal) members; ``rope_stage`` reads
    (stage, crossing code) from nodes; ``style_class(chirality=...)`` is the expert's nominal
    style; ``sample_style`` and ``run_expert`` are what `expert_runner.demonstrate_from_seed`
    takes."""

    stage_enum: type[IntEnum]
    rope_stage: Callable[[np.ndarray], tuple[IntEnum, str]]
    is_knot: Callable[[np.ndarray], bool]
    style_class: Callable[..., Any]
    sample_style: Callable[[np.random.Generator, float], Any]
    run_expert: Callable[..., DemoRun[Any]]


class KnotTaskMethods:
    """`stage`, `is_success`, `demonstrate` and `run_expert` from a task's `parts()`."""

    def parts(self) -> KnotTaskParts:
        """The task's own functions (imported on first call)."""
        raise NotImplementedError

    def stage(self, nodes_k3: np.ndarray) -> StageReading:
        """The stage of the rope's crossing code (0, no code, for non-finite nodes)."""
        parts = self.parts()
        if not np.all(np.isfinite(nodes_k3)):
            return StageReading(int(parts.stage_enum["OTHER"]), "", False)
        stage, code = parts.rope_stage(nodes_k3)
        return StageReading(int(stage), code, stage is parts.stage_enum["KNOT"])

    def is_success(self, nodes_k3: np.ndarray) -> bool:
        """The task's knot invariant under both closures (never for non-finite nodes)."""
        return bool(np.all(np.isfinite(nodes_k3))) and bool(self.parts().is_knot(nodes_k3))

    def demonstrate(self, world: RopeWorld, settings: GenSettings, seed: int) -> DemoRun[Any]:
        """A gently curved start rope and an expert style drawn from ``seed``, then the
        scripted expert (retries and new loops as ``settings`` allow)."""
        from knotlab.core.tasks.expert_runner import demonstrate_from_seed

        parts = self.parts()
        return demonstrate_from_seed(
            world, settings, seed, sample_style=parts.sample_style, run_expert=parts.run_expert
        )

    def run_expert(
        self,
        world: RopeWorld,
        start_nodes_k3: np.ndarray,
        *,
        mirrored: bool,
        seed: int,
        max_attempts: int,
        max_restarts: int,
    ) -> DemoRun[Any]:
        """The expert's nominal style (mirrored: chirality -1) from ``start_nodes_k3``."""
        parts = self.parts()
        return parts.run_expert(
            world,
            start_nodes_k3,
            parts.style_class(chirality=-1 if mirrored else 1),
            seed=seed,
            max_attempts=max_attempts,
            max_restarts=max_restarts,
        )
