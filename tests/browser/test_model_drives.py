"""Label where the model goes, in the browser: the checkbox lets the model's own choices move the
rope (fast-forwarded) until one fails or X stops it; the labeller labels that state, and the
store records which policy and model reached it."""

from __future__ import annotations

from knotlab.app.web.session_records import Phase
from knotlab.core.selection.labels import REACHED_BY
from tests.browser.conftest import wait_until
from tests.browser.test_labelling_view import assert_no_badge_under_the_caption

DRIVE_TIMEOUT = 120.0  # s: a few starts of up to five fast-forwarded model steps


def _labelled(app, labeller: str):
    """The labeller's one execution with a label (an accept that ends an episode claims the
    next start: its new, empty episode is not it)."""
    (stored,) = [
        se
        for se in app.store.stored_executions(
            labeller=labeller, statuses=("in_progress", "completed")
        )
        if se.execution.steps
    ]
    return stored


def _tick_model_mode(tab) -> None:
    tab.page.get_by_text("Label where the model goes").click()
    wait_until(lambda: tab.session.view().model_mode, 10, "the mode on")


def test_x_stops_the_model_and_the_labeller_labels_where_it_stopped(tabs, app):
    tab = tabs("uma", submit="enter")  # keyboard only
    tab.press("m")
    wait_until(lambda: tab.session.view().model_mode, 10, "M to turn the mode on")
    checkbox = tab.page.get_by_role("checkbox", name="Label where the model goes")
    wait_until(checkbox.is_checked, 10, "the checkbox ticked by M")
    wait_until(lambda: tab.session.view().phase is Phase.MODEL, 20, "the model to drive")
    wait_until(
        lambda: tab.page.get_by_role("button", name="Stop the model here (X)").is_visible(),
        10,
        "the stop button",
    )
    tab.press("x")
    view = wait_until(
        lambda: (v := tab.session.view()).phase is Phase.CHOOSING and v,
        DRIVE_TIMEOUT,
        "the model to hand the rope over",
    )
    assert "you stopped the model" in view.message  # the model was mid-step when X came
    wait_until(
        lambda: "label " in tab.page.inner_text("body") and "uma" in tab.page.inner_text("body"),
        10,
        "the hand-over said in the panel",
    )
    tab.settled_camera()
    assert_no_badge_under_the_caption(tab, "where the model stopped")
    tab.screenshot("model_stopped")
    for _ in range(len(view.candidates)):  # Enter tries; Y accepts, N rejects a failed try
        tab.press("Enter")
        judged = wait_until(
            lambda: (v := tab.session.view()).phase is Phase.JUDGING and v, 60, "the try"
        )
        if judged.last_try.acceptable:
            tab.press("y")
            break
        tab.press("n")
        wait_until(lambda: tab.session.view().phase is Phase.CHOOSING, 20, "the reject")
    wait_until(lambda: app.store.labels(labeller="uma"), 20, "the label stored")
    stored = _labelled(app, "uma")
    assert view.first_step >= 1  # X came while the first step ran: the model moved the rope
    reached = stored.execution.metadata[REACHED_BY]
    assert reached["step"] == view.first_step and reached["why"] == "you stopped the model"
    assert reached["model"] == app.resources.current.version
    assert stored.step_provenance[0].episode_step == view.first_step


def test_the_model_drives_until_its_choice_fails_then_the_labeller_takes_over(tabs, app):
    tab = tabs("vic")
    _tick_model_mode(tab)  # mouse only
    view = wait_until(
        lambda: (v := tab.session.view()).phase is Phase.CHOOSING and v.first_step >= 1 and v,
        DRIVE_TIMEOUT,
        "the model to reach a state it fails in",
    )
    assert "the model's choice failed here" in view.message
    step = f"step {view.rollout_step + 1} of {view.step_limit}"
    wait_until(lambda: step in tab.page.inner_text("body"), 10, "the panel's step")
    failed = tab.server_tab.panels.cand_buttons[0]
    wait_until(lambda: failed.disabled, 10, "the model's failed choice greyed out")
    tab.screenshot("model_handed_over")
    episode, _ = app.store.open_episode("vic")
    assert episode.first_step == view.first_step
    assert len(episode.policy_chosen) == view.first_step
    wait_until(lambda: "model's: failed" in tab.page.inner_text("body"), 10, "the grey mark")
    # The expert labels it with the mouse: the selected candidate is tried, then judged.
    for _ in range(len(view.candidates)):
        tab.button("Try (Enter)").click()
        judged = wait_until(
            lambda: (v := tab.session.view()).phase is Phase.JUDGING and v, 60, "the try"
        )
        if judged.last_try.acceptable:
            tab.button("Accept (Y)").click()
            break
        tab.button("Reject (N)").click()
        wait_until(lambda: tab.session.view().phase is Phase.CHOOSING, 20, "the reject")
    wait_until(lambda: app.store.labels(labeller="vic"), 20, "the label stored")
    stored = _labelled(app, "vic")
    reached = stored.execution.metadata[REACHED_BY]
    assert reached["chosen_before"] == list(episode.policy_chosen)
    assert reached["why"].startswith("the model's choice failed here")
    assert stored.execution.steps[0].chosen_demo == judged.last_try.demo_key


def test_the_stop_key_leaves_the_camera_where_it_is(tabs):
    """X, not S: viser moves the camera while W, A, S, D, Q or E is held, so S stopped the model
    and backed the view away from the rope the labeller was about to label."""
    import time

    import numpy as np

    tab = tabs("vic")
    camera = tab.server_tab.client.camera

    def held(key: str) -> None:
        tab.focus_canvas()
        tab.page.keyboard.down(key)
        time.sleep(0.4)
        tab.page.keyboard.up(key)

    before = np.array(camera.position)
    held("x")
    time.sleep(1.0)  # a moved camera would have reached the server by now
    assert np.allclose(camera.position, before, atol=1e-9)
    held("s")  # the key it replaced does move it: this check can see a move
    wait_until(lambda: not np.allclose(camera.position, before, atol=1e-3), 10, "S to move it")
