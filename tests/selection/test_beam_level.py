"""A lookahead level's beam, and which of the next level's members are certain early."""

from __future__ import annotations

import numpy as np

from knotlab.core.selection.lookahead import beam_level, certain_members


def _random_node(rng: np.random.Generator, n_actions: int = 12) -> np.ndarray:
    q = np.round(rng.normal(size=n_actions), 1)  # rounded: ties happen
    q[rng.random(n_actions) < 0.2] = -np.inf  # unusable demos
    return q


def test_with_every_child_known_the_certain_members_are_the_beam():
    rng = np.random.default_rng(0)
    for width in (1, 3, 5, 10):
        for n_nodes in range(1, 6):
            nodes = [_random_node(rng) for _ in range(n_nodes)]
            assert certain_members(nodes, 0, width) == [
                (i, a) for _, i, a in beam_level(nodes, width)
            ]


def test_certain_members_are_in_the_next_level_whatever_the_rest_bring():
    rng = np.random.default_rng(1)
    found_some = 0
    for _ in range(3000):
        width = int(rng.integers(1, 11))
        known = [_random_node(rng) for _ in range(int(rng.integers(0, 6)))]
        unknown = int(rng.integers(0, 5))
        certain = certain_members(known, unknown, width)
        # The children still to come: any number of them open a node (the others are knots,
        # blow-ups or memo misses that open nothing), with any Q, often above every known one.
        opened = int(rng.integers(0, unknown + 1))
        rest = [_random_node(rng) + rng.choice([0.0, 5.0]) for _ in range(opened)]
        level = {(i, a) for _, i, a in beam_level(known + rest, width)}
        assert set(certain) <= level, (width, len(known), unknown, opened)
        found_some += bool(certain) and unknown > 0
    assert found_some > 100  # the property is not vacuous


def test_four_of_five_known_make_the_top_three_certain():
    # la2x5 with two workers: when 4 of 5 level-1 children are known (all open), each node
    # offers 2 and the last child at most 2 more, so the 3 best known candidates are certain.
    q = [np.array([9.0, 1, 0]), np.array([8.0, 7, 0]), np.array([6.0, 5, 0]), np.array([4.0, 3, 0])]
    assert certain_members(q, 1, 5) == [(0, 0), (1, 0), (1, 1)]
