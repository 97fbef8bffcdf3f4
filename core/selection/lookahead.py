"""Lookahead: beam search in simulation over the learned Q (the paper's search policy).

Shape suffix: a = demos (actions).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.arrays import cloud_digest
from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.execution.expansion import (
    ExpansionJob,
    ExpansionResult,
    ExpansionRunner,
    SequentialRunner,
    child_is_valued,
    value_child,
)
from knotlab.core.execution.memo import OutcomeMemo, snapshot_digest
from knotlab.core.selection.decision import Decision, LevelDecision, Policy, StepContext
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.ranking import demo_scores

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.sim import SimSnapshot


@dataclass
class _Node:
    snapshot: SimSnapshot
    cloud_n3: np.ndarray
    q_a: np.ndarray
    root_action: int  # -1 at the root
    keys: tuple[str, str] = ("", "")  # (snapshot digest, cloud digest), for the memo
    tree_id: int = 0  # its entry in the decision's tree (0 = the root)


def _level_candidates(
    q_by_node: list[np.ndarray], width: int, n_open: int
) -> list[tuple[float, int, int]]:
    """Every node's best actions as (Q, node, action), best first; ``n_open`` nodes are open."""
    per_node = width if n_open < 3 else max(1, width // 2)
    candidates = []
    for node_i, q_a in enumerate(q_by_node):
        order = np.argsort(-q_a, kind="stable")[:per_node]
        candidates += [(float(q_a[a]), node_i, int(a)) for a in order if np.isfinite(q_a[a])]
    candidates.sort(key=lambda c: (-c[0], c[1], c[2]))
    return candidates


def beam_level(q_by_node: list[np.ndarray], width: int) -> list[tuple[float, int, int]]:
    """The (Q, node, action) a lookahead level expands: the ``width`` best over the open nodes."""
    return _level_candidates(q_by_node, width, len(q_by_node))[:width]


def certain_members(known_q: list[np.ndarray], unknown: int, width: int) -> list[tuple[int, int]]:
    """(node, action) pairs of the next level whatever ``unknown`` children still to come bring.

    The known children are the first nodes of the next level, in order. Each child still to come
    may open a node whose ``per_node`` candidates all outrank every known one (ties go to the
    lower node, i.e. the known), so a known candidate is certain when it stays within ``width``
    in every case: 0 to ``unknown`` more nodes open, each changing ``per_node``.
    """
    certain: set[tuple[int, int]] | None = None
    for extra in range(unknown + 1):
        n_open = len(known_q) + extra
        per_node = width if n_open < 3 else max(1, width // 2)
        slots = max(width - extra * per_node, 0)
        members = {(i, a) for _, i, a in _level_candidates(known_q, width, n_open)[:slots]}
        certain = members if certain is None else certain & members
    ranked = _level_candidates(known_q, width, len(known_q) + unknown)
    return [(i, a) for _, i, a in ranked if certain and (i, a) in certain]


class LookaheadPolicy(Policy):
    """Beam search in simulation over Q, stopping at the first knot.

    The search follows docs/reference/policies.md, 'Lookahead beam search'.

    Each level expands the ``width`` best (node, action) pairs by Q (each node offering its best
    ``width``, or ``width // 2`` (at least 1) once three or more nodes are open), simulating every
    expansion from the node's snapshot. A knot ends the search at once. Otherwise a child is
    valued V(s') = max_a' Q(s', a'). Back-up (fixing the original, which subtracted max child
    value from less-expanded children and so was only right for positive values): a root action
    is valued by the best child reached at the *deepest* level any branch reached; only root
    actions that reached that level compete, so values of different depths (and signs) are never
    compared. Ties and the no-expansion case fall back to the root's Q. Children of the episode's
    last action are not valued (only a knot counts there), which saves a scan per expansion.

    Where expansions run is the ``runner``'s business (`core.selection.expansion`): in this
    process by default, or a level at a time in worker processes (the app); the choice and the
    outcome are the same either way. Expansions already simulated (`OutcomeMemo`) are reused.
    ``decision.info["tree"]`` lists every expansion: its node, parent, demo, value and stage.
    """

    def __init__(
        self,
        model: QModel,
        depth: int = 1,
        width: int = 10,
        runner: ExpansionRunner | None = None,
    ) -> None:
        if depth < 1 or width < 1:
            raise ValueError(f"lookahead needs depth >= 1 and width >= 1, got {depth}, {width}")
        self.model = model
        self.depth = depth
        self.width = width
        self.name = f"la{depth}x{width}"
        self.runner: ExpansionRunner = runner or SequentialRunner()
        self.memo = OutcomeMemo()

    def _memo(self, ctx: StepContext) -> OutcomeMemo:
        """The step's shared memo if it has one, else this policy's own."""
        return ctx.memo if ctx.memo is not None else self.memo

    def _run_level(
        self,
        ctx: StepContext,
        nodes: list[_Node],
        actions: list[int],
        value: bool,
        early: dict[tuple[int, int], ExpansionJob],
    ) -> Iterator[tuple[ExpansionResult, bool]]:
        """(result, from the memo) per (node, action), in order; misses go to the runner
        (as the job objects handed to it early, where `_prefetch` did)."""
        keys = [
            OutcomeMemo.key(ctx.world, ctx.transferer, *node.keys, a)
            for node, a in zip(nodes, actions, strict=True)
        ]
        memo = self._memo(ctx)
        known = [memo.get(k) for k in keys]
        misses = [
            early.get((node.tree_id, a)) or ExpansionJob(node.snapshot, node.cloud_n3, a, value)
            for node, a, out in zip(nodes, actions, known, strict=True)
            if out is None
        ]
        fresh = self.runner.run(ctx.world, ctx.transferer, ctx.featurizer, self.model, misses)
        for key, out in zip(keys, known, strict=True):
            if out is None:
                result = next(fresh)
                memo.put(key, result.outcome)
                yield result, False
                continue
            cloud = q = None
            if value and not out.knot and child_is_valued(out):
                ctx.world.restore(out.snapshot_after)
                cloud, q = value_child(ctx.world, ctx.featurizer, self.model)
            yield ExpansionResult(out, cloud, q), True

    def _prefetch(
        self,
        ctx: StepContext,
        known: list[_Node],
        unknown: int,
        value: bool,
        early: dict[tuple[int, int], ExpansionJob],
    ) -> None:
        """Hand the runner the next level's expansions that are certain already.

        With 2 workers and 5 expansions a level, the level's last one runs alone; a worker
        starts on the next level instead. Only certain members (`certain_members`) go early, so
        the search simulates nothing the sequential one would not, except when a knot among
        the level's last results ends it (the prefetched work is then dropped).
        """
        jobs = []
        for node_i, a in certain_members([n.q_a for n in known], unknown, self.width):
            node = known[node_i]
            if (node.tree_id, a) in early:
                continue
            if self._memo(ctx).get(OutcomeMemo.key(ctx.world, ctx.transferer, *node.keys, a)):
                continue  # the level takes it from the memo
            job = ExpansionJob(node.snapshot, node.cloud_n3, a, value)
            early[(node.tree_id, a)] = job
            jobs.append(job)
        if jobs:
            self.runner.prefetch(self.model, jobs)

    def choose(self, ctx: StepContext) -> Decision:
        """Beam search from the current state; returns the best root action."""
        world = ctx.world
        root_snapshot = world.snapshot()
        root_q = demo_scores(ctx.scan, ctx.phi_ad, self.model)
        root_keys = (snapshot_digest(root_snapshot), cloud_digest(ctx.cloud_n3))
        frontier = [_Node(root_snapshot, ctx.cloud_n3, root_q, -1, root_keys)]
        backed: dict[int, tuple[int, float]] = {}  # root action -> (depth reached, value)
        root_outcomes: dict[int, ActionOutcome] = {}
        tree: list[dict] = []
        expansions = reused = 0  # reused: taken from the memo, not simulated
        early: dict[tuple[int, int], ExpansionJob] = {}  # (node tree id, action) -> prefetched
        t0 = time.perf_counter()
        max_depth = min(self.depth, ctx.steps_left)
        try:
            for level in range(max_depth):
                chosen = beam_level([node.q_a for node in frontier], self.width)
                # After the episode's last action only a knot counts: a non-knot child is a
                # failure whatever it looks like, so its value is not worth a scan.
                at_horizon = level + 1 >= ctx.steps_left
                results = self._run_level(
                    ctx,
                    [frontier[i] for _, i, _ in chosen],
                    [a for _, _, a in chosen],
                    not at_horizon,
                    early,
                )
                next_frontier = []
                for done, ((_, node_i, a), (res, from_memo)) in enumerate(
                    zip(chosen, results, strict=True), start=1
                ):
                    node, outcome = frontier[node_i], res.outcome
                    expansions += 1
                    reused += from_memo
                    root_a = a if node.root_action < 0 else node.root_action
                    if node.root_action < 0:
                        root_outcomes[a] = outcome
                    value = -np.inf if res.child_q_a is None else float(np.max(res.child_q_a))
                    tree.append(
                        {
                            "node": len(tree) + 1,
                            "parent": node.tree_id,
                            "level": level + 1,
                            "root_action": int(root_a),
                            "action": int(a),
                            "q": float(node.q_a[a]),
                            "value": None if not np.isfinite(value) else value,
                            "knot": bool(outcome.knot),
                            "stage": int(outcome.stage),
                            "failure": outcome.failure,
                            "reused": bool(from_memo),
                        }
                    )
                    if outcome.knot:
                        return self._decide(
                            root_a, root_q, backed, root_outcomes, expansions, t0, True,
                            reused, tree,
                        )  # fmt: skip
                    depth_reached = level + 1
                    prev = backed.get(root_a)
                    if (
                        prev is None
                        or depth_reached > prev[0]
                        or (depth_reached == prev[0] and value > prev[1])
                    ):
                        backed[root_a] = (depth_reached, value)
                    if res.child_q_a is not None and level + 1 < max_depth:
                        assert res.child_cloud_n3 is not None
                        child_keys = (
                            snapshot_digest(outcome.snapshot_after),
                            cloud_digest(res.child_cloud_n3),
                        )
                        next_frontier.append(
                            _Node(
                                outcome.snapshot_after,
                                res.child_cloud_n3,
                                res.child_q_a,
                                root_a,
                                child_keys,
                                len(tree),
                            )
                        )
                    if self.runner.speculates and level + 1 < max_depth:
                        self._prefetch(
                            ctx, next_frontier, len(chosen) - done, level + 2 < ctx.steps_left,
                            early,
                        )  # fmt: skip
                if ctx.on_level is not None:
                    so_far = self._decide(
                        None, root_q, dict(backed), root_outcomes, expansions, t0, False,
                        reused, list(tree),
                    )  # fmt: skip
                    levels = level + 1 if not next_frontier else max_depth
                    ctx.on_level(LevelDecision(level + 1, levels, so_far))
                frontier = next_frontier
                if not frontier:
                    break
        finally:
            self.runner.drop_prefetched()
            world.restore(root_snapshot)
        return self._decide(
            None, root_q, backed, root_outcomes, expansions, t0, False, reused, tree
        )

    def _decide(
        self,
        goal_action: int | None,
        root_q: np.ndarray,
        backed: dict[int, tuple[int, float]],
        root_outcomes: dict[int, ActionOutcome],
        expansions: int,
        t0: float,
        goal: bool,
        reused: int = 0,
        tree: Sequence[dict] = (),
    ) -> Decision:
        info = {
            "expansions": expansions,
            "reused_expansions": reused,
            "goal_found": goal,
            "search_s": time.perf_counter() - t0,
            "tree": list(tree),
        }
        if goal_action is not None:
            action = goal_action
        else:
            deepest = max((d for d, _ in backed.values()), default=0)
            contenders = {a: v for a, (d, v) in backed.items() if d == deepest}
            finite = {a: v for a, v in contenders.items() if np.isfinite(v)}
            if finite:
                best = max(finite.values())
                tied = [a for a, v in finite.items() if v == best]
                action = max(tied, key=lambda a: root_q[a])
            else:
                action = int(np.argmax(root_q))
        scores = np.array(root_q, dtype=float)
        for a, (_, v) in backed.items():
            scores[a] = v
        if goal:
            scores[action] = np.inf
        info["backed_up"] = {int(a): (int(d), float(v)) for a, (d, v) in backed.items()}
        return Decision(int(action), scores, info, root_outcomes.get(int(action)))
