"""A retrain that cannot make things worse: the store is seeded with the shipped model's oracle
labels once, the active model is persisted (a reopened store and a restarted app rank with it,
not with the newest model), and a retrained model becomes active only when it is not worse than
the active one on the same held-out executions (real small models on the mini library)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from knotlab.app.web.jobs import run_retrain
from knotlab.app.web.resources import (
    AppResources,
    qmodel_from_store,
    save_qmodel_to_store,
    seed_shipped_labels,
)
from knotlab.core.selection.labels import LabelledExecution
from knotlab.core.selection.model_selection import QModelSearch
from knotlab.core.selection.qmodel import QModel
from knotlab.labeling_db.errors import InvalidRecordError, RecordNotFoundError
from knotlab.labeling_db.store import StoredExecution, open_store
from tests.db_fixtures import make_execution
from tests.minilib import mini_executions, mini_library, mini_tasks

# ----------------------------------------------------------------------------- seeding


def test_seeding_twice_adds_nothing_and_keeps_the_labels_oracle(db_url: str) -> None:
    items = [StoredExecution(make_execution(f"seed-{i}", seed=i)) for i in range(3)]
    with open_store(db_url) as store:
        first = store.seed_executions(items)
        again = store.seed_executions(items)
        stats = store.stats()
        mix = store.label_mix()
    assert (first.added_executions, first.added_labels, first.present_executions) == (3, 9, 0)
    assert (again.added_executions, again.added_labels, again.present_executions) == (0, 0, 3)
    assert stats["episodes"] == 3 and stats["labels_by_source"] == {"oracle": 9}
    assert [(sh.labeller, sh.source, sh.labels, sh.executions) for sh in mix.shares] == [
        ("oracle", "oracle", 9, 3)
    ]


def test_only_oracle_executions_seed_a_store(db_url: str) -> None:
    human = make_execution("by-hand", labeller="ann", source="human")
    with open_store(db_url) as store:
        with pytest.raises(InvalidRecordError, match="only oracle labels seed"):
            store.seed_executions([StoredExecution(make_execution("ok")), StoredExecution(human)])
        assert store.stats()["episodes"] == 0  # nothing of the batch was written


def test_the_label_mix_counts_what_a_retrain_fits_on_per_labeller(tmp_path: Path) -> None:
    with open_store(f"sqlite:///{tmp_path / 'k.db'}") as store:
        store.seed_executions([StoredExecution(make_execution("o-1"))])
        store.add_execution(make_execution("h-1", labeller="ann", source="human", seed=1))
        store.add_execution(make_execution("h-2", labeller="bo", source="human", n_steps=2))
        store.add_execution(
            StoredExecution(
                make_execution("h-3", labeller="bo", source="human", knot=False),
                status="abandoned",
            )
        )
        store.add_execution(  # dead ends only: no label, yet a retrain fits its values
            make_execution("h-4", labeller="cy", source="human", n_steps=0, knot=False, n_dead=2)
        )
        mix = store.label_mix()
    assert (mix.labels, mix.executions, mix.dead_end_only) == (8, 3, 1)
    assert [(sh.labeller, sh.labels) for sh in mix.of_source("human")] == [("ann", 3), ("bo", 2)]
    assert [(sh.labeller, sh.labels) for sh in mix.of_source("oracle")] == [("oracle", 3)]


@pytest.fixture(scope="module")
def shipped_resources() -> AppResources:
    from knotlab.app import defaults
    from knotlab.app.web.resources import load_resources

    return load_resources(defaults.LIBRARY_PATH, defaults.task_set_path("main", "train"), 5)


def test_a_fresh_store_gets_the_shipped_models_training_labels_once(
    tmp_path: Path, shipped_resources: AppResources
) -> None:
    from knotlab.app import defaults

    shipped = QModel.load(defaults.MODEL_PATH)
    with open_store(f"sqlite:///{tmp_path / 'k.db'}") as store:
        t0 = time.perf_counter()
        first = seed_shipped_labels(store, shipped_resources, shipped, defaults.MODEL_PATH)
        seconds = time.perf_counter() - t0
        again = seed_shipped_labels(store, shipped_resources, shipped, defaults.MODEL_PATH)
        stats = store.stats()
        (model,) = store.list_models()
        labellers = {sh.labeller: sh.source for sh in store.label_mix().shares}
    assert first.path is not None and first.path.name == "labels_oracle_main.jsonl"
    assert (first.added_executions, first.added_labels) == (300, 870)
    assert (again.added_executions, again.present_executions) == (0, 300)
    assert stats["labels_by_source"] == {"oracle": 870} and labellers == {"oracle": "oracle"}
    # The shipped model is stored with exactly the states it was fitted on (its recorded split).
    assert model.version == shipped.content_hash()
    assert model.n_training_labels == shipped.metrics["n_states"] == 695
    assert seconds < 30  # a few seconds on a laptop; generous for a loaded CI machine


# ----------------------------------------------------------------------------- the active model


def _save(store, version: str) -> None:
    store.save_model(
        version, arrays={"w": np.arange(3.0)}, hyperparameters={}, feature_spec={"f": 1}
    )


def test_the_active_model_survives_reopening_and_is_not_the_newest(db_url: str) -> None:
    with open_store(db_url) as store:
        assert store.active_model() is None  # a new store: never activated
        _save(store, "m-old")
        store.set_active_model("m-old", reason="chosen")
        _save(store, "m-new")  # newer, never activated
    with open_store(db_url) as store:
        active = store.active_model()
        assert active is not None and (active.version, active.reason) == ("m-old", "chosen")
        again = store.set_active_model("m-old", reason="again")  # already active: no new row
        assert again.reason == "chosen"
        store.set_active_model(None, reason="nearest neighbour")
        active = store.active_model()
        assert active is not None and active.version is None
        with pytest.raises(RecordNotFoundError, match="no model version 'm-gone'"):
            store.set_active_model("m-gone", reason="x")


def test_activate_if_active_refuses_when_someone_switched_meanwhile(db_url: str) -> None:
    with open_store(db_url) as store:
        for v in ("m-a", "m-b", "m-c"):
            _save(store, v)
        store.set_active_model("m-a", reason="start")
        assert store.activate_if_active("m-b", expected="m-a", reason="retrain") is True
        assert store.activate_if_active("m-c", expected="m-a", reason="stale retrain") is False
        active = store.active_model()
    assert active is not None and (active.version, active.reason) == ("m-b", "retrain")


# ----------------------------------------------------------------------------- the gate


def _fit(executions: list[LabelledExecution]) -> QModel:
    search = QModelSearch(C=[1000.0], D=[10.0], validation_fraction=0.0, workers=1, progress=False)
    return search.fit(executions, mini_library(3)).best_model_


def _mislabelled(ex: LabelledExecution) -> LabelledExecution:
    """The same states with another demo of the same step chosen (a labeller gone wrong)."""
    keys = mini_library(3).keys
    steps = tuple(
        dataclasses.replace(
            st,
            chosen_demo=next(
                k for k in keys if k != st.chosen_demo and k[-3:] == st.chosen_demo[-3:]
            ),
        )
        for st in ex.steps
    )
    return dataclasses.replace(ex, execution_id=f"{ex.execution_id}-wrong", steps=steps)


@pytest.fixture(scope="module")
def mini_models() -> dict[str, QModel]:
    """A model fitted on every mini label ("good") and one on mislabelled copies ("bad")."""
    labels = mini_executions(3)
    return {"good": _fit(labels), "bad": _fit([_mislabelled(e) for e in labels])}


def _store_with(tmp_path: Path, active: QModel | None):
    store = open_store(f"sqlite:///{tmp_path / 'k.db'}")
    store.add_executions(mini_executions(3))
    if active is not None:
        version = save_qmodel_to_store(store, active, mini_library(3).content_hash(), [])
        store.set_active_model(version, reason="test")
    return store


def test_a_worse_retrain_is_stored_but_the_active_model_stays(tmp_path, mini_models) -> None:
    good = mini_models["good"]
    with _store_with(tmp_path, good) as store:
        outcome = run_retrain(store, mini_library(3))
        active = store.active_model()
        stored = [m.version for m in store.list_models()]
        held_out = store.load_model(outcome.version).info.metrics["held_out"]
    verdict = outcome.verdict
    assert verdict is not None and verdict.worse_on == ("top-1",)
    assert verdict.active.version == good.content_hash() and verdict.candidate.n_states == 3
    assert verdict.candidate.top1 < verdict.active.top1
    assert not outcome.activated and "worse than" in outcome.why
    assert active is not None and active.version == good.content_hash()  # unchanged
    assert outcome.version in stored  # kept, so someone can still use it anyway
    assert held_out["active"]["top1"] == verdict.active.top1 and not held_out["not_worse"]


def test_a_retrain_not_worse_on_the_same_held_out_states_becomes_active(
    tmp_path, mini_models
) -> None:
    with _store_with(tmp_path, mini_models["bad"]) as store:
        outcome = run_retrain(store, mini_library(3))
        active = store.active_model()
    assert outcome.verdict is not None and outcome.verdict.not_worse and outcome.activated
    assert active is not None and active.version == outcome.version
    assert active.reason.startswith("retrain: not worse than")


def test_a_switch_during_the_retrain_wins_over_its_result(tmp_path, mini_models) -> None:
    with _store_with(tmp_path, mini_models["bad"]) as store:
        other = save_qmodel_to_store(store, mini_models["good"], mini_library(3).content_hash(), [])

        def switch(text: str, _fraction: float) -> None:
            if text.startswith("scoring"):  # a labeller switches while the models are scored
                store.set_active_model(other, reason="switched by hand")

        outcome = run_retrain(store, mini_library(3), on_stage=switch)
        active = store.active_model()
    assert outcome.verdict is not None and outcome.verdict.not_worse
    assert not outcome.activated and "switched during the retrain" in outcome.why
    assert active is not None and active.version == other


def test_the_held_out_executions_are_ones_the_active_model_was_not_trained_on(
    tmp_path, mini_models
) -> None:
    library = mini_library(3)
    copies = [
        dataclasses.replace(e, execution_id=f"{e.execution_id}-again") for e in mini_executions(3)
    ]
    with _store_with(tmp_path, None) as store:
        store.add_executions(copies)
        seen = [e.execution_id for e in mini_executions(3)]
        good = save_qmodel_to_store(store, mini_models["good"], library.content_hash(), seen)
        store.set_active_model(good, reason="trained on the first three")
        outcome = run_retrain(store, library)
        trained = set(store.model_training_executions(outcome.version))
    assert outcome.held_out and set(outcome.held_out) <= {e.execution_id for e in copies}
    assert not trained & set(outcome.held_out)  # the new model did not see them either
    assert trained | set(outcome.held_out) == set(seen) | {e.execution_id for e in copies}


def test_held_out_indices_leave_one_to_train_on_and_only_draw_unseen() -> None:
    from knotlab.app.web.jobs import held_out_indices

    assert held_out_indices(1, [0], 0.2, 0) == []
    assert held_out_indices(2, [0, 1], 0.2, 0) in ([0], [1])
    assert held_out_indices(10, [7, 8, 9], 0.2, 0) in ([7, 8], [7, 9], [8, 9])
    assert held_out_indices(10, [3], 0.5, 0) == [3]
    assert held_out_indices(5, [], 0.2, 0) == []
    assert held_out_indices(10, list(range(10)), 0.2, 1) == held_out_indices(
        10, list(range(10)), 0.2, 1
    )  # seeded


# ----------------------------------------------------------------------------- app start-up


def test_a_restarted_app_ranks_with_the_persisted_model_not_the_newest(
    tmp_path, mini_models
) -> None:
    from knotlab.app.web.server import load_models

    library = mini_library(3)
    url = f"sqlite:///{tmp_path / 'k.db'}"
    absent = tmp_path / "no_default_model.npz"
    with open_store(url) as store:
        good = save_qmodel_to_store(store, mini_models["good"], library.content_hash(), [])
        save_qmodel_to_store(store, mini_models["bad"], library.content_hash(), [])  # newest
        store.set_active_model(good, reason="chosen")
    for _restart in range(2):
        with open_store(url) as store:
            resources = AppResources(library, mini_tasks(3, "train", n_demos=3))
            load_models(resources, store, None, absent)
            assert resources.current.version == good
            assert {r.version for r in resources.models()} == {
                good,
                mini_models["bad"].content_hash(),
            }
    assert qmodel_from_store(open_store(url), good).content_hash() == good


def test_a_new_store_starts_with_the_shipped_default_and_persists_it(tmp_path, mini_models) -> None:
    from knotlab.app.web.server import load_models

    library = mini_library(3)
    default = mini_models["good"].save(tmp_path / "default.npz")
    with open_store(f"sqlite:///{tmp_path / 'k.db'}") as store:
        save_qmodel_to_store(store, mini_models["bad"], library.content_hash(), [])  # newest
        resources = AppResources(library, mini_tasks(3, "train", n_demos=3))
        load_models(resources, store, None, default)
        active = store.active_model()
    shipped = mini_models["good"].content_hash()
    assert resources.current.version == shipped
    assert active is not None and active.version == shipped
    assert active.reason == "the shipped default model"
