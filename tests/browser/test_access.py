"""An app started with an access token: a browser gets nothing of it (no scene, no panels, no
labelling state) until it gives the token, is told so on a wrong one, and is asked only once."""

from __future__ import annotations

import pytest

from tests.browser.conftest import keep_shot, start_app, wait_until

TOKEN = "pink-elephant-42"


@pytest.fixture(scope="module")
def gated(tmp_path_factory):
    """An app that asks for ``TOKEN``."""
    app = start_app(f"sqlite:///{tmp_path_factory.mktemp('gate') / 'k.db'}", token=TOKEN)
    yield app
    app.stop()
    app.store.close()


def _scene_names(page) -> list[str]:
    return page.evaluate(
        "() => { const s = window.__viserSceneTree; return s ? Object.keys(s.getState()) : []; }"
    )


def _give(page, token: str) -> None:
    field = (
        page.locator("label", has_text="Access token")
        .locator("xpath=ancestor::div[contains(@class,'Flex-root')][1]")
        .locator("input:not([type='hidden'])")
    )
    field.fill(token)
    page.get_by_role("button", name="Enter", exact=True).click()


def test_a_wrong_token_gets_nothing_the_right_one_gets_the_app_once(browser, gated):
    context = browser.new_context(viewport={"width": 1280, "height": 760})
    try:
        page = context.new_page()
        page.goto(gated.url)
        page.get_by_text("This knotlab app asks for its access token").wait_for(timeout=30_000)
        _give(page, "guess")
        page.get_by_text("That is not this app's access token").wait_for(timeout=20_000)
        keep_shot(page, "token_wrong")
        # Nothing of the app reached this browser: no tab, no labelling panel, no scene nodes.
        assert gated.tabs() == []
        body = page.locator("body").inner_text()
        assert "Who is labelling?" not in body and "knotlab: label demonstrations" not in body
        assert not [n for n in _scene_names(page) if n.startswith(("/label", "/table"))]
        _give(page, TOKEN)
        page.get_by_text("Who is labelling?").wait_for(timeout=30_000)  # now the app
        wait_until(lambda: len(gated.tabs()) == 1, 20, "the tab")
        wait_until(lambda: "/table" in _scene_names(page), 20, "the scene")
        keep_shot(page, "token_right")
        # The browser kept it: a second page of it is not asked again.
        second = context.new_page()
        second.goto(gated.url)
        wait_until(lambda: len(gated.tabs()) == 2, 30, "the second tab admitted")
        assert "asks for its access token" not in second.locator("body").inner_text()
    finally:
        context.close()


def test_another_browser_is_asked_again(browser, gated):
    context = browser.new_context(viewport={"width": 1280, "height": 760})
    try:
        page = context.new_page()
        before = len(gated.tabs())
        page.goto(gated.url)
        page.get_by_text("This knotlab app asks for its access token").wait_for(timeout=30_000)
        page.wait_for_timeout(500)
        assert len(gated.tabs()) == before
    finally:
        context.close()
