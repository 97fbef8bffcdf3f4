"""rank_demos: best first, unusable demos never offered, ties stable, NN without a model."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.ranking import demo_scores, rank_demos, rank_order


def _scan(cost, ok):
    return SimpleNamespace(nn_cost_a=np.asarray(cost, float), ok_a=np.asarray(ok, bool))


def test_without_a_model_the_cheapest_registration_ranks_first():
    scan = _scan([0.3, 0.1, 0.2, 0.05], [True, True, True, False])
    ranked = rank_demos(scan, None, None, ("a", "b", "c", "d"))
    assert [r.demo_key for r in ranked] == ["b", "c", "a"]  # d failed to register
    assert [r.rank for r in ranked] == [1, 2, 3] and ranked[0].q is None


def test_with_a_model_q_ranks_and_ties_keep_library_order():
    model = SimpleNamespace(q=lambda phi: phi[:, 0])
    scan = _scan([1, 1, 1], [True, True, True])
    phi = np.array([[1.0], [2.0], [2.0]])
    ranked = rank_demos(scan, phi, model, ("a", "b", "c"), top_k=2)
    assert [r.demo_key for r in ranked] == ["b", "c"] and ranked[0].q == 2.0


def test_non_finite_scores_are_dropped_and_bad_arguments_refused():
    scores = demo_scores(_scan([np.nan, 0.2], [True, True]), None, None)
    assert list(rank_order(scores)) == [1]
    with pytest.raises(InvalidInputError, match="top_k"):
        rank_demos(_scan([0.1], [True]), None, None, ("a",), top_k=0)
    with pytest.raises(InvalidInputError, match="phi_ad"):
        demo_scores(_scan([0.1], [True]), None, SimpleNamespace(q=None))
