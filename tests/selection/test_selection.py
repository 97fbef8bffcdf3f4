"""Features, policies, episodes and the oracle labeller on a tiny real library (tests.minilib)."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import KnotlabError
from knotlab.core.experiments.labeller import OracleParams, label_task
from knotlab.core.registration.planner import TransferPlan
from knotlab.core.selection.decision import Policy, StepContext
from knotlab.core.selection.learner import MaxMarginQLearner
from knotlab.core.selection.lookahead import LookaheadPolicy
from knotlab.core.selection.policies import (
    GreedyPolicy,
    NearestNeighbourPolicy,
    SimulationOraclePolicy,
    make_policy,
)
from knotlab.core.selection.qmodel import QModel
from tests.minilib import mini_executions

pytestmark = pytest.mark.xdist_group("minilib")


def _ctx(world, featurizer, transferer, nodes, step=0):
    world.reset(nodes)
    cloud = world.observe()
    return StepContext(world, cloud, featurizer.scan(cloud), featurizer, transferer, step, 5 - step)


def test_features_have_the_spec_shape_and_meaning(lib, featurizer):
    seg = lib[lib.index_of("s001-t1")]
    phi, scan = featurizer.features(seg.pre_cloud_n3)
    spec = featurizer.feature_spec
    n = len(lib)
    assert phi.shape == (n, len(spec.names)) == (n, 14 + n)
    assert np.all(np.isfinite(phi))
    np.testing.assert_array_equal(phi[:, -n:], np.eye(n))  # the demo one-hot
    assert sum(spec.indicator_mask) == n
    names = list(spec.names)
    phase = phi[0, names.index("phase_0") : names.index("phase_2") + 1]
    assert phase.sum() == pytest.approx(1.0)
    # A demo's own cloud matches itself best: lowest mapping error and a grasp on the rope.
    a = lib.index_of("s001-t1")
    assert np.argmin(scan.nn_cost_a) == a
    assert phi[a, names.index("grasp_dist_m")] < 0.03  # within the grasp radius
    assert phi[a, names.index("phase_match")] == phi[a, names.index("phase_1")]
    # Quadratic terms are products of the cost columns.
    c1 = phi[:, names.index("c1_map")]
    np.testing.assert_allclose(phi[:, names.index("c1_map*c1_map")], c1 * c1)


def test_margins_are_zero_for_the_expert_and_grow_with_trajectory_difference(lib, featurizer):
    seg = lib[lib.index_of("s000-t0")]
    _, scan = featurizer.features(seg.pre_cloud_n3)
    m = featurizer.margins(scan, lib.index_of("s000-t0"))
    assert m[lib.index_of("s000-t0")] == 0.0
    assert np.all(m >= 0)
    # The twin demo's step 0 warps onto nearly the same path; a different step does not.
    assert m[lib.index_of("s001-t0")] < m[lib.index_of("s000-t2")]


def test_nearest_neighbour_and_greedy_choose_by_their_scores(world, lib, featurizer, transferer):
    ctx = _ctx(world, featurizer, transferer, lib[lib.index_of("s000-t1")].pre_nodes_k3, 1)
    nn = NearestNeighbourPolicy().choose(ctx)
    assert nn.action == int(np.argmin(ctx.scan.nn_cost_a))
    d = ctx.phi_ad.shape[1]
    weights = np.zeros(d)
    favourite = lib.index_of("s001-t2")
    weights[d - len(lib) + favourite] = 1.0  # Q = the one-hot of one demo
    model = QModel(weights, 0.0, np.zeros(d), np.ones(d), featurizer.spec(), {})
    assert GreedyPolicy(model).choose(ctx).action == favourite


def test_make_policy_parses_names_and_rejects_bad_ones(featurizer):
    d = 14 + featurizer.n_actions
    model = QModel(np.zeros(d), 0.0, np.zeros(d), np.ones(d), {}, {})
    assert isinstance(make_policy("nn"), NearestNeighbourPolicy)
    assert isinstance(make_policy("oracle"), SimulationOraclePolicy)
    la = make_policy("la2x5", model)
    assert (la.depth, la.width, la.name) == (2, 5, "la2x5")
    with pytest.raises(ValueError, match="needs a trained QModel"):
        make_policy("greedy")
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("random")
    with pytest.raises(ValueError, match="la2x5"):
        make_policy("laXY", model)


def test_lookahead_finds_the_knot_and_restores_the_world(world, lib, featurizer, transferer):
    nodes = lib[lib.index_of("s000-t2")].pre_nodes_k3  # one pull from a knot
    ctx = _ctx(world, featurizer, transferer, nodes, 2)
    before = world.snapshot()
    d = ctx.phi_ad.shape[1]
    model = QModel(np.zeros(d), 0.0, np.zeros(d), np.ones(d), featurizer.spec(), {})
    decision = LookaheadPolicy(model, depth=1, width=len(lib)).choose(ctx)
    assert decision.info["goal_found"]
    assert decision.outcome is not None and decision.outcome.knot
    assert world.snapshot().equals(before)  # the search leaves the world where it found it


@pytest.mark.slow
def test_lookahead_on_the_last_step_values_only_knots(world, lib, featurizer, transferer):
    nodes = lib[lib.index_of("s000-t0")].pre_nodes_k3  # a start: no knot in one action
    world.reset(nodes)
    cloud = world.observe()
    ctx = StepContext(world, cloud, featurizer.scan(cloud), featurizer, transferer, 4, 1)
    d = ctx.phi_ad.shape[1]
    w = np.zeros(d)
    w[-len(lib) :] = np.arange(len(lib))  # Q prefers the last demo
    model = QModel(w, 0.0, np.zeros(d), np.ones(d), featurizer.spec(), {})
    decision = LookaheadPolicy(model, depth=2, width=len(lib)).choose(ctx)
    assert not decision.info["goal_found"]
    assert decision.info["expansions"] == len(lib)  # one level only: the episode ends here
    # No child can be worth anything but a knot, so the root's Q decides.
    assert all(v == -np.inf for _, v in decision.info["backed_up"].values())
    assert decision.action == len(lib) - 1


def test_lookahead_backup_compares_negative_values_at_the_deepest_level(featurizer):
    d = 14 + featurizer.n_actions
    model = QModel(np.zeros(d), 0.0, np.zeros(d), np.ones(d), {}, {})
    policy = LookaheadPolicy(model, depth=2, width=3)
    root_q = np.array([5.0, 1.0, 0.0, -1.0, 0, 0])
    # Action 0 was only expanded one level; 1 and 2 reached depth 2 with negative values.
    backed = {0: (1, 8.0), 1: (2, -6.0), 2: (2, -3.0)}
    decision = policy._decide(None, root_q, backed, {}, 5, 0.0, goal=False)
    assert decision.action == 2  # the best among the deepest, though all are negative


def test_oracle_policy_and_episode_tie_the_knot_from_the_last_step(world, lib, agent):
    nodes = lib[lib.index_of("s000-t2")].pre_nodes_k3
    record = agent.with_policy("oracle").run_episode(world, nodes, max_steps=2)
    assert record.success and record.failure_kind is None
    step = record.steps[0]
    assert step.knot and step.outcome == "knot" and step.stage == 3
    assert step.trajectory is not None and step.scores_a.shape == (len(lib),)
    assert step.timings["decide_s"] > 0 and "execute_s" in step.timings
    assert record.summary()["chosen"] == [step.chosen_key]


def test_episode_records_failed_registration_and_errors_without_raising(
    world, lib, agent, monkeypatch
):
    nodes = lib[0].pre_nodes_k3

    def failing_plan(cloud, a):
        return TransferPlan(a, None, None, "registration: forced failure")

    monkeypatch.setattr(agent.transferer, "plan", failing_plan)
    record = agent.run_episode(world, nodes)
    assert not record.success and record.failure_kind == "registration"
    assert record.steps[0].outcome == "registration"

    class Broken(Policy):
        name = "broken"

        def choose(self, ctx):
            raise KnotlabError("solver returned NaN")

    broken = agent.with_policy("nn")
    broken.policy = Broken()
    record = broken.run_episode(world, nodes)
    assert record.failure_kind == "error" and "NaN" in record.error


def test_oracle_labeller_labels_a_state_one_step_from_the_knot(world, lib, agent):
    nodes = lib[lib.index_of("s001-t2")].pre_nodes_k3
    result = label_task(agent, world, nodes, task_id="t", params=OracleParams(sim_budget=6))
    ex = result.execution
    assert result.solved and ex.ended_in_knot and ex.source == "oracle"
    assert [s.outcome for s in ex.steps] == ["knot"]
    assert ex.steps[0].candidates and ex.steps[0].candidate_scores_c is not None
    assert ex.library_hash == lib.content_hash()
    assert 1 <= result.simulations <= 6


def test_learner_fits_real_features_and_ranks_the_expert_first(featurizer):
    model = MaxMarginQLearner(C=100.0, D=1.0).fit(mini_executions(2), featurizer)
    assert model.feature_spec.names == featurizer.feature_spec.names
    assert model.metrics["train_top1"] >= 0.8
    assert model.metrics["n_bellman_rows"] >= 2
