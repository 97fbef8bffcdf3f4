"""Tests for the max-margin + Bellman QP learner and QModel persistence."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import CorruptFileError, InvalidInputError, SolverError
from knotlab.core.selection.learner import LabelledState, MaxMarginQLearner, TrainingData
from knotlab.core.selection.qmodel import QModel


def _toy_separable(n_states: int = 30, n_actions: int = 8, seed: int = 0) -> TrainingData:
    """States where the expert always picks the action with the largest first feature."""
    rng = np.random.default_rng(seed)
    states = []
    for _ in range(n_states):
        phi = rng.normal(size=(n_actions, 4))
        a_star = int(np.argmax(phi[:, 0]))
        margins = np.abs(phi[a_star, 0] - phi[:, 0]) * 0.05  # metres-like, 0 at a*
        states.append(LabelledState(phi, a_star, margins))
    return TrainingData(tuple(states))


def test_separable_toy_set_ranks_expert_action_first():
    train = _toy_separable(seed=0)
    model = MaxMarginQLearner(C=100.0, D=1.0).fit(train)
    assert model.metrics["train_top1"] == 1.0
    test = _toy_separable(n_states=50, seed=1)
    hits = [int(np.argmax(model.q(s.phi_ad)) == s.expert_action) for s in test.states]
    assert np.mean(hits) >= 0.9  # generalises: the rule is linear in the features


def test_learner_prefers_expert_when_a_distractor_feature_is_noise():
    rng = np.random.default_rng(3)
    states = []
    for _ in range(40):
        phi = np.column_stack([rng.normal(size=6), rng.normal(size=6) * 10.0])
        a_star = int(np.argmax(phi[:, 0]))
        states.append(LabelledState(phi, a_star, np.where(np.arange(6) == a_star, 0.0, 0.02)))
    model = MaxMarginQLearner(C=10.0).fit(TrainingData(tuple(states)))
    # Standardisation puts both columns on one scale; the informative one must dominate.
    assert abs(model.weights_d[0]) > 5 * abs(model.weights_d[1])


def _chain(length: int = 4, n_actions: int = 3) -> TrainingData:
    """One expert execution of ``length`` steps; state t is a one-hot feature block."""
    states = []
    for t in range(length):
        phi = np.zeros((n_actions, length + n_actions))
        phi[:, t] = 1.0
        phi[np.arange(n_actions), length + np.arange(n_actions)] = 1.0
        states.append(LabelledState(phi, 0, np.array([0.0] + [0.05] * (n_actions - 1)), 0, t))
    pairs = tuple((t, t + 1) for t in range(length - 1))
    return TrainingData(tuple(states), pairs, (length - 1,))


def test_bellman_values_are_recovered_on_a_chain():
    data = _chain(length=4)
    model = MaxMarginQLearner(C=1.0, D=1000.0, standardize=False).fit(data)
    values = [model.q(s.phi_ad)[s.expert_action] for s in data.states]
    # r = -1 per step, +10 at the goal: Q(s_T-k, a*) = 9 - k.
    np.testing.assert_allclose(values, [6.0, 7.0, 8.0, 9.0], atol=1e-3)
    assert model.metrics["bellman_mean_abs_error"] < 1e-3


def test_dead_end_values_are_pushed_below_the_bound():
    data = _chain(length=2)
    dead = np.zeros((3, 5))
    dead[:, 2:] = np.eye(3)  # a state unlike any expert state
    data = TrainingData(data.states, data.bellman_pairs, data.goal_states, (dead,))
    model = MaxMarginQLearner(C=1.0, D=1000.0, standardize=False).fit(data)
    assert np.all(model.q(dead) <= -10.0 + 1e-3)


def test_infeasible_hard_bellman_raises_clear_error():
    phi = np.eye(2)
    s0 = LabelledState(phi, 0, np.array([0.0, 0.1]))
    s1 = LabelledState(phi, 0, np.array([0.0, 0.1]))  # same features, so same Q(s, a*)
    # Q(s0) = -1 + Q(s1) with Q(s0) == Q(s1) has no solution.
    data = TrainingData((s0, s1), ((0, 1),))
    with pytest.raises(SolverError, match="infeasible"):
        MaxMarginQLearner(hard_bellman=True, standardize=False).fit(data)


def test_solver_iteration_limit_raises_clear_error():
    data = _toy_separable(n_states=20)
    learner = MaxMarginQLearner(C=100.0, solver_options={"max_iter": 1})
    with pytest.raises(SolverError, match="status"):
        learner.fit(data)


def test_the_raised_iteration_cap_changes_no_fit_that_converged_under_the_old_one():
    """CLARABEL's own cap is 200 iterations; the learner allows more (large pooled label sets
    need them), and a fit that converges under 200 is the same model either way."""
    data = _toy_separable(n_states=20)
    raised = MaxMarginQLearner(C=100.0).fit(data)
    capped = MaxMarginQLearner(C=100.0, solver_options={"max_iter": 200}).fit(data)
    assert np.array_equal(raised.weights_d, capped.weights_d) and raised.bias == capped.bias
    assert MaxMarginQLearner()._options()["max_iter"] > 200
    assert MaxMarginQLearner(solver="SCS")._options() == {}


def test_bad_inputs_are_rejected():
    with pytest.raises(InvalidInputError, match="non-finite"):
        LabelledState(np.array([[np.nan, 1.0]]), 0, np.zeros(1))
    with pytest.raises(InvalidInputError, match="expert_action"):
        LabelledState(np.ones((2, 2)), 5, np.zeros(2))
    with pytest.raises(InvalidInputError, match="C must be"):
        MaxMarginQLearner(C=-1.0).fit(_toy_separable(5))
    with pytest.raises(InvalidInputError, match="featurizer"):
        MaxMarginQLearner().fit([])


def test_qmodel_save_load_round_trip(tmp_path):
    model = MaxMarginQLearner(C=10.0).fit(_toy_separable(10))
    path = model.save(tmp_path / "model.npz")
    loaded = QModel.load(path)
    assert loaded.content_hash() == model.content_hash()
    phi = np.random.default_rng(0).normal(size=(8, 4))
    np.testing.assert_array_equal(loaded.q(phi), model.q(phi))
    assert loaded.hyperparameters["C"] == 10.0


def test_qmodel_load_rejects_corrupt_and_truncated_files(tmp_path):
    path = MaxMarginQLearner().fit(_toy_separable(10)).save(tmp_path / "model.npz")
    raw = path.read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(CorruptFileError, match=r"trunc\.npz"):
        QModel.load(tmp_path / "trunc.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a model at all")
    with pytest.raises(CorruptFileError, match="junk"):
        QModel.load(tmp_path / "junk.npz")


def test_qmodel_q_rejects_wrong_feature_dimension():
    model = MaxMarginQLearner().fit(_toy_separable(10))
    with pytest.raises(InvalidInputError, match="shape"):
        model.q(np.ones((3, 7)))


def test_dead_end_only_data_merges_but_cannot_be_fitted_alone():
    dead = TrainingData((), dead_ends_phi=(np.ones((3, 4)),))
    assert dead.n_features == 4
    with pytest.raises(InvalidInputError, match="at least one labelled expert state"):
        MaxMarginQLearner().fit(dead)
    with pytest.raises(InvalidInputError, match="state or dead end"):
        TrainingData(())
