"""A lookahead that re-estimates its model online: plan in the ensemble member that has predicted
the executed steps best so far.

The robust lookahead (`robust.py`) hedges over k models at every decision. This policy instead
learns which of them is the world: member 0 is the agent's own model world (the step context's),
members 1..k-1 copies with every physical factor scaled by a seeded draw within +-``spread``
(the same draws as the robust lookahead's, `mismatch.perturb_params`). After choosing a demo it
executes that demo in every member from the same state (k executions, no search): each member's
*prediction* of the rope after the step. At the next decision of the episode the observed rope
(the agent's estimate of it) is compared with each prediction (mean node distance, mm) and the
error is added to the member's running total; the plain lookahead then plans in the member with
the lowest total (ties: the lower member, so member 0 first). Step 0 of an episode starts the
totals afresh.

With the agent's model equal to the world and a perfect estimate, member 0 predicts every step
exactly (error 0), so this policy makes the plain lookahead's choices, bit for bit. A decision
costs one lookahead plus k - 1 executions (member 0's prediction is the search's own when it
planned there); the robust lookahead costs k lookaheads. A member's simulated outcome is never
handed back: the world executes the choice.
Shape suffix: a = demos (actions), k = rope nodes, m = members.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.execution.memo import execute_with_memo
from knotlab.core.selection.decision import Decision, Policy, StepContext
from knotlab.core.selection.ensemble import EnsembleWorlds
from knotlab.core.selection.lookahead import LookaheadPolicy
from knotlab.core.selection.qmodel import QModel

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.protocol import World
    from knotlab.core.world.sim import RopeWorld


@dataclass(frozen=True)
class _Prediction:
    """What each member predicted the rope to be after the step chosen at ``step_index``."""

    step_index: int
    nodes_mk3: list[np.ndarray | None]  # None: the member's execution failed or blew up


def prediction_errors_mm(predicted: list[np.ndarray | None], observed_k3: np.ndarray) -> np.ndarray:
    """Mean node distance (mm) of each member's predicted rope to the observed one (inf where a
    member predicted nothing usable)."""
    from knotlab.core.world.estimate import node_error_mm

    out = np.full(len(predicted), np.inf)
    for m, nodes in enumerate(predicted):
        if nodes is not None and np.all(np.isfinite(nodes)):
            out[m] = node_error_mm(nodes, observed_k3)
    return out


def best_member(totals_m: np.ndarray) -> int:
    """The member with the lowest running error (ties: the lowest index; member 0 first)."""
    finite = np.where(np.isfinite(totals_m), totals_m, np.inf)
    if not np.isfinite(finite).any():
        return 0
    return int(np.argmin(finite))


class AdaptiveLookaheadPolicy(Policy):
    """Beam search over Q in the ensemble member whose predictions matched the world best."""

    def __init__(
        self,
        model: QModel,
        depth: int,
        width: int,
        members: int,
        spread: float = 0.25,
        seed: int = 0,
    ) -> None:
        if members < 2:
            raise ValueError(f"an adaptive lookahead needs at least 2 members, got {members}")
        if not 0 < spread < 1:
            raise ValueError(f"spread must be in (0, 1), got {spread}")
        self.model = model
        self.depth, self.width, self.members = depth, width, members
        self.spread, self.seed = spread, seed
        spread_tag = "" if spread == 0.25 else f"s{round(100 * spread)}"
        self.name = f"ala{depth}x{width}k{members}{spread_tag}"
        self._searches = [LookaheadPolicy(model, depth, width) for _ in range(members)]
        self._ensemble = EnsembleWorlds(members, spread, seed)  # members 1..k-1
        self._totals_m = np.zeros(members)
        self._pending: _Prediction | None = None

    def _member_worlds(self, ctx: StepContext) -> list[RopeWorld]:
        """The worlds of members 1..k-1 for the context's model physics (made once)."""
        return self._ensemble.perturbed(ctx.world)

    def close(self) -> None:
        """Release the members' simulators."""
        self._ensemble.close()

    def _update(self, ctx: StepContext) -> np.ndarray:
        """Score the last step's predictions against the rope now observed; the errors (mm)."""
        pending, self._pending = self._pending, None
        if ctx.step_index == 0 or pending is None or pending.step_index != ctx.step_index - 1:
            self._totals_m = np.zeros(self.members)  # a new episode (or a state out of turn)
            return np.zeros(self.members)
        errors = prediction_errors_mm(pending.nodes_mk3, ctx.world.rope_nodes())
        self._totals_m = self._totals_m + errors
        return errors

    def choose(self, ctx: StepContext) -> Decision:
        """Update the members' running errors, plan in the best one, predict with every one."""
        from knotlab.core.world.estimate import RopeEstimate, place_estimate

        t0 = time.perf_counter()
        errors = self._update(ctx)
        m = best_member(self._totals_m)
        root = ctx.world.snapshot()
        estimate = RopeEstimate(ctx.world.rope_nodes(), root)
        worlds: list[World] = [ctx.world, *self._member_worlds(ctx)]
        planner = worlds[m]
        if m > 0:
            place_estimate(planner, estimate)
        own = m == 0  # the shared memo and the anytime reports are the agent's model's
        plan_ctx = replace(
            ctx,
            world=planner,
            memo=ctx.memo if own else None,
            on_level=ctx.on_level if own else None,
        )
        decision = self._searches[m].choose(plan_ctx)
        t_search = time.perf_counter() - t0
        predicted: list[np.ndarray | None] = []
        for i, world in enumerate(worlds):
            if i == 0:
                world.restore(root)
            else:
                place_estimate(world, estimate)
            if i == m and decision.outcome is not None:
                after = decision.outcome  # the search simulated the choice in this member
            else:  # member 0's through the shared memo: the bench may have simulated it
                memo = ctx.memo if i == 0 else None
                after = execute_with_memo(
                    memo, world, ctx.transferer, ctx.cloud_n3, decision.action
                )
            usable = not after.exploded  # a failed plan moves nothing, in any member
            predicted.append(np.array(after.nodes_after_k3) if usable else None)
        ctx.world.restore(root)
        self._pending = _Prediction(ctx.step_index, predicted)
        info = {
            **decision.info,
            "planned_in": m,
            # None: the member's prediction blew up (JSON has no infinity)
            "member_errors_mm": [float(e) if np.isfinite(e) else None for e in errors],
            "member_totals_mm": [float(e) if np.isfinite(e) else None for e in self._totals_m],
            "search_s": t_search,
            "predict_s": time.perf_counter() - t0 - t_search,
        }
        # The planner's own simulated outcome is the world's only when it planned in member 0,
        # the agent's model (as the plain lookahead's is).
        return Decision(
            decision.action, decision.scores_a, info, decision.outcome if m == 0 else None
        )
