"""Topological progress of the rope toward a figure-eight knot, from its crossing code.

Stages (docs/tasks.md, "The figure-eight knot"): 4 = figure-eight knot (the knot invariant under
both closures); 3 = the loop's first arm laid over the wrapped tail, code U0 O1 U2 O0 O2 U1;
2 = the tail wrapped over the run below the loop, code O0 U1 O1 U0; 1 = a single loop, U0 O0;
0 = anything else. Codes are compared in the direction-free canonical form, as the overhand
task's are. Used by the oracle and failure analysis only: learned features never see it.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from knotlab.core.world.knot import (
    KnotAnalysis,
    alexander_polynomial,
    analyse_knot,
    canonical_code,
)

# Delta(t) = -t + 3 - 1/t, normalised as `alexander_polynomial` returns it.
FIGURE_EIGHT_POLYNOMIAL: tuple[int, ...] = (1, -3, 1)
FIGURE_EIGHT_DETERMINANT = 5


class Stage(IntEnum):
    """Progress toward the figure-eight knot; ordered, so ``a > b`` means "further along"."""

    OTHER = 0
    LOOP = 1  # a single loop, code U0 O0
    WRAPPED = 2  # the end beyond the loop laid over the run, code O0 U1 O1 U0
    UNDER_ARM = 3  # the loop's first arm over the wrapped end, code U0 O1 U2 O0 O2 U1
    KNOT = 4  # a figure-eight knot under both closures

    @property
    def label(self) -> str:
        """Lower-case name for tables and logs."""
        return self.name.lower()


STAGE_NAMES: tuple[str, ...] = tuple(s.label for s in Stage)
# Gauss code of the open rope expected after each of the expert's first three steps.
STAGE_CODES: tuple[str, ...] = ("U0 O0", "O0 U1 O1 U0", "U0 O1 U2 O0 O2 U1")
_STAGE_BY_CODE = {canonical_code(code): Stage(i + 1) for i, code in enumerate(STAGE_CODES)}


def is_figure_eight_analysis(rope_nodes_k3: np.ndarray, analysis: KnotAnalysis) -> bool:
    """True when both closures are the figure-eight knot: determinant 5, then (only then, it
    costs more) the whole Alexander polynomial -t + 3 - 1/t under each closure."""
    if analysis.determinants != (FIGURE_EIGHT_DETERMINANT, FIGURE_EIGHT_DETERMINANT):
        return False
    if analysis.alexander_values != (1, 1):  # |Delta(2)| = 1/2: odd part 1
        return False
    return all(
        alexander_polynomial(rope_nodes_k3, above=above) == FIGURE_EIGHT_POLYNOMIAL
        for above in (True, False)
    )


def is_figure_eight(rope_nodes_k3: np.ndarray) -> bool:
    """True if the open rope, closed far above and far below, is a figure-eight knot both ways."""
    return is_figure_eight_analysis(rope_nodes_k3, analyse_knot(rope_nodes_k3))


def stage_of(code: str, is_knot: bool) -> Stage:
    """The stage of a crossing code and the knot test's verdict."""
    if is_knot:
        return Stage.KNOT
    return _STAGE_BY_CODE.get(canonical_code(code), Stage.OTHER)


def rope_stage(rope_nodes_k3: np.ndarray) -> tuple[Stage, str]:
    """(stage, crossing code) of a rope."""
    analysis = analyse_knot(rope_nodes_k3)
    knot = is_figure_eight_analysis(rope_nodes_k3, analysis)
    return stage_of(analysis.gauss_code, knot), analysis.gauss_code
