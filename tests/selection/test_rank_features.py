"""Cost-rank features: where each demo stands in a state's registration-cost order."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.features import LibraryFeaturizer, rank_columns
from knotlab.core.selection.model_selection import FeatureCache, QModelSearch
from tests.minilib import mini_executions, mini_library


def test_rank_columns_on_hand_made_costs() -> None:
    cost = np.array([0.4, 0.2, np.inf, 0.2, 0.8])
    cols = rank_columns(cost)
    # ranks: 0.2 (index 1) -> 0, 0.2 (index 3) -> 1 (stable), 0.4 -> 2, 0.8 -> 3, inf -> 4
    assert cols[:, 1].tolist() == [0, 1, 0, 0, 0]
    assert cols[:, 2].tolist() == [0, 0, 0, 1, 0]
    assert cols[:, 3].tolist() == [1, 0, 0, 0, 0]
    assert np.allclose(cols[:, 4], np.array([2, 0, 4, 1, 3]) / 10)
    assert np.allclose(cols[:, 0], [1.0, 0.0, 3.0, 0.0, 3.0])  # failed: the worst finite one


def test_rank_columns_cap_ranks_at_ten_and_refuse_all_failed() -> None:
    cols = rank_columns(np.arange(1.0, 21.0))
    assert cols[:, 4].max() == 1.0 and np.sum(cols[:, 4] == 1.0) == 10
    with pytest.raises(InvalidInputError, match="every demo"):
        rank_columns(np.full(3, np.inf))


def test_featurizer_adds_the_rank_columns_only_when_asked(lib) -> None:
    plain = LibraryFeaturizer(lib)
    ranked = LibraryFeaturizer(lib, rank_features=True)
    cloud = lib[0].pre_cloud_n3
    phi0, scan = plain.features(cloud)
    phi1, _ = ranked.features(cloud)
    names = ranked.feature_spec.names
    assert phi1.shape[1] == phi0.shape[1] + 5
    assert "rank_features" not in plain.spec()  # older models keep their spec and hash
    assert ranked.spec()["rank_features"] is True
    first = names.index("nn_rank_0")
    # the demo of the state's own cloud is the cheapest to register: rank 0
    assert phi1[int(np.argmin(scan.nn_cost_a)), first] == 1.0
    assert phi1[:, first].sum() == 1.0
    mask = ranked.feature_spec.indicator_mask
    assert [mask[names.index(n)] for n in ("nn_rel", "nn_rank_0", "nn_rank_10")] == [
        False,
        True,
        False,
    ]


def test_a_rank_model_round_trips_through_for_model_and_ranks_like_training() -> None:
    executions, library = mini_executions(3), mini_library(3)
    search = QModelSearch(
        C=[10.0], D=[1.0], landmarks=(0, 0), validation_fraction=0.0, workers=1,
        progress=False, rank_features=True, feature_cache=FeatureCache(),
    )  # fmt: skip
    model = search.fit(executions, library).best_model_
    featurizer = LibraryFeaturizer.for_model(library, model)
    assert featurizer.rank_features
    phi, _ = featurizer.features(executions[0].steps[0].cloud_n3)
    assert phi.shape[1] == model.n_features
    # Without the flag the featurizer's columns do not match the model: refused by name.
    spec = {k: v for k, v in model.spec_dict.items() if k != "rank_features"}
    with pytest.raises(InvalidInputError, match="retrain"):
        LibraryFeaturizer.for_model(library, dataclasses.replace(model, spec_dict=spec))
