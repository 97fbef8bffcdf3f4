"""The adaptive lookahead: names, the members' running errors, and real searches that keep to the
agent's model when it is the world and move to the member that is the world when it is not."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.execution.apply import apply_demo
from knotlab.core.selection.adaptive import (
    AdaptiveLookaheadPolicy,
    best_member,
    prediction_errors_mm,
)
from knotlab.core.selection.decision import StepContext
from knotlab.core.selection.lookahead import LookaheadPolicy
from knotlab.core.selection.policies import make_policy, policy_config
from knotlab.core.selection.qmodel import QModel
from knotlab.core.world.estimate import RopeEstimate, place_estimate
from knotlab.core.world.mismatch import PhysicsParams, perturb_params
from knotlab.core.world.sim import GripperParams, RopeWorld

pytestmark = pytest.mark.xdist_group("minilib")


def test_names_parse_to_an_adaptive_ensemble():
    config = policy_config("ala2x5k4")
    assert (config.kind, config.depth, config.width, config.members) == ("adaptive", 2, 5, 4)
    assert config.needs_model and config.simulates
    assert config.spread == 0.25
    wide = policy_config("ala2x5k4s50")
    assert (wide.members, wide.spread) == (4, 0.5)
    q = QModel(np.zeros(1), 0.0, np.zeros(1), np.ones(1), None, {})  # type: ignore[arg-type]
    assert make_policy("ala2x5k4s50", q).name == "ala2x5k4s50"
    assert make_policy("rla2x5k2mins50", q).name == "rla2x5k2mins50"
    assert make_policy("ala2x5k4", q).name == "ala2x5k4"
    for bad in ("ala2x5k1", "ala2x5", "ala0x5k2", "ala2x5k2min", "ala2x5k2s0", "ala2x5k2s100"):
        with pytest.raises(InvalidInputError, match="ala<D>x<W>k<K>"):
            policy_config(bad)


def test_errors_are_mean_node_distances_and_the_lowest_total_wins_ties_to_member_0():
    observed = np.zeros((5, 3))
    shifted = observed + np.array([0.0, 0.002, 0.0])  # every node 2 mm off
    errors = prediction_errors_mm([observed, shifted, None], observed)
    assert errors[0] == 0.0 and errors[1] == pytest.approx(2.0) and errors[2] == np.inf
    assert best_member(np.array([1.0, 1.0, 0.5])) == 2
    assert best_member(np.array([0.5, 0.5, np.inf])) == 0  # ties: the agent's own model first
    assert best_member(np.array([np.inf, np.inf])) == 0  # nothing predicted: its own model


def _model(lib, featurizer, ctx) -> QModel:
    d = ctx.phi_ad.shape[1]
    w = np.zeros(d)
    w[-len(lib) :] = np.arange(len(lib))
    return QModel(w, 0.0, np.zeros(d), np.ones(d), featurizer.spec(), {})


def _ctx(world, featurizer, transferer, cloud, step: int) -> StepContext:
    return StepContext(world, cloud, featurizer.scan(cloud), featurizer, transferer, step, 3 - step)


@pytest.mark.slow
def test_with_its_model_the_world_it_plans_as_the_plain_lookahead(
    lib, world, featurizer, transferer
):
    world.reset(lib[lib.index_of("s000-t0")].pre_nodes_k3)
    cloud = featurizer.observe(world)
    model = _model(lib, featurizer, _ctx(world, featurizer, transferer, cloud, 0))
    adaptive = AdaptiveLookaheadPolicy(model, 1, 2, 3)
    plain = LookaheadPolicy(model, 1, 2)
    try:
        for step in range(2):
            cloud = featurizer.observe(world)
            before = world.snapshot()
            got = adaptive.choose(_ctx(world, featurizer, transferer, cloud, step))
            assert world.snapshot().equals(before)  # the world as found
            want = plain.choose(_ctx(world, featurizer, transferer, cloud, step))
            assert got.action == want.action and np.array_equal(got.scores_a, want.scores_a)
            assert got.info["planned_in"] == 0
            if step == 1:  # member 0 predicted the step exactly; the others did not
                errors = got.info["member_errors_mm"]
                assert errors[0] == 0.0 and min(errors[1:]) > 0
            apply_demo(world, transferer, cloud, got.action)
    finally:
        adaptive.close()


@pytest.mark.slow
def test_in_a_world_unlike_its_model_it_plans_in_the_member_that_predicted_it(
    lib, world, featurizer, transferer
):
    # The world is member 1's physics (its rope 4 % shorter, so the start fits it too); the
    # agent's model (member 0) is the nominal rope, member 2 another draw.
    truth = perturb_params(PhysicsParams(world.params, GripperParams()), 0.25, 1)
    model_world = world
    with RopeWorld(truth.rope, truth.gripper) as real:
        real.reset(lib[lib.index_of("s000-t0")].pre_nodes_k3)
        cloud = featurizer.observe(real)
        model = _model(lib, featurizer, _ctx(real, featurizer, transferer, cloud, 0))
        policy = make_policy("ala1x2k3", model)
        assert isinstance(policy, AdaptiveLookaheadPolicy)
        try:
            for step in range(2):
                cloud = featurizer.observe(real)
                place_estimate(model_world, RopeEstimate(real.rope_nodes(), real.snapshot()))
                got = policy.choose(_ctx(model_world, featurizer, transferer, cloud, step))
                apply_demo(real, transferer, cloud, got.action)  # the world acts
            errors = got.info["member_errors_mm"]
            assert int(np.argmin(errors)) == 1, errors
            assert got.info["planned_in"] == 1 and got.outcome is None
        finally:
            policy.close()


@pytest.mark.slow
def test_an_episode_records_the_member_each_step_planned_in(lib, world, featurizer, transferer):
    from knotlab.core.agent import Agent

    start = lib[lib.index_of("s000-t0")].pre_nodes_k3
    world.reset(start)
    cloud = featurizer.observe(world)
    model = _model(lib, featurizer, _ctx(world, featurizer, transferer, cloud, 0))
    adaptive = Agent(lib, model, "ala1x2k2")
    plain = Agent(lib, model, "la1x2")
    got = adaptive.run_episode(world, start, max_steps=2).summary()
    want = plain.run_episode(world, start, max_steps=2).summary()
    assert got["planned_in"] == [0] * got["n_steps"]  # the model is the world: its own model
    assert got["chosen"] == want["chosen"] and "planned_in" not in want
