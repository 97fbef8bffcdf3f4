"""Browser tests: the real app (viser server, SQLite file, simulator) driven by headless Chromium.

Debian's Chromium through Playwright (never `playwright install`). Tests are marked ``browser``
and skipped, not failed, when Chromium or Playwright is missing. One app per test module (the
kernel warm-up and the 300 starts are paid once); every test opens its own browser context, so
local storage (the labeller's name) and the viser client are fresh unless a test reuses one.
Set ``KNOTLAB_SCREENSHOTS=DIR`` to keep the screenshots the tests take (the README's and
docs/app.md's come from there).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-renderer-backgrounding",
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
]


# The floating control panel: the widest ancestor of its title that is still panel-sized.
PANEL_BOX_JS = """() => {
  const title = Array.from(document.querySelectorAll('*')).find(
    (el) => el.childElementCount === 0
      && el.textContent.trim() === 'knotlab: label demonstrations');
  let box = null;
  for (let el = title; el && el !== document.body; el = el.parentElement) {
    const r = el.getBoundingClientRect();
    if (r.width > 500) break;
    box = {x: r.x, y: r.y, width: r.width, height: r.height};
  }
  return box;
}"""


def pytest_collection_modifyitems(config, items) -> None:
    """Mark every test here `browser`; skip them when the browser stack is missing."""
    try:
        import playwright.sync_api  # noqa: F401

        missing = None if shutil.which(CHROMIUM) or Path(CHROMIUM).exists() else CHROMIUM
    except ImportError:
        missing = "playwright"
    here = Path(__file__).parent
    for item in items:
        if Path(item.fspath).is_relative_to(here):
            item.add_marker(pytest.mark.browser)
            item.add_marker(pytest.mark.xdist_group("browser"))  # one worker: shares the CPU
            if missing:
                item.add_marker(pytest.mark.skip(reason=f"{missing} not installed"))


def keep_shot(page, name: str) -> bytes:
    """A screenshot of the page (PNG), also saved as NAME.png when KNOTLAB_SCREENSHOTS names a
    folder."""
    png = page.screenshot()
    folder = os.environ.get("KNOTLAB_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / f"{name}.png").write_bytes(png)
    return png


def wait_until(pred: Callable[[], object], timeout: float = 20.0, what: str = "condition"):
    """Poll ``pred`` until it is truthy; its value. Fails the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def app_args(db_url: str, **over) -> argparse.Namespace:
    """The `knotlab app` arguments of a test server (any free port, shipped files)."""
    args = dict(
        db=db_url,
        library=None,
        level="main",
        model=None,
        host="127.0.0.1",
        port=0,
        top=5,
        sim_workers=1,  # one try process: the suite shares two cores with another worker
        token=None,  # loopback: no access token asked
    )
    args.update(over)
    return argparse.Namespace(**args)


def start_app(db_url: str, **over):
    """A running LabelApp on a free loopback port, rendering light (software WebGL)."""
    from knotlab.app.cmd_app import build_app

    return build_app(app_args(db_url, **over), lite_rendering=True)


@pytest.fixture(scope="session")
def browser():
    """One headless Chromium for the session."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def db_url(tmp_path_factory) -> str:
    """A fresh SQLite file per test module."""
    return f"sqlite:///{tmp_path_factory.mktemp('appdb') / 'knotlab.db'}"


SEED_EXECUTIONS = 12  # of the shipped labels, seeded into each module's store


@pytest.fixture(scope="module")
def app(db_url, tmp_path_factory, project_root):
    """The app under test, stopped at the end of the module. Its store is seeded with the last
    few executions of the shipped labels, not all 300: a retrain in a test then takes seconds."""
    from knotlab.app.web import resources

    shipped = project_root / "results" / "labels_oracle_main.jsonl"
    lines = shipped.read_text(encoding="utf-8").splitlines(keepends=True)
    seed = tmp_path_factory.mktemp("seed") / "labels_oracle_main.jsonl"
    seed.write_text("".join(lines[:1] + lines[-SEED_EXECUTIONS:]), encoding="utf-8")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(resources, "shipped_labels_path", lambda _model, _path: seed)
        a = start_app(db_url)
    yield a
    a.stop()


@dataclass
class Tab:
    """A browser page connected to the app, and the server-side tab it became."""

    page: object
    context: object
    server_tab: object
    errors: list

    @property
    def session(self):
        """The labelling session behind the page."""
        return self.server_tab.session

    def focus_canvas(self) -> None:
        """Take keyboard focus off any field, so that a key is a hotkey (viser's hotkeys listen
        on the document and skip inputs). No click: the framed scene fills the canvas, and a
        click anywhere on it may select a candidate."""
        self.page.evaluate("() => document.activeElement && document.activeElement.blur()")

    def press(self, key: str) -> None:
        """A hotkey, as a labeller presses it."""
        self.focus_canvas()
        self.page.keyboard.press(key)

    def button(self, name: str):
        """A GUI button by its label (exact text start)."""
        return self.page.get_by_role("button", name=name)

    def screenshot(self, name: str) -> Path | None:
        """Save a screenshot when KNOTLAB_SCREENSHOTS names a folder."""
        folder = os.environ.get("KNOTLAB_SCREENSHOTS")
        if not folder:
            return None
        Path(folder).mkdir(parents=True, exist_ok=True)
        path = Path(folder) / f"{name}.png"
        toasts = self.page.locator(".mantine-Notification-root button")  # e.g. "software WebGL"
        n_open = toasts.count()
        for _ in range(n_open):
            with contextlib.suppress(Exception):
                toasts.nth(0).click(timeout=1000)
        if n_open:
            time.sleep(0.8)  # let the toasts' closing animation finish
        self.page.screenshot(path=str(path))
        return path

    def settled_camera(self, timeout: float = 10.0):
        """The browser's camera once two reads 0.3 s apart agree (a look_at may be under way)."""

        def pose() -> tuple:
            cam = self.server_tab.client.camera
            return (tuple(np.round(cam.position, 6)), tuple(np.round(cam.wxyz, 6)), cam.aspect)

        def settled():
            before = pose()
            time.sleep(0.3)
            return self.server_tab.client.camera if pose() == before else None

        return wait_until(settled, timeout, "the camera to settle")

    def project(self, points_p3: np.ndarray) -> np.ndarray:
        """Where world points appear on the page (pixels, P x 2), by the browser's camera once
        it has settled; a point behind the camera fails the test."""
        cam = self.settled_camera()
        import viser.transforms as tf

        world_from_cam = tf.SE3.from_rotation_and_translation(
            tf.SO3(np.asarray(cam.wxyz)), np.asarray(cam.position)
        )
        p = np.asarray(points_p3, float).reshape(-1, 3)
        q = np.stack([world_from_cam.inverse() @ x for x in p])
        assert (q[:, 2] > 0).all(), "a point is behind the camera"
        xy = q[:, :2] / q[:, 2:] / np.tan(cam.fov / 2)
        xy[:, 0] /= cam.aspect
        uv = (1 + xy) / 2
        box = self.page.locator("canvas").nth(1).bounding_box()
        return np.c_[box["x"] + uv[:, 0] * box["width"], box["y"] + uv[:, 1] * box["height"]]

    def free_view(self, points_p3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(which points appear inside the canvas and left of the side panel, how much of that
        free space the points spread over: a fraction across and a fraction down)."""
        uv = self.project(points_p3)
        panel = self.panel_box()
        canvas = self.page.locator("canvas").nth(1).bounding_box()
        inside = (
            (uv[:, 0] >= canvas["x"])
            & (uv[:, 0] <= panel["x"])
            & (uv[:, 1] >= canvas["y"])
            & (uv[:, 1] <= canvas["y"] + canvas["height"])
        )
        spread = np.ptp(uv, axis=0) / (panel["x"] - canvas["x"], canvas["height"])
        return inside, spread

    def click_world(self, point_3: np.ndarray) -> None:
        """Click where a world point appears on the canvas (camera from the browser)."""
        ((u, v),) = self.project(np.asarray(point_3, float)[None])
        self.page.mouse.click(u, v)

    def panel_box(self) -> dict:
        """The side panel's box on the page (x, y, width, height), measured in the browser."""
        return self.page.evaluate(PANEL_BOX_JS)


def name_field(page):
    """The name prompt's text field (viser labels it beside, not on, the input)."""
    return (
        page.locator("label", has_text="Your name")
        .locator("xpath=ancestor::div[contains(@class,'Flex-root')][1]")
        .locator("input:not([type='hidden'])")
    )


def open_page(app, context):
    """A new page of ``context`` on the app, and the server-side tab it became (nothing typed)."""
    before = {t.client.client_id for t in app.tabs()}
    page = context.new_page()
    page.goto(app.url)
    server_tab = wait_until(
        lambda: next((t for t in app.tabs() if t.client.client_id not in before), None),
        30,
        "the server to see the new tab",
    )
    return page, server_tab


def give_name(page, name: str) -> None:
    """Type ``name`` in the name prompt and click Start labelling."""
    name_field(page).fill(name)
    page.get_by_role("button", name="Start labelling").click()


def open_tab(
    browser,
    app,
    name: str | None,
    *,
    context=None,
    timeout: float = 30.0,
    submit: str = "click",
    query: str = "",
) -> Tab:
    """Open the app in a new page, give the labeller's name if asked, wait for a drawn state.

    ``submit``: how the name is sent: "click" the button, or "enter" in the field (keyboard
    only). ``query``: added to the app's URL (e.g. viser's "?fixedDpr=0.75")."""
    ctx = context or browser.new_context(viewport={"width": 1280, "height": 760})
    before = {t.client.client_id for t in app.tabs()}
    page = ctx.new_page()
    errors: list = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(app.url + query)
    page.wait_for_function(
        "() => !document.body.innerText.includes('Connecting...')", timeout=timeout * 1000
    )
    tab = wait_until(
        lambda: next((t for t in app.tabs() if t.client.client_id not in before), None),
        timeout,
        "the server to see the new client",
    )
    if name is not None:
        field = name_field(page)
        field.wait_for(timeout=timeout * 1000)
        if submit == "enter":
            field.click()
            # At a person's pace: viser drops a keystroke sent within 50 ms before the submit.
            page.keyboard.type(name, delay=120)
            page.wait_for_timeout(120)
            page.keyboard.press("Enter")
        elif submit == "button-enter":  # Tab from the field to the button, then Enter
            field.click()
            page.keyboard.type(name, delay=120)
            page.keyboard.press("Tab")
            page.keyboard.press("Enter")
        else:
            field.fill(name)
            page.get_by_role("button", name="Start labelling").click()
    wait_until(lambda: tab.ready.is_set(), timeout, "the first state to be drawn")
    return Tab(page, ctx, tab, errors)


@pytest.fixture
def tabs(browser, app) -> Iterator[Callable[..., Tab]]:
    """Factory of connected tabs; closes their contexts after the test, then checks JS errors."""
    opened: list[Tab] = []

    def make(name: str | None = None, **kw) -> Tab:
        tab = open_tab(browser, app, name, **kw)
        opened.append(tab)
        return tab

    yield make
    errors = [e for t in opened for e in t.errors]
    for t in opened:
        with contextlib.suppress(Exception):  # a test may have closed it already
            t.context.close()
    assert not errors, f"page errors: {errors}"
