"""The app serving the figure-eight task (`knotlab app --task figure8`): a labeller labels its
ropes with the keyboard, Inspect explains a choice, Playback replays the stored episode; the
store holds the figure-eight's labels only."""

from __future__ import annotations

import pytest

from knotlab.app.web.session import Phase
from knotlab.core.tasks import get_task
from knotlab.labeling_db.errors import TaskMismatchError
from tests.browser.conftest import SEED_EXECUTIONS, start_app, wait_until


@pytest.fixture(scope="module")
def app(db_url, tmp_path_factory, project_root):
    """The app on the figure-eight's shipped library, start sets and model. Its store is seeded
    with a few of the model's training executions, not all 298 (as the overhand app's tests)."""
    from knotlab.app.web import resources

    shipped = project_root / "results" / "figure8" / "labels_oracle_main.jsonl"
    lines = shipped.read_text(encoding="utf-8").splitlines(keepends=True)
    seed = tmp_path_factory.mktemp("seed8") / "labels_oracle_main.jsonl"
    seed.write_text("".join(lines[:1] + lines[-SEED_EXECUTIONS:]), encoding="utf-8")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(resources, "shipped_labels_path", lambda _model, _path: seed)
        a = start_app(db_url, task="figure8")
    yield a
    a.stop()


def test_a_keyboard_labeller_labels_figure8_ropes_and_the_store_is_the_figure8s(tabs, app):
    task = get_task("figure8")
    tab = tabs("ivy", submit="enter")  # keyboard only from here on
    view = tab.session.view()
    assert view.step_limit == task.step_limit
    assert "nearest neighbour" not in view.model  # the figure-eight's shipped model ranks
    goal = f"goal: {task.description}"  # the panel says which knot is being tied
    wait_until(lambda: goal in tab.page.inner_text("body"), 30, "the goal in the panel")
    first = view.task_id
    keys = {"try": "Enter", "accept": "y", "reject": "n"}
    labelled = 0
    for _ in range(task.step_limit + 4):
        if tab.session.view().task_id != first:
            break
        tab.page.keyboard.press(keys["try"])
        wait_until(lambda: tab.session.view().phase is Phase.JUDGING, 90, "the try")
        result = tab.session.view().last_try
        assert result.stage_reached in task.stage_names  # the figure-eight's own stages
        if result.acceptable:
            tab.page.keyboard.press(keys["accept"])
            labelled += 1
        else:
            tab.page.keyboard.press(keys["reject"])
        wait_until(lambda: tab.session.view().phase is not Phase.JUDGING, 30, "the judgement")
    tab.screenshot("figure8_labelling")
    assert labelled >= 1
    assert app.store.check_task("figure8") is None  # the store is the figure-eight's
    labels = app.store.labels(labeller="ivy")
    assert len(labels) == labelled
    library_keys = {seg.key for seg in app.resources.library.segments}
    assert {label.chosen_demo for label in labels} <= library_keys  # the figure-eight's demos
    assert app.store.tasks() == {"figure8"}
    with pytest.raises(TaskMismatchError, match="figure8"):
        app.store.check_task("overhand")


def test_a_mouse_labeller_labels_a_figure8_rope_to_its_end(tabs, app):
    task = get_task("figure8")
    tab = tabs("mo")  # the name by clicking the button; no keys from here on
    first = tab.session.view().task_id
    names = {"try": "Try (Enter)", "accept": "Accept (Y)", "reject": "Reject (N)"}
    for _ in range(task.step_limit + 4):
        if tab.session.view().task_id != first:
            break
        tab.button(names["try"]).click()
        wait_until(lambda: tab.session.view().phase is Phase.JUDGING, 90, "the try")
        act = "accept" if tab.session.view().last_try.acceptable else "reject"
        tab.button(names[act]).click()
        wait_until(lambda: tab.session.view().phase is not Phase.JUDGING, 30, "the judgement")
    else:
        raise AssertionError("the episode did not end")
    done = [e for e in app.store.stored_executions() if e.execution.labeller == "mo"]
    assert any(e.status == "completed" for e in done)
