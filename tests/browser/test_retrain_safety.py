"""A retrain that cannot make things worse, in the real app: on a fresh database seeded with
the shipped model's oracle labels, a retrain on them plus a human label is kept inactive because
it ranks the held-out states worse than the shipped model, the Model tab says why and asks before
switching, and a restarted server ranks with the persisted active model, not the newest one.

The seed is the first executions of the shipped labels file (not all 300): a retrain on all of
them takes minutes, and the gate behaves the same on fewer.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest

from knotlab.app import defaults
from knotlab.app.web import resources as app_resources
from knotlab.app.web.session_records import Phase
from knotlab.core.selection.qmodel import QModel
from tests.browser.conftest import open_tab, start_app, wait_until

SEED_EXECUTIONS = 10


@pytest.fixture(scope="module")
def small_seed(tmp_path_factory, project_root) -> Path:
    """The first executions of the shipped labels file, as the app seeds them."""
    shipped = project_root / "results" / "labels_oracle_main.jsonl"
    lines = shipped.read_text(encoding="utf-8").splitlines(keepends=True)
    path = tmp_path_factory.mktemp("seed") / "labels_oracle_main.jsonl"
    path.write_text("".join(lines[: 1 + SEED_EXECUTIONS]), encoding="utf-8")
    return path


@pytest.fixture
def seeded_from(small_seed, monkeypatch) -> Path:
    """Make the app find ``small_seed`` where the shipped model's provenance points."""
    monkeypatch.setattr(app_resources, "shipped_labels_path", lambda _m, _p: small_seed)
    return small_seed


def _label_one_step(tab) -> None:
    """Try candidates in rank order until one executes and accept it, by hotkeys."""
    session = tab.session
    for _ in range(session.res.top_k):
        tab.press("Enter")
        wait_until(lambda: session.view().phase is Phase.JUDGING, 60, "the try to finish")
        if session.view().last_try.acceptable:
            tab.press("Y")
            wait_until(lambda: session.view().step_index == 1, 20, "the label to be stored")
            return
        tab.press("N")
        wait_until(lambda: session.view().phase is Phase.CHOOSING, 20, "the reject")
    raise AssertionError("no candidate of the first state executed")


def _stop(app) -> None:
    app.stop()
    app.store.close()


def test_a_worse_retrain_stays_inactive_and_a_restart_keeps_the_active_model(
    browser, tmp_path, seeded_from
) -> None:
    url = f"sqlite:///{tmp_path / 'fresh.db'}"
    shipped = QModel.load(defaults.MODEL_PATH).content_hash()
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    errors: list = []
    apps = [start_app(url, sim_workers=0)]  # tries in the server: one process less to start
    try:
        app = apps[0]
        assert app.store.stats()["labels_by_source"] == {"oracle": 30}  # seeded at start-up
        tab = open_tab(browser, app, "lea", context=context)
        errors = tab.errors
        panels = tab.server_tab.panels
        _label_one_step(tab)  # a human label: the panel's mix follows at once
        wait_until(lambda: "human: 1 (lea 1)" in panels.label_mix.content, 10, "the label mix")
        page = tab.page
        page.get_by_role("tab", name="Model").click()
        page.get_by_text("Labels a retrain fits on: 31 states").wait_for(timeout=10_000)
        assert "oracle: 30 (oracle 30)" in panels.label_mix.content

        page.get_by_role("button", name="Retrain on all labels").click()
        wait_until(lambda: app.retrain_job.last is not None, 150, "the retrain to finish")
        outcome = app.retrain_job.last.outcome
        assert outcome is not None, app.retrain_job.last.text
        verdict = outcome.verdict
        assert verdict is not None and "top-1" in verdict.worse_on, verdict
        assert verdict.active.version == shipped and verdict.candidate.top1 < verdict.active.top1
        assert not outcome.activated and app.resources.current.version == shipped
        new = outcome.version
        # Why, in the panel: both models side by side on the same held-out states.
        page.get_by_text("is stored but not active").wait_for(timeout=10_000)
        assert f"new {new[:8]}" in panels.comparison.content
        assert f"active: {shipped[:8]}" in panels.comparison.content
        assert f"| **▶ active** | {shipped[:8]} |" in panels.model_table.content
        use_anyway = page.get_by_role("button", name="Use it anyway")
        use_anyway.wait_for(timeout=10_000)
        tab.screenshot("retrain_safety")
        use_anyway.click()  # asks first; Cancel changes nothing
        page.get_by_text("Use the new model anyway?").wait_for(timeout=10_000)
        page.get_by_role("button", name="Cancel").click()
        page.get_by_text("Use the new model anyway?").wait_for(state="hidden", timeout=10_000)
        assert app.resources.current.version == shipped
        port = app.server.get_port()
        page.close()  # else it reconnects to the restarted server as a second client
        _stop(apps.pop())

        # A restart ranks with the persisted active model, not the newest stored one.
        apps.append(start_app(url, port=port, sim_workers=0))
        app = apps[0]
        assert [m.version for m in app.store.list_models()][-1] == new  # the newest
        assert app.resources.current.version == shipped
        tab = open_tab(browser, app, None, context=context)  # the browser remembers the name
        errors = tab.errors
        page, panels = tab.page, tab.server_tab.panels
        page.get_by_role("tab", name="Model").click()
        assert f"| **▶ active** | {shipped[:8]} |" in panels.model_table.content
        # Switching asks first, then updates what says which model ranks.
        label = next(r.label for r in app.model_rows() if r.version == new)
        page.get_by_label("Model", exact=True).click()
        page.get_by_role("option", name=label).click()
        wait_until(lambda: panels.model_dropdown.value == label, 10, "the dropdown choice")
        page.get_by_role("button", name="Rank with this model").click()
        page.get_by_role("button", name="Yes, rank with it").click()
        wait_until(lambda: app.resources.current.version == new, 10, "the switch")
        page.get_by_text(f"Next states are ranked by {label} active since").wait_for(timeout=10_000)
        assert "switched to it by lea" in panels.model_status.content
        # Drawn before the line above (it would race if the line came first).
        assert f"| **▶ active** | {new[:8]} |" in panels.model_table.content
        record = app.store.active_model()  # what the next restart ranks with
        assert record is not None and (record.version, record.reason) == (
            new,
            "switched to it by lea",
        )
    finally:
        for app in apps:
            with contextlib.suppress(Exception):
                _stop(app)
        context.close()
    assert not errors, errors
