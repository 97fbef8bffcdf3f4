"""Topological progress stage of the rope toward an overhand knot, from its crossing code.

Stages (docs/reference/knot_and_stages.md, "Stage codes"): 3 = overhand knot (trefoil under both
closures); 2 = the loop's side laid over the tail, code U0 O1 O0 U1; 1 = a single loop, code U0 O0
read from the end that was not laid; 0 = anything else. Codes are compared in a direction-free
canonical form (the lexicographic minimum of the code read from either end), so the stage does not
depend on which end the rope's node list starts at. Used by the simulation oracle and failure
analysis only: learned features never see it (they must stay task-independent).
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from knotlab.core.world.knot import analyse_knot, canonical_code


class Stage(IntEnum):
    """Progress toward the overhand knot; ordered, so ``a > b`` means "further along"."""

    OTHER = 0
    LOOP = 1  # a single loop, code U0 O0
    OVER_TAIL = 2  # the loop's side over the tail, code U0 O1 O0 U1
    KNOT = 3  # an overhand knot (trefoil under both closures)

    @property
    def label(self) -> str:
        """Lower-case name for tables and logs (other, loop, over_tail, knot)."""
        return self.name.lower()


STAGE_NAMES: tuple[str, ...] = tuple(s.label for s in Stage)


_STAGE_BY_CODE = {
    canonical_code("U0 O0"): Stage.LOOP,
    canonical_code("U0 O1 O0 U1"): Stage.OVER_TAIL,
}


def stage_of_code(code: str, is_knot: bool) -> Stage:
    """The stage of a crossing code and the knot test's verdict."""
    if is_knot:
        return Stage.KNOT
    return _STAGE_BY_CODE.get(canonical_code(code), Stage.OTHER)


def rope_stage(rope_nodes_k3: np.ndarray) -> tuple[Stage, str]:
    """(stage, crossing code) of a rope."""
    analysis = analyse_knot(rope_nodes_k3)
    return stage_of_code(analysis.gauss_code, analysis.is_overhand), analysis.gauss_code
