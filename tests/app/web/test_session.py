"""The labelling session without a browser: the protocol, the store rows, the shared ranking.

Real parts: the shipped library and training starts, the simulator and a SQLite file.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from knotlab.app.web.session import LabelSession
from knotlab.app.web.session_records import Phase, SessionError
from knotlab.core.machine import numeric_kind
from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.selection.decision import StepContext
from knotlab.core.selection.policies import GreedyPolicy, NearestNeighbourPolicy
from tests.app.web.sessions import accept_something


def _session(store, resources, name="ann", **kw) -> LabelSession:
    s = LabelSession(store, resources, name, **kw)
    s.start()
    return s


def test_the_ranking_shown_is_the_greedy_policys_and_nn_without_a_model(store, resources):
    s = _session(store, resources)
    view = s.view()
    ctx = StepContext(
        s.world,
        view.cloud_n3,
        s.scan,
        resources.current.featurizer,
        DemoTransferer(resources.library),
        0,
        5,
    )
    greedy = GreedyPolicy(resources.current.model).choose(ctx)
    assert view.candidates[0].ranked.demo_index == greedy.action
    order = np.argsort(-greedy.scores_a, kind="stable")[: len(view.candidates)]
    assert [c.ranked.demo_index for c in view.candidates] == list(order)
    s.close()
    try:
        resources.use(None)
        nn = _session(store, resources, "bob")
        ctx.scan, ctx.cloud_n3 = nn.scan, nn.view().cloud_n3
        ctx.world = nn.world
        assert (
            nn.view().candidates[0].ranked.demo_index == NearestNeighbourPolicy().choose(ctx).action
        )
        assert nn.view().candidates[0].ranked.q is None
        nn.close()
    finally:
        resources.use(resources.models()[0].version)


def test_accept_stores_state_choice_ranking_model_and_resume_point(store, resources):
    s = _session(store, resources)
    shown = [c.ranked.demo_key for c in s.view().candidates]
    chosen = accept_something(s)
    (label,) = store.labels(labeller="ann")
    assert label.chosen_demo == chosen and label.step_index == 0
    execution = store.training_executions(include_unfinished=True)[0]
    step = execution.steps[0]
    assert list(step.candidates) == shown and step.model_version == resources.current.version
    assert execution.metadata["numeric_kind"] == numeric_kind()  # the CPU kind that ranked it
    episode, resume = store.open_episode("ann")
    assert episode.n_labels == 1 and s.view().step_index == 1
    # the state shown is the rope placed from the stored resume point, exactly
    from knotlab.core.world.sim import RopeWorld

    with RopeWorld() as world:
        world.reset(resume)
        assert np.array_equal(world.rope_nodes(), s.view().rope_nodes_k3)


def test_reject_restores_the_state_exactly_and_selects_the_next(store, resources):
    s = _session(store, resources)
    before = s.world.rope_nodes().copy()
    s.try_selected()
    assert s.view().phase is Phase.JUDGING
    s.reject()
    view = s.view()
    assert view.phase is Phase.CHOOSING and view.rejected == {1} and view.selected == 2
    assert np.array_equal(s.world.rope_nodes(), before)
    with pytest.raises(SessionError, match="rejected"):
        s.select(1)


def test_dead_end_is_stored_and_the_state_restored(store, resources):
    s = _session(store, resources)
    s.try_selected()
    s.dead_end()
    assert store.progress("ann").dead_ends == 1
    assert s.view().phase is Phase.CHOOSING and 1 in s.view().rejected


def test_actions_out_of_turn_are_refused(store, resources):
    s = _session(store, resources)
    for action in (s.accept, s.reject, s.dead_end):
        with pytest.raises(SessionError, match="try a candidate first"):
            action()
    with pytest.raises(SessionError, match="no candidate ranked 9"):
        s.select(9)
    s.try_selected()
    with pytest.raises(SessionError, match="cannot try while judging"):
        s.try_selected()


def test_undo_goes_back_to_the_state_of_the_undone_step(store, resources):
    s = _session(store, resources)
    start_nodes = s.view().rope_nodes_k3.copy()
    task = s.view().task_id
    accept_something(s)
    s.undo()
    assert store.labels(labeller="ann") == []
    view = s.view()
    assert view.task_id == task and view.step_index == 0
    assert np.allclose(view.rope_nodes_k3, start_nodes, atol=1e-6)
    s.undo()  # nothing left on this rope: said, nothing changed
    assert "nothing to undo" in s.view().message and s.view().step_index == 0


def test_the_step_limit_ends_the_episode_and_claims_the_next_start(store, resources):
    s = _session(store, resources, max_steps=1)
    first = s.view().task_id
    accept_something(s)
    assert s.view().task_id != first and s.view().step_index == 0
    (done,) = [e for e in store.stored_executions() if e.status == "completed"]
    assert len(done.execution.steps) == 1


def test_resample_abandons_and_close_releases_an_untouched_start(store, resources):
    s = _session(store, resources)
    first = s.view().task_id
    s.resample()
    assert s.view().task_id != first
    second = s.view().task_id
    s.close()
    other = _session(store, resources, "cat")
    assert other.view().task_id in (first, second)  # both starts are free again
    other.close()
    assert store.progress("ann").episodes_abandoned == 2


def test_new_rope_moves_on_to_other_starts_then_offers_the_left_ones_again(
    tmp_path, store, resources
):
    import copy

    from knotlab.labeling_db.store import open_store

    s = _session(store, resources)
    seen = [s.view().task_id]
    for _ in range(4):  # R keeps bringing starts not seen in this tab (it used to swap two)
        s.resample()
        seen.append(s.view().task_id)
    assert len(set(seen)) == 5, seen
    s.close()
    few = copy.copy(resources)
    few.tasks = resources.tasks[:3]  # a store with three starts only
    small = open_store(f"sqlite:///{tmp_path / 'three.db'}")
    few.register_starts(small, "main")
    t = _session(small, few, "dee")
    order = [t.view().task_id]
    for _ in range(5):
        t.resample()
        order.append(t.view().task_id)
    assert len(set(order[:3])) == 3  # each start once ...
    assert set(order[3:]) <= set(order[:3])  # ... then the ones left are offered again
    t.close()
    small.close()


def test_two_sessions_claim_different_starts(store, resources):
    a, b = _session(store, resources, "ann"), _session(store, resources, "bob")
    assert a.view().task_id != b.view().task_id
    a.close()
    b.close()


def test_an_empty_name_is_refused(store, resources):
    with pytest.raises(SessionError, match="name"):
        LabelSession(store, resources, "  ")


def test_a_suggested_order_is_followed_and_never_claims_a_held_start(store, resources):
    a = _session(store, resources, "ann")  # holds the oldest start
    held = a.episode.start_state_id
    ids = sorted(st.state_id for st in store.start_states_to_label())
    order = [held, ids[-1], ids[-2]]
    b = LabelSession(store, resources, "bob")
    b.prefer = lambda: order
    b.start()
    assert b.episode.start_state_id == ids[-1]  # the first suggested start nobody holds
    c = LabelSession(store, resources, "cat")
    c.prefer = lambda: order
    c.start()
    assert c.episode.start_state_id == ids[-2]


def test_with_overlap_a_second_labeller_gets_a_start_another_holds(store, resources):
    from knotlab.core.selection.agreement import OverlapPolicy

    a = _session(store, resources, "ann")
    try:
        resources.overlap = OverlapPolicy(1.0, seed=0)  # every start offered twice
        b = _session(store, resources, "bob")
        assert b.episode.start_state_id == a.episode.start_state_id
        c = _session(store, resources, "cat")  # a third labeller is not offered it
        assert c.episode.start_state_id != a.episode.start_state_id
    finally:
        resources.overlap = None


def test_undo_on_a_fresh_rope_leaves_the_finished_episode_finished(store, resources):
    s = _session(store, resources, max_steps=1)
    accept_something(s)  # step limit 1: the episode is finished, a fresh rope is claimed
    fresh = s.view().task_id
    s.undo()
    # Said in the status area (the panel shows the message), not a toast or an exception.
    assert "nothing to undo on this rope" in s.view().message
    assert s.view().task_id == fresh and s.view().step_index == 0
    assert len(store.labels(labeller="ann")) == 1
    (done,) = [e for e in store.stored_executions() if e.status == "completed"]
    assert len(done.execution.steps) == 1


def test_a_new_rope_after_a_dead_end_clears_the_dead_end_message(store, resources):
    s = _session(store, resources)
    while not s.try_selected().acceptable:
        s.reject()
    s.dead_end()
    assert "dead end" in s.view().message
    s.resample()
    assert "dead end" not in s.view().message


def test_the_last_label_and_the_episodes_end_are_one_transaction(store, resources, monkeypatch):
    s = _session(store, resources, max_steps=1)
    episode_id = s.episode.episode_id

    def crash(*_a, **_k):  # the server dying between two transactions
        raise RuntimeError("crash")

    monkeypatch.setattr(store, "finish_episode", crash)
    with contextlib.suppress(RuntimeError):
        accept_something(s)
    info = store.episode(episode_id)
    # Never a stored last step on an episode that is still open (a resume would land on a
    # knotted rope at "step 2 of 1"): both or neither.
    assert (info.n_labels, info.status) in ((1, "completed"), (0, "in_progress"))


def test_a_try_says_the_stage_it_reached_and_whether_that_is_progress(store, resources):
    s = _session(store, resources)
    names = resources.task.stage_names
    result = s.try_selected()
    while not result.acceptable:
        s.reject()
        result = s.try_selected()
    before = resources.task.stage(s.view().rope_nodes_k3).stage
    after = int(result.outcome.stage)
    assert result.stage_before == before
    text = result.summary
    assert names[after] in text
    assert f"({result.outcome.gauss_code or 'no crossings'})" in text  # a straight rope too
    if not result.outcome.knot:
        want = "advanced" if after > before else ("nothing gained" if after == before else "went")
        assert want in text
    assert text in s.view().message
    s.accept()  # the episode's history names the stage reached, not "progressed"
    if not result.outcome.knot:  # (a knot ends the episode: a new rope, a new history)
        assert s.view().history[-1].endswith(f"{result.demo_key} ({names[after]})")


def test_a_dead_end_reads_as_a_dead_end_not_a_reject(store, resources):
    from knotlab.app.web.panels import judged_suffix

    s = _session(store, resources)
    while not s.try_selected().acceptable:
        s.reject()
    rank = s.view().last_try.rank
    s.dead_end()
    view = s.view()
    assert rank in view.dead_ends and rank in view.rejected
    assert judged_suffix(rank, view) == " · dead end"
    other = next(iter(view.rejected - view.dead_ends), None)
    if other is not None:
        assert judged_suffix(other, view) == " · rejected"


def _ranking(s: LabelSession) -> list[tuple[str, float, float]]:
    """The ranking shown: demo, score and registration cost of every candidate, exactly."""
    return [(c.ranked.demo_key, c.ranked.score, c.ranked.nn_cost) for c in s.candidates]


def test_undo_and_resume_reproduce_the_ranking_shown_bit_for_bit(tmp_path, store, resources):
    s = _session(store, resources, "uma")
    accept_something(s)  # step 1's state: placed from the stored rope
    shown, nodes = _ranking(s), s.view().rope_nodes_k3.copy()
    assert shown
    accept_something(s)
    s.undo()  # back to step 1: the same state, the same ranking, to the last bit
    assert s.view().step_index == 1
    assert np.array_equal(s.view().rope_nodes_k3, nodes)
    assert _ranking(s) == shown
    s.close()
    # a restart: a new session of the same labeller resumes that state, ranked identically
    again = _session(store, resources, "uma")
    assert again.view().step_index == 1
    assert np.array_equal(again.view().rope_nodes_k3, nodes)
    assert _ranking(again) == shown
    # and the label made there stores the ranking shown
    accept_something(again)
    (mine,) = [e for e in store.training_executions(include_unfinished=True) if e.labeller == "uma"]
    step = mine.steps[1]
    assert list(step.candidates) == [k for k, _, _ in shown]
    assert np.allclose(step.candidate_scores_c, [v for _, v, _ in shown], rtol=1e-6)


def test_a_fresh_start_is_ranked_from_the_shipped_start_scans_as_a_full_scan_would(
    tmp_path, resources
):
    from knotlab.app import defaults
    from knotlab.app.web.resources import load_resources
    from knotlab.core.machine import numeric_kind
    from knotlab.core.registration import ScanResult
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.selection.summary_ranking import SummaryScan
    from knotlab.labeling_db.store import open_store

    scanned = load_resources(defaults.LIBRARY_PATH, defaults.task_set_path("main", "train"), 5)
    scanned.use(scanned.add_model(QModel.load(defaults.MODEL_PATH), "shipped").version)
    assert "600 precomputed" in scanned.load_start_scans(defaults.scans_path("main", "train"))
    views, scans = [], []
    for res, name in ((scanned, "quick"), (resources, "full")):
        store = open_store(f"sqlite:///{tmp_path / name}.db")
        res.register_starts(store, "main")
        misses = res.current.featurizer.memo_stats[1]
        s = _session(store, res)
        views.append(s.view())
        scans.append((s.scan, res.current.featurizer.memo_stats[1] - misses))
        s.close()
        store.close()
    quick, full = views
    assert quick.task_id == full.task_id  # the same start, claimed first in both stores
    if scanned.start_scans.made_on != numeric_kind():  # summaries of another CPU kind: unused
        assert isinstance(scans[0][0], ScanResult)
        return
    assert isinstance(scans[0][0], SummaryScan) and scans[0][1] == 0  # no library scan made
    assert isinstance(scans[1][0], ScanResult)  # (maybe from the memo of an earlier test)
    assert [c.ranked for c in quick.candidates] == [c.ranked for c in full.candidates]
    for a, b in zip(quick.candidates, full.candidates, strict=True):
        assert np.array_equal(a.positions_gt3, b.positions_gt3)  # the warped paths drawn


def test_a_labelled_episode_replays_as_it_was_labelled(store, resources):
    """Playback of a store episode places each state as the app did (at rest, from the exact
    rope stored for it), so the replay meets every recorded rope and ends as the record says."""
    from knotlab.app.episodes import store_episode
    from knotlab.core.experiments.playback import resimulate

    s = _session(store, resources, "pia")
    episode_id = s.episode.episode_id
    while s.episode.episode_id == episode_id:  # to its end: a knot or the step limit
        accept_something(s)
    episode, library = store_episode(store, episode_id, resources.library)
    assert len(episode.steps) >= 2
    replay = resimulate(episode, library, dt=0.1)
    assert replay.warnings == []
    assert replay.knot == episode.recorded_knot


def test_a_stored_dead_end_is_marked_again_after_a_reload(store, resources):
    s = _session(store, resources, "dee")
    accept_something(s)  # a labelled step: a reload resumes this episode
    first = s.view().selected
    s.try_selected()
    s.dead_end()
    s.close()
    again = _session(store, resources, "dee")  # a reload: the same episode, the same state
    view = again.view()
    assert first in view.dead_ends and first in view.rejected and view.selected != first
    assert store.progress("dee").dead_ends == 1
    # marking it once more (the try simulated again) stores nothing new
    assert again.episode is not None
    (demo,) = store.dead_end_demos(again.episode.episode_id, 1)
    visits = [v for v in store.state_visits() if v.labeller == "dee"]
    assert [v.dead_end for v in visits] == [False, True]
    assert demo == next(c.ranked.demo_key for c in view.candidates if c.ranked.rank == first)


def test_a_person_cannot_label_under_the_simulated_experts_name(store, resources):
    with pytest.raises(SessionError, match="simulated expert"):
        LabelSession(store, resources, " Oracle ")
    store.add_labeller("la2x5-search", "oracle")  # any simulated expert's name in the store
    with pytest.raises(Exception, match="belongs to a simulated expert"):
        _session(store, resources, "la2x5-search")
    assert store.labellers() == ["la2x5-search"]  # nothing was filed under it
