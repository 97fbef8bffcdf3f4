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

from knotlab.core.tasks.base import PerturbationLevel, TaskFiles
from knotlab.core.tasks.knot_task import KnotTaskMethods, KnotTaskParts
from knotlab.core.tasks.registry import register_task

# The overhand knot's two perturbation sizes; their own seeds, so the start sets are new draws.
_LEVELS = MappingProxyType(
    {
        "main": PerturbationLevel("main", rho_m=0.05, seed=3),
        "hard": PerturbationLevel("hard", rho_m=0.10, seed=4),
    }
)


@register_task("figure8")
@dataclass(frozen=True)
class Figure8Task(KnotTaskMethods):
    """Tie a figure-eight knot (4_1 under both closures) in at most 4 + 2 steps."""

    name: str = "figure8"
    description: str = "tie a figure-eight knot (4_1 under both closures)"
    expert_steps: int = 4
    step_limit: int = 6
    stage_names: tuple[str, ...] = ("other", "loop", "wrapped", "under_arm", "knot")
    levels: Mapping[str, PerturbationLevel] = field(default_factory=lambda: _LEVELS)
    files: TaskFiles = field(default_factory=lambda: TaskFiles("knotlab.core.tasks.figure8"))
    reference_rates: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))

    def parts(self) -> KnotTaskParts:
        """Its stages (`stages.py`), its knot invariant and its scripted expert (`expert.py`)."""
        from knotlab.core.tasks.figure8 import expert, stages

        return KnotTaskParts(
            stages.Stage,
            stages.rope_stage,
            stages.is_figure_eight,
            expert.Figure8Style,
            expert.sample_style,
            expert.run_expert,
        )
