"""Feature contributions add up to Q; the lookahead tree is ordered by depth then value."""

from __future__ import annotations

import numpy as np

from knotlab.core.selection.explain import PolicyChoices, feature_contributions, lookahead_tree
from knotlab.core.selection.qmodel import QModel


def test_contributions_sum_to_q_minus_bias_largest_first():
    model = QModel(
        np.array([2.0, -1.0, 0.5]),
        0.3,
        np.array([1.0, 0.0, 0.0]),
        np.array([2.0, 1.0, 1.0]),
        {"names": ["a", "b", "c"]},
        {},
    )
    phi = np.array([[5.0, 0.5, 0.1]])
    parts = feature_contributions(model, phi[0], ["a", "b", "c"])
    assert [p.name for p in parts] == ["a", "b", "c"]  # 4.0, -0.5, 0.05
    assert abs(sum(p.contribution for p in parts) + model.bias - model.q(phi)[0]) < 1e-12


def test_tree_and_agreement():
    info = {"backed_up": {0: (1, 5.0), 2: (2, -1.0), 1: (2, 3.0)}}
    assert [r[0] for r in lookahead_tree(info, ("x", "y", "z"))] == ["y", "z", "x"]
    assert PolicyChoices(1, 1, 1).agree() and not PolicyChoices(1, 2).agree()
