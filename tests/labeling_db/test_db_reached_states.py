"""Episodes that begin where a policy's rollout left their start (label where the model goes):
the store keeps how the state was reached and the exact rope it was placed from, the first label
gets its own state row, resume and undo return to that rope, and a claim can pass starts over
(SQLite and PostgreSQL)."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.selection.labels import REACHED_BY, LabelledStep
from knotlab.labeling_db.errors import ConflictError, InvalidRecordError
from knotlab.labeling_db.store import StateProvenance, open_store
from tests.db_fixtures import cloud


def _starts(store, n: int = 3) -> list[int]:
    rng = np.random.default_rng(0)
    return store.add_start_states(
        [cloud(i) for i in range(n)],
        rope_nodes_k3=[rng.normal(size=(12, 3)) for _ in range(n)],
        provenance=[StateProvenance(f"t-{i}", 0, i) for i in range(n)],
    )


def _step(i: int, seed: int) -> LabelledStep:
    rng = np.random.default_rng(seed)
    return LabelledStep(
        step_index=i,
        cloud_n3=rng.normal(size=(30, 3)),
        chosen_demo="s001-t1",
        outcome="progressed",
        rope_nodes_k3=rng.normal(size=(12, 3)),
        candidates=("s001-t1", "s002-t2"),
        candidate_scores_c=np.array([0.5, 0.1]),
        model_version="m-1",
    )


REACHED = {"policy": "greedy", "model": "m-1", "step": 2, "chosen_before": ["s003-t0", "s004-t1"]}


def test_a_reached_state_is_kept_exactly_and_labelled_on_its_own_row(db_url: str) -> None:
    nodes = np.random.default_rng(5).normal(size=(12, 3)) * 0.1 + 1e-9  # not float32-exact
    with open_store(db_url) as store:
        start, *_ = _starts(store)
        ep = store.start_episode("ann", state_id=start)
        marked = store.mark_reached(ep.episode_id, nodes, REACHED)
        assert (marked.first_step, marked.policy_chosen) == (2, ("s003-t0", "s004-t1"))
        info, resume = store.open_episode("ann")
        assert info.first_step == 2 and info.n_labels == 0
        assert resume is not None and np.array_equal(resume, nodes)  # float64, bit for bit
        label = store.add_label(
            ep.episode_id, _step(0, 1), provenance=StateProvenance("t-0", 2, None)
        )
        assert label.state_id != start  # the first label's state is the reached one
        assert store.get_state(label.state_id).role == "step"
        (stored,) = store.stored_executions(labeller="ann", statuses=("in_progress",))
        assert stored.execution.metadata[REACHED_BY] == REACHED
        assert stored.step_provenance[0].episode_step == 2
        assert np.allclose(stored.execution.steps[0].cloud_n3, _step(0, 1).cloud_n3, atol=1e-6)
        # undoing the first label returns to the reached rope, exactly
        store.undo_last_label("ann")
        info, resume = store.open_episode("ann")
        assert info.n_labels == 0 and info.first_step == 2
        assert resume is not None and np.array_equal(resume, nodes)


def test_only_a_fresh_episode_begins_at_a_reached_state(db_url: str) -> None:
    nodes = np.zeros((12, 3))
    with open_store(db_url) as store:
        start, *_ = _starts(store)
        ep = store.start_episode("ann", state_id=start)
        with pytest.raises(InvalidRecordError, match="step >= 1"):
            store.mark_reached(ep.episode_id, nodes, {**REACHED, "step": 0})
        with pytest.raises(InvalidRecordError, match="resume rope nodes"):
            store.mark_reached(ep.episode_id, np.full((12, 3), np.nan), REACHED)
        store.add_label(ep.episode_id, _step(0, 1))
        with pytest.raises(ConflictError, match="fresh in-progress episode"):
            store.mark_reached(ep.episode_id, nodes, REACHED)
        info, _ = store.open_episode("ann")
        assert info.first_step == 0  # nothing was written by the refused calls


def test_a_claim_passes_over_excluded_starts(db_url: str) -> None:
    with open_store(db_url) as store:
        a, b, c = _starts(store)
        got = store.start_episode("ann", exclude=[a, b])
        assert got is not None and got.start_state_id == c
        assert store.start_episode("bo", exclude=[a, b]) is None  # c is held, a and b excluded
        other = store.start_episode("bo")
        assert other is not None and other.start_state_id == a


def test_a_reached_episodes_states_pair_with_the_same_states_of_other_labellers(
    db_url: str,
) -> None:
    from knotlab.core.selection.agreement import pair_agreement

    with open_store(db_url) as store:
        start, *_ = _starts(store)
        ann = store.start_episode("ann", state_id=start, task_id="t-0")
        for i, demo in enumerate(("s003-t0", "s004-t1", "s001-t1")):
            store.add_label(ann.episode_id, _step_choosing(i, demo))
        cyd = store.start_episode("cyd", state_id=start, task_id="t-0")
        store.mark_reached(cyd.episode_id, np.zeros((12, 3)), REACHED)  # after s003, s004
        store.add_label(cyd.episode_id, _step_choosing(0, "s001-t1"))
        visits = [v for v in store.state_visits() if v.labeller == "cyd"]
        assert [(v.step_index, v.path, v.chosen_demo) for v in visits] == [
            (2, ("s003-t0", "s004-t1"), "s001-t1")
        ]
        pa = pair_agreement(store.state_visits(), "ann", "cyd")
        assert (pa.n_compared, pa.n_agree) == (1, 1)


def _step_choosing(i: int, demo: str) -> LabelledStep:
    step = _step(i, i)
    return LabelledStep(
        step.step_index,
        step.cloud_n3,
        demo,
        step.outcome,
        step.rope_nodes_k3,
        step.candidates,
        step.candidate_scores_c,
        step.model_version,
    )
