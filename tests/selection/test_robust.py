"""The robust lookahead: names, the ensemble's aggregation, a real search in two models."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.decision import Decision, StepContext
from knotlab.core.selection.policies import policy_config
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.robust import RobustLookaheadPolicy

pytestmark = pytest.mark.xdist_group("minilib")


def test_names_parse_to_an_ensemble_of_lookaheads():
    config = policy_config("rla2x5k3")
    assert (config.kind, config.depth, config.width, config.members) == ("robust", 2, 5, 3)
    assert config.aggregate == "mean" and config.needs_model and config.simulates
    assert policy_config("rla1x10k2min").aggregate == "min"
    for bad in ("rla2x5k1", "rla2x5", "rla0x5k2", "rla2x5k2max"):
        with pytest.raises(InvalidInputError, match="rla<D>x<W>k<K>"):
            policy_config(bad)


def _decision(action: int, n: int, backed: dict, goal: bool = False) -> Decision:
    q = np.arange(n, dtype=float) / 10  # root Q: later demos slightly better
    return Decision(action, q, {"backed_up": backed, "goal_found": goal, "expansions": 3})


def _policy(aggregate: str) -> RobustLookaheadPolicy:
    q = QModel(np.zeros(1), 0.0, np.zeros(1), np.ones(1), None, {})  # type: ignore[arg-type]
    return RobustLookaheadPolicy(q, 1, 3, 3, aggregate)


def test_the_goal_in_most_members_wins_then_the_aggregated_value():
    members = [
        _decision(1, 5, {0: (1, 2.0), 1: (1, 1.0)}),
        _decision(0, 5, {0: (1, -3.0), 1: (1, 1.5)}),
        _decision(2, 5, {}, goal=True),
    ]
    mean = _policy("mean")._aggregate(members, 0.0)
    assert mean.action == 2  # a goal beats any value
    assert mean.info["goal_votes"] == {2: 1} and mean.scores_a[2] == np.inf
    no_goal = members[:2]
    # mean: demo 0 = -0.5, demo 1 = 1.25; min: demo 0 = -3, demo 1 = 1.0
    assert _policy("mean")._aggregate(no_goal, 0.0).action == 1
    assert _policy("min")._aggregate(no_goal, 0.0).info["pooled"] == {0: -3.0, 1: 1.0}


def test_values_of_shallower_levels_or_too_few_members_do_not_count():
    members = [
        _decision(0, 4, {0: (2, 1.0), 3: (1, 9.0)}),  # 3 only reached level 1 here
        _decision(3, 4, {3: (2, 0.5)}),
        _decision(0, 4, {0: (2, 0.8)}),
    ]
    decision = _policy("mean")._aggregate(members, 0.0)
    assert decision.info["pooled"] == {0: pytest.approx(0.9)}  # 3 valued by 1 of 3 members
    assert decision.action == 0


@pytest.mark.slow
def test_a_robust_search_runs_in_its_own_members_and_leaves_the_world_as_found(
    lib, world, featurizer, transferer
):
    world.reset(lib[lib.index_of("s000-t0")].pre_nodes_k3)
    cloud = featurizer.observe(world)
    ctx = StepContext(world, cloud, featurizer.scan(cloud), featurizer, transferer, 0, 3)
    d = ctx.phi_ad.shape[1]
    w = np.zeros(d)
    w[-len(lib) :] = np.arange(len(lib))
    model = QModel(w, 0.0, np.zeros(d), np.ones(d), featurizer.spec(), {})
    policy = RobustLookaheadPolicy(model, 1, 2, 2)
    before = world.snapshot()
    try:
        decision = policy.choose(ctx)
        assert world.snapshot().equals(before)
        assert len(decision.info["members"]) == 2 and decision.outcome is None
        assert decision.info["expansions"] >= 2
        member = policy._member_worlds(ctx)[0]
        assert member is not world and member.params != world.params  # a perturbed model
        again = policy.choose(ctx)  # the members' own memos: the same decision
        assert again.action == decision.action
    finally:
        policy.close()
