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

from knotlab.core.tasks.base import PerturbationLevel, TaskFiles
from knotlab.core.tasks.knot_task import KnotTaskMethods, KnotTaskParts
from knotlab.core.tasks.registry import register_task

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
class OverhandTask(KnotTaskMethods):
    """Tie an overhand knot (trefoil under both closures) in at most 3 + 2 steps."""

    name: str = "overhand"
    description: str = "tie an overhand knot (a trefoil under both closures)"
    expert_steps: int = 3
    step_limit: int = 5
    stage_names: tuple[str, ...] = ("other", "loop", "over_tail", "knot")
    levels: Mapping[str, PerturbationLevel] = field(default_factory=lambda: _LEVELS)
    files: TaskFiles = field(default_factory=lambda: TaskFiles("knotlab.core.tasks.overhand"))
    reference_rates: Mapping[str, float] = field(default_factory=lambda: _PAPER_TABLE1)

    def parts(self) -> KnotTaskParts:
        """Its stages (`stages.py`), its knot invariant and its scripted expert (`expert.py`)."""
        from knotlab.core.tasks.overhand import expert, stages
        from knotlab.core.world.knot import is_overhand_knot as is_knot

        return KnotTaskParts(
            stages.Stage,
            stages.rope_stage,
            is_knot,
            expert.ExpertStyle,
            expert.sample_style,
            expert.run_expert,
        )
