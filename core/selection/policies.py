"""Demonstration-selection policies by name: nearest neighbour, greedy Q, lookahead, oracle.

`policy_config(name)` parses a name (nn, greedy, la<D>x<W>, oracle) once; `make_policy` builds the
policy. The interface is in `decision.py`, the lookahead's beam search in `lookahead.py`.
Shape suffix: a = demos (actions).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.execution.memo import execute_with_memo, snapshot_digest
from knotlab.core.selection.decision import Decision, Policy, StepContext
from knotlab.core.selection.lookahead import LookaheadPolicy
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.ranking import demo_scores, rank_order

PolicyKind = Literal["nn", "greedy", "lookahead", "robust", "adaptive", "oracle"]


def _best_of(scores_a: np.ndarray) -> Decision:
    """The top-ranked demo (demo 0 when none is usable: the episode then records the failure)."""
    order = rank_order(scores_a)
    return Decision(int(order[0]) if len(order) else 0, scores_a)


class NearestNeighbourPolicy(Policy):
    """Schulman et al.: the demo with the lowest bidirectional registration cost."""

    name = "nn"

    def choose(self, ctx: StepContext) -> Decision:
        """argmin_a nn_cost(a) (the first of the app's ranking without a model)."""
        return _best_of(demo_scores(ctx.scan, None, None))


class GreedyPolicy(Policy):
    """argmax_a Q(s, a) of a learned model."""

    name = "greedy"

    def __init__(self, model: QModel) -> None:
        self.model = model

    def choose(self, ctx: StepContext) -> Decision:
        """argmax_a Q(s, a) over usable demos: the first of the app's ranking (one code path)."""
        return _best_of(demo_scores(ctx.scan, ctx.phi_ad, self.model))


class SimulationOraclePolicy(Policy):
    """The library's ceiling estimate: try the ``width`` lowest-cost demos in simulation.

    Keeps the candidate reaching the highest topological stage (ties: lower registration cost),
    stopping at the first knot (docs/reference/policies.md, 'Simulation oracle'). Uses the knot
    stage, so it is task-specific: a yardstick, never a feature.
    """

    name = "oracle"

    def __init__(self, width: int = 10) -> None:
        self.width = width

    def choose(self, ctx: StepContext) -> Decision:
        """Simulate the top-``width`` demos by cost; keep the best stage."""
        world = ctx.world
        root = world.snapshot()
        cost = np.where(ctx.scan.ok_a, ctx.scan.nn_cost_a, np.inf)
        order = [
            int(a) for a in np.argsort(cost, kind="stable")[: self.width] if np.isfinite(cost[a])
        ]
        best: tuple[int, int, ActionOutcome] | None = None  # (stage, -rank, outcome)
        stages = {}
        root_key = snapshot_digest(root) if ctx.memo is not None else None
        t0 = time.perf_counter()
        try:
            for rank, a in enumerate(order):
                world.restore(root)
                outcome = execute_with_memo(
                    ctx.memo, world, ctx.transferer, ctx.cloud_n3, a, root_key
                )
                stage = -1 if outcome.exploded else outcome.stage
                stages[a] = stage
                if best is None or stage > best[0]:
                    best = (stage, rank, outcome)
                if outcome.knot:
                    break
        finally:
            world.restore(root)
        scores = np.full(cost.shape, -np.inf)
        for a, s in stages.items():
            scores[a] = s
        info = {"expansions": len(stages), "search_s": time.perf_counter() - t0}
        if best is None:
            return Decision(int(np.argmin(cost)), scores, info)
        return Decision(best[2].plan.demo_index, scores, info, best[2])


@dataclass(frozen=True)
class PolicyConfig:
    """A policy name parsed once: what it needs and what it costs (the CLI, bench and app)."""

    name: str
    kind: PolicyKind
    needs_model: bool  # ranks demos with a learned QModel
    simulates: bool  # simulates candidates at every step (slow: lookahead, oracle)
    depth: int = 0
    width: int = 0
    members: int = 0  # robust or adaptive lookahead: models in the ensemble
    aggregate: str = ""  # robust lookahead: "mean" or "min" over the members
    spread: float = 0.25  # robust or adaptive lookahead: members' factors drawn within +-spread

    def build(self, model: QModel | None = None) -> Policy:
        """The policy object; a learned one needs ``model``."""
        if self.needs_model and model is None:
            raise InvalidInputError(f"policy {self.name!r} needs a trained QModel")
        if self.kind == "nn":
            return NearestNeighbourPolicy()
        if self.kind == "oracle":
            return SimulationOraclePolicy()
        if self.kind == "greedy":
            return GreedyPolicy(model)
        assert model is not None
        if self.kind == "robust":
            from knotlab.core.selection.robust import RobustLookaheadPolicy

            return RobustLookaheadPolicy(
                model, self.depth, self.width, self.members, self.aggregate, self.spread
            )
        if self.kind == "adaptive":
            from knotlab.core.selection.adaptive import AdaptiveLookaheadPolicy

            return AdaptiveLookaheadPolicy(model, self.depth, self.width, self.members, self.spread)
        return LookaheadPolicy(model, self.depth, self.width)


_LOOKAHEAD_NAME = re.compile(r"la([1-9][0-9]*)x([1-9][0-9]*)")
# s<P>: the members' spread in percent (default 25), e.g. rla2x5k2s50.
_ROBUST_NAME = re.compile(
    r"rla([1-9][0-9]*)x([1-9][0-9]*)k([2-9]|[1-9][0-9]+)(min)?(?:s([1-9][0-9]?))?"
)
_ADAPTIVE_NAME = re.compile(
    r"ala([1-9][0-9]*)x([1-9][0-9]*)k([2-9]|[1-9][0-9]+)(?:s([1-9][0-9]?))?"
)


def _spread(percent: str | None) -> float:
    return 0.25 if percent is None else int(percent) / 100


_FIXED_POLICIES = {
    "nn": PolicyConfig("nn", "nn", needs_model=False, simulates=False),
    "greedy": PolicyConfig("greedy", "greedy", needs_model=True, simulates=False),
    "oracle": PolicyConfig("oracle", "oracle", needs_model=False, simulates=True),
}


def policy_config(name: str) -> PolicyConfig:
    """The config of a policy name: nn, greedy, la<depth>x<width> (e.g. la2x5), the robust
    lookahead rla<depth>x<width>k<members>[min][s<spread %>] (e.g. rla2x5k2, rla2x5k2s50), the
    adaptive lookahead ala<depth>x<width>k<members>[s<spread %>] (e.g. ala2x5k4) or oracle."""
    if name in _FIXED_POLICIES:
        return _FIXED_POLICIES[name]
    adaptive = _ADAPTIVE_NAME.fullmatch(name)
    if adaptive is not None:
        depth, width, members = (int(adaptive.group(i)) for i in (1, 2, 3))
        spread = _spread(adaptive.group(4))
        return PolicyConfig(name, "adaptive", True, True, depth, width, members, spread=spread)
    robust = _ROBUST_NAME.fullmatch(name)
    if robust is not None:
        depth, width, members = (int(robust.group(i)) for i in (1, 2, 3))
        aggregate = "min" if robust.group(4) else "mean"
        spread = _spread(robust.group(5))
        return PolicyConfig(
            name, "robust", True, True, depth, width, members, aggregate, spread=spread
        )
    match = _LOOKAHEAD_NAME.fullmatch(name)
    if match is None:
        raise InvalidInputError(
            f"unknown policy {name!r}; expected nn, greedy, la<D>x<W> (e.g. la2x5), "
            "rla<D>x<W>k<K>[min][s<P>] (e.g. rla2x5k2), ala<D>x<W>k<K>[s<P>] (e.g. ala2x5k4) "
            "or oracle"
        )
    depth, width = int(match.group(1)), int(match.group(2))
    return PolicyConfig(name, "lookahead", True, True, depth, width)


def make_policy(name: str, model: QModel | None = None) -> Policy:
    """Policy by bench name: nn, greedy, la<depth>x<width>, oracle."""
    return policy_config(name).build(model)
