"""Rank a state's demos: the one scoring function the greedy policy and the labelling app share.

With a learned model the score is Q(s, a); without one it is the negated registration cost (the
nearest-neighbour baseline). Demos whose registration failed score -inf and are never offered.
Shape suffix: a = demos (actions).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.qmodel import QModel


@dataclass(frozen=True)
class RankedDemo:
    """One offered candidate: its rank (1 = best), which demo, its score and its costs."""

    rank: int
    demo_index: int
    demo_key: str
    score: float  # Q with a model, else -registration cost (higher is better either way)
    q: float | None  # Q(s, a), None when ranked without a model
    nn_cost: float  # bidirectional registration cost (the nearest-neighbour score)


class RegisteredDemos(Protocol):
    """What scoring needs of a scan: each demo's registration cost and whether it registered
    (a `ScanResult`, or its summary)."""

    @property
    def nn_cost_a(self) -> np.ndarray: ...

    @property
    def ok_a(self) -> np.ndarray: ...


def demo_scores(
    scan: RegisteredDemos, phi_ad: np.ndarray | None, model: QModel | None
) -> np.ndarray:
    """Score of every demo (higher = better): Q with a model, else -nn_cost; -inf if unusable."""
    if model is None:
        raw = -np.asarray(scan.nn_cost_a, dtype=float)
    else:
        if phi_ad is None:
            raise InvalidInputError("ranking with a Q-model needs the state's features phi_ad")
        raw = np.asarray(model.q(phi_ad), dtype=float)
    scores = np.where(np.asarray(scan.ok_a, bool), raw, -np.inf)
    scores[~np.isfinite(scores)] = -np.inf
    return scores


def rank_order(scores_a: np.ndarray) -> np.ndarray:
    """Demo indices best first; ties keep the lower index (stable), unusable demos dropped."""
    order = np.argsort(-scores_a, kind="stable")
    return order[np.isfinite(scores_a[order])]


def rank_demos(
    scan: RegisteredDemos,
    phi_ad: np.ndarray | None,
    model: QModel | None,
    keys: tuple[str, ...],
    top_k: int | None = None,
) -> list[RankedDemo]:
    """The best ``top_k`` demos of a state (all usable ones when None), best first."""
    if top_k is not None and top_k < 1:
        raise InvalidInputError(f"top_k must be >= 1, got {top_k}")
    scores = demo_scores(scan, phi_ad, model)
    q_a = scores if model is not None else None
    order = rank_order(scores)[:top_k]
    cost = np.asarray(scan.nn_cost_a, dtype=float)
    return [
        RankedDemo(
            rank=r + 1,
            demo_index=int(a),
            demo_key=keys[a],
            score=float(scores[a]),
            q=None if q_a is None else float(q_a[a]),
            nn_cost=float(cost[a]),
        )
        for r, a in enumerate(order)
    ]
