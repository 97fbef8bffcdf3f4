"""A lookahead that plans for its own model error: the beam search run in an ensemble of models.

Member 0 is the agent's own model world (the step context's); members 1..k-1 are copies of it
with every physical factor scaled by a seeded draw within +-``spread`` (`mismatch.perturb_params`),
each placed in the same state (`estimate.place_estimate`). Each member runs the plain lookahead
(`LookaheadPolicy`) from that state. A root action's value is then:

1. how many members reached the goal with it (more is better), then
2. the members' backed-up values of it, each at that member's deepest level, aggregated by the
   ``mean`` or by the ``min`` (the worst member: a lower quantile at k <= 4),
   over the members that valued it, provided at least half of them did.

Ties go to member 0's root Q. The members' worlds are the policy's own (made on first use, kept),
so a decision costs k lookaheads: k = 2 is twice the plain lookahead's time. The chosen action's
simulated outcome is never handed back: which member's would it be? The world executes it.
Shape suffix: a = demos (actions).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.selection.decision import Decision, Policy, StepContext
from knotlab.core.selection.ensemble import EnsembleWorlds
from knotlab.core.selection.lookahead import LookaheadPolicy
from knotlab.core.selection.qmodel import QModel

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.sim import RopeWorld

AGGREGATES = ("mean", "min")


class RobustLookaheadPolicy(Policy):
    """Beam search over Q in k models of the world at once; the action robust across them."""

    def __init__(
        self,
        model: QModel,
        depth: int,
        width: int,
        members: int,
        aggregate: str = "mean",
        spread: float = 0.25,
        seed: int = 0,
    ) -> None:
        if members < 2:
            raise ValueError(f"a robust lookahead needs at least 2 members, got {members}")
        if aggregate not in AGGREGATES:
            raise ValueError(f"aggregate must be one of {AGGREGATES}, got {aggregate!r}")
        if not 0 < spread < 1:
            raise ValueError(f"spread must be in (0, 1), got {spread}")
        self.model = model
        self.depth, self.width, self.members = depth, width, members
        self.aggregate, self.spread, self.seed = aggregate, spread, seed
        suffix = "" if aggregate == "mean" else aggregate
        spread_tag = "" if spread == 0.25 else f"s{round(100 * spread)}"
        self.name = f"rla{depth}x{width}k{members}{suffix}{spread_tag}"
        self._searches = [LookaheadPolicy(model, depth, width) for _ in range(members)]
        self._ensemble = EnsembleWorlds(members, spread, seed)  # members 1..k-1

    def _member_worlds(self, ctx: StepContext) -> list[RopeWorld]:
        """The worlds of members 1..k-1 for the context's model physics (made once)."""
        return self._ensemble.perturbed(ctx.world)

    def close(self) -> None:
        """Release the members' simulators."""
        self._ensemble.close()

    def choose(self, ctx: StepContext) -> Decision:
        """Run the lookahead in every member from the context's state; aggregate per action."""
        from knotlab.core.world.estimate import RopeEstimate, place_estimate

        t0 = time.perf_counter()
        root = ctx.world.snapshot()
        estimate = RopeEstimate(ctx.world.rope_nodes(), root)
        worlds = [ctx.world, *self._member_worlds(ctx)]
        decisions = []
        for m, (world, search) in enumerate(zip(worlds, self._searches, strict=True)):
            if m > 0:
                place_estimate(world, estimate)
            member_ctx = replace(ctx, world=world, memo=None, on_level=None)
            decisions.append(search.choose(member_ctx))
        ctx.world.restore(root)
        return self._aggregate(decisions, t0)

    def _aggregate(self, decisions: list[Decision], t0: float) -> Decision:
        """The action most members reach the goal with, then the best aggregated value."""
        goals: dict[int, int] = {}
        values: dict[int, list[float]] = {}
        for d in decisions:
            if d.info.get("goal_found"):
                goals[d.action] = goals.get(d.action, 0) + 1
                continue
            backed = d.info.get("backed_up", {})
            deepest = max((depth for depth, _ in backed.values()), default=0)
            for a, (depth, value) in backed.items():
                if depth == deepest and math.isfinite(value):
                    values.setdefault(int(a), []).append(float(value))
        need = math.ceil(len(decisions) / 2)
        agg = np.mean if self.aggregate == "mean" else np.min
        pooled = {a: float(agg(v)) for a, v in values.items() if len(v) >= need}
        root_q = decisions[0].scores_a  # member 0's scores: its root Q where nothing was backed up
        candidates = set(goals) | set(pooled)
        if candidates:
            action = max(
                candidates,
                key=lambda a: (goals.get(a, 0), pooled.get(a, -math.inf), root_q[a]),
            )
        else:
            action = decisions[0].action
        scores = np.array(root_q, dtype=float)
        for a, v in pooled.items():
            scores[a] = v
        for a in goals:
            scores[a] = math.inf
        info = {
            "expansions": sum(int(d.info.get("expansions", 0)) for d in decisions),
            "search_s": time.perf_counter() - t0,
            "goal_found": bool(goals),
            "members": [
                {"action": int(d.action), "goal": bool(d.info.get("goal_found"))} for d in decisions
            ],
            "goal_votes": {int(a): n for a, n in goals.items()},
            "pooled": {int(a): v for a, v in pooled.items()},
        }
        return Decision(int(action), scores, info, None)
