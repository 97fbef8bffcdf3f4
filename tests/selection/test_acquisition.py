"""Acquisition scores (Q margin, policy disagreement) and the labelling order they give."""

from __future__ import annotations

import math

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.acquisition import (
    AcquisitionScore,
    choice_disagreement,
    q_margin,
    rank_for_labelling,
    score_state,
)


def test_q_margin_is_the_gap_between_the_two_best_usable_demos() -> None:
    assert q_margin(np.array([0.1, 2.0, 1.5, -3.0])) == pytest.approx(0.5)
    assert q_margin(np.array([1.0, -np.inf, 1.0])) == 0.0  # a tie is the least certain
    assert q_margin(np.array([-np.inf, 4.0, np.nan, 1.0])) == pytest.approx(3.0)
    assert math.isinf(q_margin(np.array([1.0, -np.inf])))  # one usable demo: nothing to learn


def test_q_margin_refuses_a_matrix() -> None:
    with pytest.raises(InvalidInputError, match="one-dimensional"):
        q_margin(np.zeros((2, 3)))


def test_choice_disagreement_is_the_share_of_disagreeing_policy_pairs() -> None:
    assert choice_disagreement({"nn": "a", "greedy": "a"}) == 0.0
    assert choice_disagreement({"nn": "a", "greedy": "b"}) == 1.0
    assert choice_disagreement({"nn": "a", "greedy": "a", "la": "b"}) == pytest.approx(2 / 3)
    assert choice_disagreement({"nn": "a"}) == 0.0


def test_combined_ranking_puts_disagreement_first_then_small_margins() -> None:
    scores = [
        score_state("calm", np.array([3.0, 0.0]), {"nn": "a", "greedy": "a"}),  # margin 3
        score_state("close", np.array([1.0, 0.9]), {"nn": "a", "greedy": "a"}),  # margin 0.1
        score_state("split", np.array([5.0, 0.0]), {"nn": "a", "greedy": "b"}),  # disagree
    ]
    order = [r.score.key for r in rank_for_labelling(scores)]
    assert order == ["split", "close", "calm"]
    assert [r.score.key for r in rank_for_labelling(scores, by="margin")] == [
        "close",
        "calm",
        "split",
    ]
    assert [r.rank for r in rank_for_labelling(scores)] == [1, 2, 3]


def test_ties_are_broken_by_the_seed_and_not_by_input_order() -> None:
    tied = [AcquisitionScore(f"t{i}", 1.0, {"nn": "a", "greedy": "a"}) for i in range(30)]
    first = [r.score.key for r in rank_for_labelling(tied, seed=1)]
    assert first == [r.score.key for r in rank_for_labelling(tied[::-1], seed=1)]
    assert first != [r.score.key for r in rank_for_labelling(tied, seed=2)]


def test_ranking_refuses_duplicate_keys_and_unknown_orders() -> None:
    twice = [AcquisitionScore("t", 1.0), AcquisitionScore("t", 2.0)]
    with pytest.raises(InvalidInputError, match="distinct"):
        rank_for_labelling(twice)
    with pytest.raises(InvalidInputError, match="rank by"):
        rank_for_labelling([], by="entropy")  # type: ignore[arg-type]
