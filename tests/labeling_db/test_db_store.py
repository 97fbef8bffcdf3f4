"""The labelling store's queries on SQLite files and on a real PostgreSQL server."""

from __future__ import annotations

import sqlite3
import threading
import time

import numpy as np
import pytest

from knotlab.core.errors import KnotlabError
from knotlab.core.selection.labels import DeadEndState, LabelledStep
from knotlab.labeling_db.arrays import decode_array, encode_array
from knotlab.labeling_db.errors import (
    ConflictError,
    CorruptDatabaseError,
    DatabaseBusyError,
    InvalidRecordError,
    RecordNotFoundError,
)
from knotlab.labeling_db.store import StateProvenance, open_store
from tests.db_fixtures import cloud, make_execution

# One plugin registration, so the session-scoped PostgreSQL server is started once.


def _step(i: int, demo: str, outcome: str = "progressed", seed: int = 0) -> LabelledStep:
    return LabelledStep(i, cloud(seed + i), demo, outcome)  # type: ignore[arg-type]


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.allclose(a, b, rtol=1e-6, atol=1e-6)


def test_execution_round_trips_through_the_store(db_url: str) -> None:
    ex = make_execution("ex-1", n_steps=4, n_dead=2, seed=3)
    with open_store(db_url) as store:
        store.add_execution(ex)
        (back,) = store.training_executions()
    assert (back.execution_id, back.source, back.labeller) == ("ex-1", "oracle", "oracle")
    assert back.ended_in_knot and back.task_id == "task-3" and back.library_hash == "lib-abc123"
    assert back.metadata == {"seed": 3, "note": "test"}
    assert len(back.steps) == 4 and len(back.dead_ends) == 2
    for a, b in zip(ex.steps, back.steps, strict=True):
        assert (a.step_index, a.chosen_demo, a.outcome) == (b.step_index, b.chosen_demo, b.outcome)
        assert a.candidates == b.candidates and a.model_version == b.model_version
        assert _close(a.cloud_n3, b.cloud_n3) and _close(a.rope_nodes_k3, b.rope_nodes_k3)
        assert _close(a.candidate_scores_c, b.candidate_scores_c)
    for a, b in zip(ex.dead_ends, back.dead_ends, strict=True):
        assert _close(a.cloud_n3, b.cloud_n3) and b.rope_nodes_k3 is None


def test_human_episode_claims_labels_and_finishes(db_url: str) -> None:
    with open_store(db_url) as store:
        ids = store.add_start_states(
            [cloud(i) for i in range(3)],
            provenance=[StateProvenance("task-a", 0, 10 + i) for i in range(3)],
        )
        first = store.next_unlabelled_state()
        assert first is not None and first.state_id == ids[0]
        assert first.provenance == StateProvenance("task-a", 0, 10)
        ep = store.start_episode("alice", task_id="task-a")
        assert ep is not None and ep.start_state_id == ids[0] and ep.status == "in_progress"
        store.add_label(ep.episode_id, LabelledStep(0, first.cloud_n3, "s001-t0", "progressed"))
        store.add_dead_end(ep.episode_id, DeadEndState(cloud(50)))
        store.add_label(ep.episode_id, _step(1, "s004-t2", "knot"))
        done = store.finish_episode(ep.episode_id)
        assert done.status == "completed" and done.ended_in_knot and done.n_labels == 2
        (ex,) = store.training_executions(source="human")
        assert ex.labeller == "alice" and ex.ended_in_knot and len(ex.dead_ends) == 1
        assert [s.chosen_demo for s in ex.steps] == ["s001-t0", "s004-t2"]
        assert _close(ex.steps[0].cloud_n3, first.cloud_n3)
        prog = store.progress("alice")
        assert prog.labels == 2 and prog.outcomes["knot"] == 1 and prog.knots == 1
        assert prog.episodes_completed == 1 and prog.dead_ends == 1
        assert prog.start_states_remaining == 2 and prog.last_label_at is not None


def test_claims_skip_taken_states_and_abandoned_ones_return(db_url: str) -> None:
    with open_store(db_url) as store:
        ids = store.add_start_states([cloud(i) for i in range(2)])
        a = store.start_episode("alice")
        b = store.start_episode("bob")
        assert (a.start_state_id, b.start_state_id) == (ids[0], ids[1])
        assert store.start_episode("carol") is None and store.next_unlabelled_state() is None
        store.finish_episode(a.episode_id, status="abandoned")
        assert store.next_unlabelled_state().state_id == ids[0]
        assert store.start_episode("carol").start_state_id == ids[0]


def test_unfinished_episodes_are_left_out_of_training_by_default(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_start_states([cloud(0)])
        ep = store.start_episode("alice")
        store.add_label(ep.episode_id, _step(0, "s001-t0"))
        assert store.training_executions() == []
        (ex,) = store.training_executions(include_unfinished=True)
        assert len(ex.steps) == 1 and not ex.ended_in_knot


def test_undo_removes_exactly_the_last_label_of_that_labeller(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_start_states([cloud(i) for i in range(2)])
        ea = store.start_episode("alice").episode_id
        eb = store.start_episode("bob").episode_id
        store.add_label(ea, _step(0, "a0"))
        store.add_label(eb, _step(0, "b0"))
        store.add_label(ea, _step(1, "a1"))
        store.add_label(eb, _step(1, "b1", "knot"))  # bob labelled last, overall
        store.finish_episode(eb)
        before = {(x.labeller, x.chosen_demo) for x in store.labels()}
        undone = store.undo_last_label("alice")
        assert (undone.labeller, undone.chosen_demo, undone.step_index) == ("alice", "a1", 1)
        after = {(x.labeller, x.chosen_demo) for x in store.labels()}
        assert before - after == {("alice", "a1")} and after < before
        # alice continues from step 1 again; bob's completed episode is untouched
        store.add_label(ea, _step(1, "a1-again"))
        assert [x.chosen_demo for x in store.labels(labeller="alice")] == ["a0", "a1-again"]
        assert store.episode(eb).status == "completed" and store.episode(eb).n_labels == 2
        # undoing bob's knot reopens his episode
        assert store.undo_last_label("bob").chosen_demo == "b1"
        assert store.episode(eb).status == "in_progress" and not store.episode(eb).ended_in_knot
        assert store.undo_last_label("bob").chosen_demo == "b0"
        assert store.undo_last_label("bob") is None
        assert [x.chosen_demo for x in store.labels()] == ["a0", "a1-again"]
        with pytest.raises(RecordNotFoundError, match="nobody"):
            store.undo_last_label("nobody")


def test_undo_refuses_a_label_a_model_was_trained_on(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_execution(make_execution("ex", labeller="oracle"))
        store.save_model("v1", arrays={"w": np.ones(2)}, hyperparameters={}, feature_spec={},
                         trained_on=["ex"])  # fmt: skip
        with pytest.raises(ConflictError, match="train"):
            store.undo_last_label("oracle")
        assert len(store.labels()) == 3


def test_labels_must_come_in_step_order(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_start_states([cloud(0)])
        ep = store.start_episode("alice").episode_id
        with pytest.raises(ConflictError, match="next step_index is 0"):
            store.add_label(ep, _step(1, "x"))
        store.add_label(ep, _step(0, "x"))
        store.finish_episode(ep)
        with pytest.raises(ConflictError, match="completed"):
            store.add_label(ep, _step(1, "y"))
        with pytest.raises(RecordNotFoundError):
            store.add_label(999_999, _step(0, "x"))


def test_a_duplicate_execution_aborts_the_whole_batch(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_execution(make_execution("dup", seed=1))
        batch = [make_execution(f"new-{i}", seed=i) for i in range(3)] + [make_execution("dup")]
        with pytest.raises(ConflictError, match="dup"):
            store.add_executions(batch)
        assert [e.execution_id for e in store.training_executions()] == ["dup"]
        ids = store.add_executions(batch, if_exists="skip")
        assert ids[3] is None and all(isinstance(i, int) for i in ids[:3])
        assert len(store.training_executions()) == 4


def test_oracle_and_human_labels_are_one_data_set_with_a_source(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_execution(make_execution("o-1", seed=1))
        store.add_execution(make_execution("h-1", labeller="alice", source="human", seed=2))
        assert {e.execution_id for e in store.training_executions()} == {"o-1", "h-1"}
        assert [e.execution_id for e in store.training_executions(source="human")] == ["h-1"]
        assert [e.execution_id for e in store.training_executions(labeller="oracle")] == ["o-1"]
        assert store.stats()["labels_by_source"] == {"human": 3, "oracle": 3}


def test_models_are_saved_listed_and_loaded(db_url: str) -> None:
    with open_store(db_url) as store:
        store.add_executions([make_execution("a", seed=1), make_execution("b", seed=2)])
        w = np.random.default_rng(0).normal(size=7)
        store.save_model(
            "v1",
            arrays={"weights_d": w, "feature_mean_d": np.zeros(7)},
            hyperparameters={"C": 1.0},
            feature_spec={"kind": "reg-cost", "d": 7},
            params={"bias": 0.5},
            metrics={"train_accuracy": 0.9},
            library_hash="lib-abc123",
            trained_on=["a", "b"],
        )
        store.save_model("v2", arrays={"weights_d": 2 * w}, hyperparameters={}, feature_spec={})
        assert [m.version for m in store.list_models()] == ["v1", "v2"]
        v1 = store.load_model("v1")
        assert np.array_equal(v1.arrays["weights_d"], w)  # float64 storage: exact
        assert v1.info.params == {"bias": 0.5} and v1.info.library_hash == "lib-abc123"
        assert v1.info.n_training_labels == 6
        assert store.model_training_executions("v1") == ["a", "b"]
        assert store.load_model().info.version == "v2"
        with pytest.raises(ConflictError, match="v1"):
            store.save_model("v1", arrays={}, hyperparameters={}, feature_spec={})
        with pytest.raises(RecordNotFoundError, match="nope"):
            store.save_model("v3", arrays={}, hyperparameters={}, feature_spec={},
                             trained_on=["nope"])  # fmt: skip
        assert [m.version for m in store.list_models()] == ["v1", "v2"]
        with pytest.raises(RecordNotFoundError):
            store.load_model("v9")


def test_invalid_records_are_refused_before_writing(db_url: str) -> None:
    with open_store(db_url) as store:
        bad_meta = make_execution("m")
        object.__setattr__(bad_meta, "metadata", {"x": float("nan")})
        with pytest.raises(InvalidRecordError, match="metadata"):
            store.add_execution(bad_meta)
        with pytest.raises(InvalidRecordError, match="NaN"):
            store.save_model("v", arrays={"w": np.array([np.nan])}, hyperparameters={},
                             feature_spec={})  # fmt: skip
        with pytest.raises(InvalidRecordError):
            store.add_start_states([np.zeros((4, 2))])
        assert store.stats()["episodes"] == 0 and store.stats()["rope_states"] == 0


def test_array_codec_round_trips_and_rejects_damage() -> None:
    a = np.random.default_rng(0).normal(size=(5, 3))
    blob = encode_array(a)
    assert np.array_equal(decode_array(blob, where="t"), a.astype(np.float32).astype(float))
    assert np.array_equal(decode_array(encode_array(a, "float64"), where="t"), a)
    assert decode_array(encode_array(np.float64(2.5), "float64"), where="t").shape == ()
    for damaged, msg in [
        (blob[:-1], "needs 60 bytes, found 59"),
        (b"XX" + blob[2:], "magic"),
        (blob[:3] + b"q" + blob[4:], "dtype"),
        (blob[:7], "truncated"),
        (None, "missing"),
    ]:
        with pytest.raises(CorruptDatabaseError, match=msg):
            decode_array(damaged, where="row 7")
    with pytest.raises(InvalidRecordError, match="NaN"):
        encode_array(np.array([1.0, np.inf]))


def test_a_damaged_stored_array_names_its_row(tmp_path) -> None:
    path = tmp_path / "labels.db"
    with open_store(f"sqlite:///{path}") as store:
        store.add_execution(make_execution("ex"))
    con = sqlite3.connect(path)
    with con:
        con.execute("UPDATE rope_states SET cloud = substr(cloud, 1, 20) WHERE id = 2")
    con.close()
    with (
        open_store(f"sqlite:///{path}") as store,
        pytest.raises(CorruptDatabaseError, match=r"state id=2\) cloud") as info,
    ):
        store.training_executions()
    assert isinstance(info.value, KnotlabError)


def test_sqlite_writes_wait_for_the_lock_then_give_up_with_a_clear_error(tmp_path) -> None:
    path = tmp_path / "labels.db"
    open_store(f"sqlite:///{path}").close()
    blocker = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    blocker.execute("BEGIN IMMEDIATE")
    threading.Timer(0.4, lambda: blocker.execute("COMMIT")).start()
    with open_store(f"sqlite:///{path}", busy_timeout_s=0.05, max_attempts=20) as store:
        start = time.monotonic()
        store.add_labeller("alice")  # retried until the blocker commits
        assert time.monotonic() - start >= 0.3
        blocker.execute("BEGIN IMMEDIATE")
    with open_store(f"sqlite:///{path}", busy_timeout_s=0.02, max_attempts=2) as store:
        with pytest.raises(DatabaseBusyError, match="locked"):
            store.add_labeller("bob")
        assert store.labellers() == ["alice"]  # reads still work under a writer (WAL)
    blocker.execute("ROLLBACK")
    blocker.close()
