"""The figure-eight knot: tie a 4_1 knot in the same rope world within 4 + 2 steps.

Success is the knot invariant (determinant 5 and Alexander polynomial -t + 3 - 1/t under both
closures of the open rope, `stages.py`); the stages are the crossing codes on the way; the
scripted expert ties it in 4 steps (`expert.py`); the shipped library and task sets are in
``data/``. How this task was added: docs/tasks.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.tasks.base import PerturbationLevel, StageReading, TaskFiles
from knotlab.core.tasks.registry import register_task

if TYPE_CHECKING:
    from knotlab.core.demos.generation import GenSettings
    from knotlab.core.tasks.figure8.expert import DemoRun
    from knotlab.core.world.sim import RopeWorld

# The overhand knot's two perturbation sizes; their own seeds, so the start sets are new draws.
_LEVELS = MappingProxyType(
    {
        "main": PerturbationLevel("main", rho_m=0.05, seed=3),
        "hard": PerturbationLevel("hard", rho_m=0.10, seed=4),
    }
)


@register_task("figure8")
@dataclass(frozen=True)
class Figure8Task:
    """Tie a figure-eight knot (4_1 under both closures) in at most 4 + 2 steps."""

    name: str = "figure8"
    description: str = "tie a figure-eight knot (4_1 under both closures)"
    expert_steps: int = 4
    step_limit: int = 6
    stage_names: tuple[str, ...] = ("other", "loop", "wrapped", "under_arm", "knot")
    levels: Mapping[str, PerturbationLevel] = field(default_factory=lambda: _LEVELS)
    files: TaskFiles = field(default_factory=lambda: TaskFiles("knotlab.core.tasks.figure8"))
    reference_rates: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))

    def stage(self, nodes_k3: np.ndarray) -> StageReading:
        """Stage from the crossing code: other 0, loop 1, wrapped 2, under the arm 3, knot 4."""
        from knotlab.core.tasks.figure8.stages import Stage, rope_stage

        if not np.all(np.isfinite(nodes_k3)):
            return StageReading(int(Stage.OTHER), "", False)
        stage, code = rope_stage(nodes_k3)
        return StageReading(int(stage), code, stage is Stage.KNOT)

    def is_success(self, nodes_k3: np.ndarray) -> bool:
        """The figure-eight invariant under both closures."""
        from knotlab.core.tasks.figure8.stages import is_figure_eight

        return bool(np.all(np.isfinite(nodes_k3))) and is_figure_eight(nodes_k3)

    def demonstrate(self, world: RopeWorld, settings: GenSettings, seed: int) -> DemoRun:
        """A gently curved start rope and an expert style drawn from ``seed``, then the
        scripted 4-step expert (retries and new loops as ``settings`` allow)."""
        from knotlab.core.tasks.expert_runner import demonstrate_from_seed
        from knotlab.core.tasks.figure8.expert import run_expert, sample_style

        return demonstrate_from_seed(
            world, settings, seed, sample_style=sample_style, run_expert=run_expert
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
    ) -> DemoRun:
        """The expert's nominal style (mirrored: chirality -1) from ``start_nodes_k3``."""
        from knotlab.core.tasks.figure8.expert import Figure8Style, run_expert

        style = Figure8Style(chirality=-1 if mirrored else 1)
        return run_expert(
            world,
            start_nodes_k3,
            style,
            seed=seed,
            max_attempts=max_attempts,
            max_restarts=max_restarts,
        )
