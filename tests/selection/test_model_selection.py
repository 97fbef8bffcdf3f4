"""QModelSearch (model selection in core), the observation model a model carries, the registry."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.demos.library import DemoLibrary, DemoSegment
from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.learner import MaxMarginQLearner
from knotlab.core.selection.model_selection import (
    QModelSearch,
    SelectBy,
    split_executions,
    value_metrics,
)
from knotlab.core.selection.policies import policy_config
from knotlab.core.world.observation import ObservationModel, centreline_points
from tests.minilib import mini_executions, mini_library


@pytest.mark.parametrize("n, frac", [(2, 0.5), (10, 0.2), (7, 0.0), (30, 0.3)])
def test_split_is_by_execution_disjoint_covering_and_seeded(n: int, frac: float) -> None:
    train, val = split_executions(n, frac, seed=4)
    assert set(train).isdisjoint(val) and sorted([*train, *val]) == list(range(n))
    assert (len(val) >= 1) == (frac > 0)
    again = split_executions(n, frac, seed=4)
    assert np.array_equal(train, again[0]) and np.array_equal(val, again[1])


def test_split_rejects_a_fraction_of_one() -> None:
    with pytest.raises(InvalidInputError, match="validation fraction"):
        split_executions(5, 1.0, seed=0)


def _small_search() -> QModelSearch:
    """A 2 x 2 grid with 2 landmarks on the 3-demo mini library, one execution held out."""
    return QModelSearch(
        C=[1.0, 100.0],
        D=[1.0, 10.0],
        landmarks=(2, 0),
        validation_fraction=0.34,
        workers=1,
        progress=False,
    )


@pytest.fixture(scope="module")
def search() -> QModelSearch:
    return _small_search().fit(mini_executions(3), mini_library(3))


def test_search_fits_every_grid_point_and_keeps_the_best(search: QModelSearch) -> None:
    assert {(p.C, p.D) for p in search.sweep_} == {
        (1.0, 1.0),
        (1.0, 10.0),
        (100.0, 1.0),
        (100.0, 10.0),
    }
    best = max(search.sweep_, key=lambda p: p.score(SelectBy.TOP1))
    assert search.best_params_ == {"C": best.C, "D": best.D}
    assert search.best_model_.metrics["training_run"]["C"] == best.C
    assert search.n_train_executions_ + search.n_validation_executions_ == 3
    assert search.n_validation_executions_ == 1
    assert len(search.landmarks_) == 2  # sampled from the training split only


def test_search_is_reproducible_with_the_same_random_state(search: QModelSearch) -> None:
    again = _small_search().fit(mini_executions(3), mini_library(3))
    assert again.best_model_.content_hash() == search.best_model_.content_hash()


def test_search_refuses_bad_grids() -> None:
    with pytest.raises(InvalidInputError, match="C must be"):
        QModelSearch(C=[-1.0], progress=False).fit(mini_executions(2), mini_library(2))
    with pytest.raises(InvalidInputError, match="no labelled executions"):
        QModelSearch(progress=False).fit([], mini_library(2))


def test_value_auc_is_the_pairwise_probability(search: QModelSearch) -> None:
    from knotlab.core.selection.learner import LabelledState, TrainingData

    model = search.best_model_
    d = model.n_features
    rng = np.random.default_rng(0)
    states = tuple(LabelledState(rng.normal(size=(4, d)), 0, np.ones(4), i, 0) for i in range(5))
    dead = tuple(rng.normal(size=(4, d)) for _ in range(6))
    data = TrainingData(states, (), (), dead)
    v_s = np.array([model.q(s.phi_ad).max() for s in states])
    v_d = np.array([model.q(p).max() for p in dead])
    brute = (v_s[:, None] > v_d[None]).mean() + 0.5 * (v_s[:, None] == v_d[None]).mean()
    assert value_metrics(model, data)["value_auc"] == pytest.approx(brute)


def _centreline_copy(lib: DemoLibrary) -> DemoLibrary:
    segs = [
        DemoSegment(
            s.key,
            s.start_index,
            s.step_index,
            s.pre_nodes_k3,
            centreline_points(s.pre_nodes_k3),
            s.trajectory,
            s.post_nodes_k3,
            s.metadata,
        )
        for s in lib
    ]
    return DemoLibrary(segs, {**lib.metadata, "observation_model": "centreline"})


def test_a_model_is_refused_with_a_library_of_another_observation_model() -> None:
    cloud_lib = mini_library(2)
    featurizer = LibraryFeaturizer(cloud_lib)
    model = MaxMarginQLearner(C=10.0).fit(mini_executions(2), featurizer)
    assert model.feature_spec.observation_model == "cloud"
    centre_lib = _centreline_copy(cloud_lib)
    assert LibraryFeaturizer(centre_lib).observation is ObservationModel.CENTRELINE
    with pytest.raises(InvalidInputError, match="'cloud' observations"):
        LibraryFeaturizer.for_model(centre_lib, model)


@pytest.mark.parametrize(
    "name, kind, needs_model, simulates, depth, width",
    [
        ("nn", "nn", False, False, 0, 0),
        ("greedy", "greedy", True, False, 0, 0),
        ("oracle", "oracle", False, True, 0, 0),
        ("la2x5", "lookahead", True, True, 2, 5),
        ("la1x10", "lookahead", True, True, 1, 10),
    ],
)
def test_policy_registry_parses_names_once(name, kind, needs_model, simulates, depth, width):
    cfg = policy_config(name)
    assert (cfg.kind, cfg.needs_model, cfg.simulates, cfg.depth, cfg.width) == (
        kind,
        needs_model,
        simulates,
        depth,
        width,
    )


@pytest.mark.parametrize("name", ["la0x5", "la2x0", "la", "lax5", "Greedy", "knn", ""])
def test_policy_registry_rejects_bad_names_naming_them(name: str) -> None:
    with pytest.raises(InvalidInputError, match="unknown policy"):
        policy_config(name)


def test_a_learned_policy_needs_a_model() -> None:
    with pytest.raises(InvalidInputError, match="needs a trained QModel"):
        policy_config("la2x5").build(None)


def test_a_portable_search_fits_the_portable_columns_alone_and_places_them_on_the_library():
    from knotlab.core.selection.transfer import (
        PortableColumns,
        is_portable,
        project_training_data,
        transplant,
    )

    library, executions = mini_library(3), mini_executions(3)
    search = QModelSearch(
        C=[10.0], D=[1.0], landmarks=(2, 0), portable=True, validation_fraction=0.34,
        workers=1, progress=False,
    )  # fmt: skip
    model = search.fit(executions, library).best_model_
    spec = LibraryFeaturizer(library).feature_spec
    assert model.feature_spec.names == spec.names and model.landmarks is None  # none sampled
    assert model.metrics["portable"] and model.metrics["training_run"]["portable"]
    zero = [i for i, n in enumerate(spec.names) if not is_portable(n)]
    assert zero and not np.any(model.weights_d[zero])
    # The same fit by hand: the training split's states on the portable columns, transplanted.
    from knotlab.core.selection.learner import build_training_data

    train_idx, _ = split_executions(len(executions), 0.34, 0)
    data = build_training_data([executions[i] for i in train_idx], LibraryFeaturizer(library))
    columns = PortableColumns.of(spec)
    by_hand = MaxMarginQLearner(C=10.0, D=1.0).fit(
        project_training_data(data, spec.names, columns.names), columns
    )
    assert transplant(by_hand, spec).content_hash() == model.content_hash()
