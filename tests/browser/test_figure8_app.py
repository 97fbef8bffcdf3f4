"""The app serving the figure-eight task (`knotlab app --task figure8`): a labeller labels its
ropes with the keyboard and with the mouse, Inspect explains a choice with the figure-eight's
demos, Playback offers and replays the figure-eight's own bench runs; the store holds the
figure-eight's labels only."""

from __future__ import annotations

import pytest

from knotlab.app.web.playback_panel import STORE
from knotlab.app.web.session_records import Phase
from knotlab.core.tasks import get_task
from knotlab.labeling_db.errors import TaskMismatchError
from tests.browser.conftest import SEED_EXECUTIONS, start_app, wait_until
from tests.browser.test_labelling import _scene_has


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


def test_inspect_explains_a_figure8_choice_with_its_own_demos(tabs, app):
    tab = tabs("ina")
    page = tab.page
    page.get_by_role("tab", name="Inspect").click()
    page.get_by_role("button", name="Inspect", exact=True).click()
    panel = tab.server_tab.inspect
    wait_until(lambda: "| nearest neighbour |" in panel.choices.content, 60, "the choices shown")
    view = tab.server_tab.inspector.view
    keys = app.resources.library.keys
    assert view.choices.nn is not None and view.choices.greedy is not None
    assert {r.demo_key for r in view.ranking} <= set(keys)  # the figure-eight's demos, ranked
    assert view.ranking[0].demo_key == keys[view.choices.greedy]  # by its model: greedy's first
    wait_until(lambda: _scene_has(page, "/inspect/rope"), 20, "the inspected rope drawn")
    tab.screenshot("figure8_inspect")
    page.get_by_role("button", name="Back to the labelling view").click()
    wait_until(lambda: tab.server_tab.drawer.label_root.visible, 10, "the labelling view back")


def test_playback_offers_and_replays_the_figure8s_own_runs(tabs, project_root):
    tab = tabs("pia")
    page = tab.page
    panel = tab.server_tab.playback
    page.get_by_role("tab", name="Playback").click()
    runs = [str(p) for p in panel.source.options if p != STORE]
    assert runs and all("/figure8/" in p for p in runs)  # never the overhand knot's runs
    assert panel.source.value == str(project_root / "results" / "figure8" / "table1_main")
    assert panel.task.value.startswith("main-test-")  # an episode that source holds
    page.get_by_role("button", name="Load and replay").click()
    wait_until(lambda: panel.replay is not None, 120, "the replay")
    assert panel.library.task == "figure8" and "no episode" not in panel.status.content
    from knotlab.app.web.playback_panel import FRAME_DT
    from knotlab.core.experiments.playback import resimulate

    want = resimulate(panel.episode, panel.library, dt=FRAME_DT)  # the panel shows the core's
    assert panel.replay.knot == want.knot and list(panel.replay.warnings) == list(want.warnings)
    wait_until(lambda: _scene_has(page, "/playback/rope"), 30, "the replayed rope in the browser")
    tab.screenshot("figure8_playback")
    # A stored labelling episode of the figure-eight plays with the figure-eight's library too.
    panel.source.value = STORE
    panel.task.value = "1"
    panel.replay = None
    page.get_by_role("button", name="Load and replay").click()
    wait_until(lambda: panel.replay is not None, 120, "the stored episode's replay")
    assert panel.library.task == "figure8" and "cannot play" not in panel.status.content
