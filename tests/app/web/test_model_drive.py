"""Label where the model goes, without a browser: the model's own choices move the rope until one
fails, the expert labels that state, and the store records how it was reached.

Real parts: the shipped library, model and training starts, the simulator and a SQLite file.
"""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.app.web.session import LabelSession, stored_nodes
from knotlab.app.web.session_records import DriveOutcome, Phase, SessionError
from knotlab.core.selection.labels import REACHED_BY
from knotlab.core.world.sim import RopeWorld
from tests.app.web.sessions import accept_something

MAX_DRIVE = 40  # drive steps a test allows before it fails (a start takes at most 5)


def _driving(store, resources, name: str = "ann") -> LabelSession:
    s = LabelSession(store, resources, name)
    s.model_mode = True
    s.start()
    assert s.view().phase is Phase.MODEL
    return s


def _drive_until(s: LabelSession, wanted: DriveOutcome) -> list[DriveOutcome]:
    """Drive (R after each hand-over) until ``wanted``; every outcome on the way."""
    seen = []
    for _ in range(MAX_DRIVE):
        out = s.drive_step()
        seen.append(out)
        if out is wanted:
            return seen
        if out is DriveOutcome.HANDED_OVER:
            s.resample()
    raise AssertionError(f"no {wanted} within {MAX_DRIVE} steps: {seen}")


def test_the_model_moves_the_rope_by_its_own_choices_until_one_fails(store, resources):
    s = _driving(store, resources)
    assert s.episode is not None and s.episode.start_state_id is not None
    start_nodes = store.get_state(s.episode.start_state_id).rope_nodes_k3  # what it is placed from
    agent = resources.current.agent  # the greedy policy with the ranking model, as a robot runs it
    _drive_until(s, DriveOutcome.HANDED_OVER)
    view = s.view()
    assert view.phase is Phase.CHOOSING and view.first_step >= 1
    assert "the model's choice failed here" in view.message
    assert 1 in view.rejected and view.selected != 1  # its failed choice is greyed out
    info, resume = store.open_episode("ann")
    assert info.first_step == view.first_step and len(info.policy_chosen) == view.first_step
    # The same rollout outside the app reaches the same rope, choice by choice.
    world = RopeWorld()
    try:
        world.reset(start_nodes)
        for step, key in enumerate(info.policy_chosen):
            decision = agent.choose(world, step_index=step)
            assert resources.library.keys[decision.action] == key
            outcome = agent.act(world, decision.action)
            world.reset(stored_nodes(outcome.nodes_after_k3))
        assert np.array_equal(world.rope_nodes(), view.rope_nodes_k3)
        # ... and the store keeps the rope it was placed from: placed again, the same state
        assert resume is not None
        world.reset(resume)
        assert np.array_equal(world.rope_nodes(), view.rope_nodes_k3)
    finally:
        world.close()
    # The expert's label is of the reached state, with how it was reached.
    accept_something(s)
    after = s.view()
    assert after.rollout_step == view.first_step + 1 and after.step_limit == view.step_limit
    (stored,) = store.stored_executions(labeller="ann", statuses=("in_progress",))
    reached = stored.execution.metadata[REACHED_BY]
    assert reached["step"] == view.first_step and reached["model"] == resources.current.version
    assert reached["policy"] == "greedy" and reached["start_task_id"] == view.task_id
    assert reached["chosen_before"] == list(info.policy_chosen)
    assert stored.step_provenance[0].episode_step == view.first_step
    assert np.allclose(stored.execution.steps[0].cloud_n3, view.cloud_n3, atol=1e-6)
    s.close()


def test_undo_and_resume_return_to_the_state_the_model_reached_bit_for_bit(store, resources):
    s = _driving(store, resources)
    _drive_until(s, DriveOutcome.HANDED_OVER)
    shown = s.view()
    accept_something(s)
    s.undo()
    back = s.view()
    assert back.phase is Phase.CHOOSING  # the expert's turn again, the model does not redrive
    assert back.first_step == shown.first_step and back.step_index == 0
    assert np.array_equal(back.rope_nodes_k3, shown.rope_nodes_k3)
    assert [c.ranked.demo_key for c in back.candidates] == [
        c.ranked.demo_key for c in shown.candidates
    ]
    assert [c.ranked.score for c in back.candidates] == [c.ranked.score for c in shown.candidates]
    # The model's failed choice is greyed out again, as it was when the rope was handed over.
    assert shown.model_failed is not None and shown.model_failed in shown.rejected
    assert (back.model_failed, back.rejected, back.selected) == (
        shown.model_failed,
        shown.rejected,
        shown.selected,
    )
    s.world.close()  # a crash before the first label: a restart resumes the reached state
    crashed = LabelSession(store, resources, "ann")
    crashed.start()
    again_shown = crashed.view()
    assert np.array_equal(again_shown.rope_nodes_k3, shown.rope_nodes_k3)
    assert (again_shown.model_failed, again_shown.rejected) == (shown.model_failed, shown.rejected)
    s = crashed
    accept_something(s)
    after = s.view()
    s.world.close()  # the tab went away without closing: a restart resumes
    again = LabelSession(store, resources, "ann")
    again.model_mode = True
    again.start()
    resumed = again.view()
    assert resumed.phase is Phase.CHOOSING and "resumed" in resumed.message
    assert (resumed.first_step, resumed.step_index) == (after.first_step, after.step_index)
    assert np.array_equal(resumed.rope_nodes_k3, after.rope_nodes_k3)
    again.close()


def test_stopping_before_the_first_step_hands_the_start_over_as_a_plain_episode(store, resources):
    s = _driving(store, resources)
    s.stop_model()
    assert s.drive_step() is DriveOutcome.HANDED_OVER
    view = s.view()
    assert view.first_step == 0 and "you stopped the model" in view.message
    assert not view.rejected  # nothing failed
    with pytest.raises(SessionError, match="not driving"):
        s.stop_model()
    accept_something(s)
    (stored,) = store.stored_executions(labeller="ann", statuses=("in_progress",))
    assert REACHED_BY not in stored.execution.metadata
    s.close()


def test_turning_the_mode_off_stops_the_model_after_its_step(store, resources):
    s = _driving(store, resources)
    with pytest.raises(SessionError, match="stop it first"):
        s.resample()  # the rope is the model's while it drives
    with pytest.raises(SessionError, match="cannot try while model"):
        s.try_selected()
    first = s.drive_step()
    s.set_model_mode(False)
    if first is DriveOutcome.CONTINUES:
        assert s.drive_step() is DriveOutcome.HANDED_OVER
        assert "you stopped the model" in s.view().message
    view = s.view()
    assert view.phase is Phase.CHOOSING and not view.model_mode
    # On again, the model does not take a rope the expert is labelling; it drives the next one.
    assert s.set_model_mode(True).phase is Phase.CHOOSING
    assert s.drive_step() is DriveOutcome.STOPPED
    assert s.resample().phase is Phase.MODEL
    s.close()


def test_a_start_the_model_ties_is_passed_over_and_not_claimed_again(store, resources):
    s = _driving(store, resources)
    seen = _drive_until(s, DriveOutcome.TIED)
    assert DriveOutcome.TIED in seen
    tied_task = s.view().message.split("from ")[1].split(" in ")[0]
    view = s.view()
    assert view.task_id != tied_task and view.phase is Phase.MODEL
    assert "tied the knot" in view.message
    abandoned = store.stored_executions(labeller="ann", statuses=("abandoned",))
    assert abandoned and all(not e.execution.steps for e in abandoned)
    for _ in range(4):  # R in model mode moves on: the tied start never comes back
        s.stop_model()
        s.drive_step()
        s.resample()
        assert s.view().task_id != tied_task
    s.close()


def test_a_model_switch_mid_drive_hands_the_rope_over_as_the_old_model_left_it(store, resources):
    s = _driving(store, resources)
    shipped = resources.current.version
    assert s.drive_step() is DriveOutcome.CONTINUES  # main-train-0000: its first step advances
    try:
        resources.use(None)  # another tab switched to nearest neighbour
        s._show_state()  # the next state is ranked by the new ranking, as the app would
        s.phase = Phase.MODEL
        assert s.drive_step() is DriveOutcome.HANDED_OVER
        assert "the ranking model changed" in s.view().message
        info, _ = store.open_episode("ann")
        (stored,) = store.stored_executions(labeller="ann", statuses=("in_progress",))
        assert info.first_step == 1
        reached = stored.execution.metadata[REACHED_BY]
        assert reached["model"] == shipped and reached["policy"] == "greedy"
    finally:
        resources.use(shipped)
        s.close()
