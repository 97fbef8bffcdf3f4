"""The overhand knot: tie a trefoil in the rope within 5 steps (the paper's task).

Success is the knot invariant (a trefoil when the open rope is closed far above and far below,
`core/world/knot.py`); the stages are the crossing codes on the way (`stages.py`); the scripted
expert ties it in 3 steps (`expert.py`); the shipped library, default model and task sets are in
``data/``.
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
    from knotlab.core.tasks.overhand.expert import DemoRun
    from knotlab.core.world.sim import RopeWorld

_LEVELS = MappingProxyType(
    {
        "main": PerturbationLevel("main", rho_m=0.05, seed=1),
        "hard": PerturbationLevel("hard", rho_m=0.10, seed=2),
    }
)

# The paper's Table I (success within 5 steps): what reports show beside ours.
_PAPER_TABLE1 = MappingProxyType({"nn": 0.688, "greedy": 0.856, "la1x10": 0.936, "la2x5": 0.952})


@register_task("overhand")
@dataclass(frozen=True)
class OverhandTask:
    """Tie an overhand knot (trefoil under both closures) in at most 3 + 2 steps."""

    name: str = "overhand"
    description: str = "tie an overhand knot (a trefoil under both closures)"
    expert_steps: int = 3
    step_limit: int = 5
    stage_names: tuple[str, ...] = ("other", "loop", "over_tail", "knot")
    levels: Mapping[str, PerturbationLevel] = field(default_factory=lambda: _LEVELS)
    files: TaskFiles = field(default_factory=lambda: TaskFiles("knotlab.core.tasks.overhand"))
    reference_rates: Mapping[str, float] = field(default_factory=lambda: _PAPER_TABLE1)

    def stage(self, nodes_k3: np.ndarray) -> StageReading:
        """Stage from the crossing code: other 0, loop 1, loop over tail 2, knot 3."""
        from knotlab.core.tasks.overhand.stages import Stage, rope_stage

        if not np.all(np.isfinite(nodes_k3)):
            return StageReading(int(Stage.OTHER), "", False)
        stage, code = rope_stage(nodes_k3)
        return StageReading(int(stage), code, stage is Stage.KNOT)

    def is_success(self, nodes_k3: np.ndarray) -> bool:
        """The trefoil invariant under both closures."""
        from knotlab.core.world.knot import is_overhand_knot

        return bool(np.all(np.isfinite(nodes_k3))) and is_overhand_knot(nodes_k3)

    def demonstrate(self, world: RopeWorld, settings: GenSettings, seed: int) -> DemoRun:
        """A gently curved start rope and an expert style drawn from ``seed``, then the
        scripted 3-step expert (retries and new loops as ``settings`` allow)."""
        from knotlab.core.tasks.expert_runner import demonstrate_from_seed
        from knotlab.core.tasks.overhand.expert import run_expert, sample_style

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
        from knotlab.core.tasks.overhand.expert import ExpertStyle, run_expert

        style = ExpertStyle(chirality=-1 if mirrored else 1)
        return run_expert(
            world,
            start_nodes_k3,
            style,
            seed=seed,
            max_attempts=max_attempts,
            max_restarts=max_restarts,
        )
