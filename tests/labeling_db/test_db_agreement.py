"""The store's per-state decisions of every labeller, and claiming with an overlap policy."""

from __future__ import annotations

from knotlab.core.selection.agreement import OverlapPolicy, pair_agreement
from knotlab.core.selection.labels import DeadEndState, LabelledStep
from knotlab.labeling_db.store import StateProvenance, open_store
from tests.db_fixtures import cloud


def _label(store, episode_id: int, i: int, demo: str, outcome: str = "progressed") -> None:
    store.add_label(episode_id, LabelledStep(i, cloud(40 + i), demo, outcome))  # type: ignore[arg-type]


def test_state_visits_pair_two_labellers_on_one_start(db_url: str) -> None:
    with open_store(db_url) as store:
        (sid,) = store.add_start_states([cloud(1)], provenance=[StateProvenance("task-a", 0, 1)])
        ann = store.start_episode("ann", state_id=sid, task_id="task-a")
        bob = store.start_episode("bob", state_id=sid, task_id="task-a")
        assert ann is not None and bob is not None
        _label(store, ann.episode_id, 0, "d1")
        _label(store, ann.episode_id, 1, "d2", "knot")
        _label(store, bob.episode_id, 0, "d1")
        store.add_dead_end(
            bob.episode_id,
            DeadEndState(cloud(7)),
            provenance=StateProvenance("task-a", 1, None),
        )
        _label(store, bob.episode_id, 1, "d3", "knot")
        assert [r.state_id for r in store.start_states_to_label()] == [sid]  # none finished
        store.finish_episode(ann.episode_id)
        assert store.start_states_to_label() == []
        visits = store.state_visits()
    assert {(v.labeller, v.step_index, v.path, v.chosen_demo, v.dead_end) for v in visits} == {
        ("ann", 0, (), "d1", False),
        ("ann", 1, ("d1",), "d2", False),
        ("bob", 0, (), "d1", False),
        ("bob", 1, ("d1",), "d3", True),
    }
    pa = pair_agreement(visits, "ann", "bob")
    assert (pa.n_compared, pa.n_agree, pa.dead_end_only_b) == (2, 1, 1)


def test_claiming_offers_an_overlap_start_to_a_second_labeller_only(db_url: str) -> None:
    everything = OverlapPolicy(1.0)
    with open_store(db_url) as store:
        ids = store.add_start_states(
            [cloud(i) for i in range(2)],
            provenance=[StateProvenance(f"task-{i}", 0, i) for i in range(2)],
        )
        first = store.start_episode("ann", overlap=everything)
        assert first is not None and first.start_state_id == ids[0]
        # Default claiming never hands out a start someone holds.
        plain = store.start_episode("bob")
        assert plain is not None and plain.start_state_id == ids[1]
        store.finish_episode(plain.episode_id, status="abandoned")
        second = store.start_episode("bob", overlap=everything)
        assert second is not None and second.start_state_id == ids[0]
        # ann already holds ids[0] and the overlap is full: she gets the free one ...
        again = store.start_episode("ann", overlap=everything)
        assert again is not None and again.start_state_id == ids[1]
        # ... and a third labeller gets nothing on ids[0], which has two live episodes.
        third = store.start_episode("cy", overlap=everything)
        assert third is not None and third.start_state_id == ids[1]
        assert store.start_episode("dee", overlap=everything) is None
        assert store.start_episode("eve", overlap=OverlapPolicy(0.0)) is None


def test_an_app_episode_on_a_start_pairs_with_an_oracle_execution_of_its_task(db_url) -> None:
    """The app claims a start state (its episode names no task); the oracle's execution names
    the task: both are the same start, so their states pair for agreement."""
    from knotlab.core.selection.labels import LabelledExecution

    oracle = LabelledExecution(
        "oracle-task-a",
        "oracle",
        "oracle",
        (LabelledStep(0, cloud(40), "d1", "progressed"), LabelledStep(1, cloud(41), "d2", "knot")),  # type: ignore[arg-type]
        True,
        task_id="task-a",
    )
    with open_store(db_url) as store:
        store.add_executions([oracle])
        store.add_start_states([cloud(1)], provenance=[StateProvenance("task-a", 0, 1)])
        ann = store.start_episode("ann")  # as the app claims: no task id given
        assert ann is not None
        _label(store, ann.episode_id, 0, "d1")
        _label(store, ann.episode_id, 1, "d3", "knot")
        visits = store.state_visits()
    assert {v.start for v in visits} == {"task-a"}
    pa = pair_agreement(visits, "oracle", "ann")
    assert (pa.n_compared, pa.n_agree) == (2, 1)


def test_a_dead_end_marked_twice_is_stored_once_and_an_undo_drops_later_marks(db_url) -> None:
    with open_store(db_url) as store:
        store.add_start_states([cloud(1)], provenance=[StateProvenance("task-a", 0, 1)])
        ep = store.start_episode("ann")
        assert ep is not None
        mark = {"provenance": StateProvenance(None, 0, None), "demo_key": "d2"}
        one = store.add_dead_end(ep.episode_id, DeadEndState(cloud(7)), **mark)
        assert store.add_dead_end(ep.episode_id, DeadEndState(cloud(7)), **mark) == one
        assert store.progress("ann").dead_ends == 1
        assert store.dead_end_demos(ep.episode_id, 0) == ("d2",)
        _label(store, ep.episode_id, 0, "d1")
        later = {"provenance": StateProvenance(None, 1, None), "demo_key": "d5"}
        store.add_dead_end(ep.episode_id, DeadEndState(cloud(8)), **later)
        assert store.dead_end_demos(ep.episode_id, 1) == ("d5",)
        store.undo_last_label("ann")  # back to step 0: step 1's state is gone, so is its mark
        assert store.dead_end_demos(ep.episode_id, 1) == ()
        assert store.dead_end_demos(ep.episode_id, 0) == ("d2",)
