"""What the labeller sees: a camera that frames each new state clear of the side panel, full
captions only for the selected candidate, the tried path alone after a try, every tab of a
browser framed, a palette apart from the rope, the warped demo cloud visible, no stale texts."""

from __future__ import annotations

import json
import threading

import numpy as np

from knotlab.app.web.scene import candidate_label
from knotlab.app.web.session_records import Phase
from knotlab.core.selection.scan_cache import ScanSummaryCache
from tests.browser.conftest import Tab, give_name, keep_shot, open_page, open_tab, wait_until
from tests.browser.test_labelling import _scene_has


def _scene_node(page, name: str) -> dict | None:
    """A scene node's message in the browser (None: not there)."""
    return json.loads(
        page.evaluate(
            "(n) => JSON.stringify((window.__viserSceneTree.getState()[n] || {}).message || null)",
            name,
        )
    )


def _candidate_points(view) -> tuple[np.ndarray, np.ndarray]:
    """(every candidate's markers, every candidate's path points) of a state."""
    markers, paths = [], []
    for c in view.candidates:
        markers += [np.asarray(p) for p in (*c.grasp_points, *c.release_points)]
        for g in range(2):
            if c.closed_gt[g].any():
                paths.append(np.asarray(c.positions_gt3[g]))
    return np.array(markers), np.concatenate(paths)


def assert_no_badge_under_the_caption(tab, what: str) -> None:
    """No badge is written over the selected caption: each one whose text starts under the
    caption's width lies a line's height lower on screen, or higher."""
    from knotlab.app.web.scene import TEXT_PX_PER_CHAR, badge_text, label_anchor

    view = tab.session.view()
    chosen = next(c for c in view.candidates if c.ranked.rank == view.selected)
    ((u, v),) = tab.project(label_anchor(chosen, view)[None])
    width = TEXT_PX_PER_CHAR * len(badge_text(chosen, view))
    for c in view.candidates:
        if c.ranked.rank == view.selected:
            continue
        ((bu, bv),) = tab.project(label_anchor(c, view)[None])
        if u - TEXT_PX_PER_CHAR * len(badge_text(c, view)) <= bu <= u + width:
            assert abs(bv - v) >= 14, f"{what}: badge #{c.ranked.rank} under the caption"


def assert_framed(tab, what: str, shot: str) -> None:
    """Every candidate's markers and paths project inside the canvas, left of the side panel,
    and with the rope fill a fair part of that space (not a few pixels in the middle)."""
    from knotlab.app.web.scene import TEXT_PX_PER_CHAR, badge_text, label_anchor

    view = tab.session.view()
    markers, paths = _candidate_points(view)
    chosen = next(c for c in view.candidates if c.ranked.rank == view.selected)
    # The state is drawn in the browser (its camera comes in the same batch as its captions).
    wait_until(
        lambda: (
            (n := _scene_node(tab.page, f"/label/candidates/{view.selected}/label")) is not None
            and n["props"]["text"] == badge_text(chosen, view)
        ),
        20,
        "the state drawn in the browser",
    )
    panel = tab.panel_box()
    tab.settled_camera()
    keep_shot(tab.page, shot)
    canvas = tab.page.locator("canvas").nth(1).bounding_box()
    assert panel is not None and panel["width"] < 500, panel
    for name, pts in (("marker", markers), ("path point", paths)):
        uv = tab.project(pts)
        inside = (
            (uv[:, 0] >= canvas["x"])
            & (uv[:, 0] <= panel["x"])
            & (uv[:, 1] >= canvas["y"])
            & (uv[:, 1] <= canvas["y"] + canvas["height"])
        )
        assert inside.all(), f"{what}: {np.sum(~inside)} {name}s off screen or under the panel"
    # The selected candidate's caption (drawn rightwards from its anchor) is clear of the panel.
    ((u, _v),) = tab.project(label_anchor(chosen, view)[None])
    width = TEXT_PX_PER_CHAR * len(badge_text(chosen, view))
    assert canvas["x"] <= u and u + width <= panel["x"], f"{what}: the caption is cut"
    assert_no_badge_under_the_caption(tab, what)
    uv = tab.project(np.concatenate([markers, paths, view.rope_nodes_k3]))
    spread = np.ptp(uv, axis=0) / (panel["x"] - canvas["x"], canvas["height"])
    assert spread.max() > 0.5, f"{what}: the candidates fill only {spread} of the free view"


def test_each_new_state_frames_every_candidate_clear_of_the_panel(tabs, app):
    from knotlab.core.machine import numeric_kind
    from knotlab.core.selection.summary_ranking import SummaryScan

    tab = tabs("fra")
    assert_framed(tab, "the first state", "framed_first")
    # A start is ranked from the shipped start scans where they were made on this CPU kind
    # (the five candidates drawn registered alone), else from a full scan.
    quick = app.resources.start_scans.made_on == numeric_kind()
    assert isinstance(tab.session.scan, SummaryScan) == quick
    first = tab.session.view().task_id
    tab.press("r")  # another rope
    wait_until(lambda: tab.session.view().task_id != first, 30, "a new rope")
    assert_framed(tab, "a new rope", "framed_new_rope")
    for _ in range(app.resources.top_k):  # accept the first candidate that executes
        tab.press("Enter")
        wait_until(lambda: tab.session.view().phase is Phase.JUDGING, 60, "the try")
        if tab.session.view().last_try.acceptable:
            break
        tab.press("n")
        wait_until(lambda: tab.session.view().phase is Phase.CHOOSING, 20, "the reject")
    tab.press("y")
    wait_until(lambda: tab.session.view().step_index == 1, 30, "the next state")
    assert_framed(tab, "step 2", "framed_step2")


def test_a_high_density_screen_frames_clear_of_the_panel_too(browser, tabs):
    # The browser reports its canvas in device pixels (2 per CSS pixel here), the panel is
    # sized in CSS pixels: framing must keep twice the pixels clear.
    context = browser.new_context(viewport={"width": 1280, "height": 760}, device_scale_factor=2)
    tab = tabs("hdpi", context=context)
    assert tab.server_tab.drawer.browser.device_ratio == 2.0
    assert tab.server_tab.client.camera.image_width == 2560
    assert_framed(tab, "a high-density screen", "framed_dpr2")


def test_notes_sit_at_the_bottom_left_clear_of_the_paths_above_the_rope(tabs):
    tab = tabs("nts")
    tab.press("Enter")  # a try: the status notes come and go; one stays until closed
    tab.server_tab.client.add_notification("a note", "where notes go", color="blue")
    box = wait_until(
        lambda: tab.page.get_by_text("where notes go").bounding_box(), 10, "the note shown"
    )
    assert box["y"] > 760 / 2 and box["x"] < 1280 / 3, box


def test_a_lowered_render_resolution_frames_as_the_full_one(tabs):
    # viser renders at down to 0.75 of the device's resolution while frames are slow (software
    # WebGL) and reports that canvas: the panel and the text are still CSS-sized, so the
    # camera must be the one the full resolution gets, not one that keeps 4/3 of them clear.
    from knotlab.app.web.scene import camera_pose, framed_points

    tab = tabs("dpr", query="?fixedDpr=0.75")
    tab.server_tab.drawer.frame(tab.session.view())  # at the canvas it reports now
    cam = tab.settled_camera()
    assert (cam.image_width, cam.image_height) == (960, 570)
    points, text_px = framed_points(tab.session.view())
    position, look_at = camera_pose(
        points, text_px, (1280, 760), 1.0, np.asarray(cam.up_direction), cam.fov
    )
    assert np.linalg.norm(np.asarray(cam.position) - position) < 1e-3
    assert np.linalg.norm(np.asarray(cam.look_at) - look_at) < 1e-3
    assert_framed(tab, "a lowered resolution", "framed_dpr075")


def test_only_the_selected_candidate_has_a_full_caption_the_rest_rank_badges(tabs):
    tab = tabs("cap")
    tab.press("3")
    wait_until(lambda: tab.session.view().selected == 3, 10, "rank 3 selected")
    view = tab.session.view()

    def texts() -> dict[int, str]:
        out = {}
        for c in view.candidates:
            node = _scene_node(tab.page, f"/label/candidates/{c.ranked.rank}/label")
            out[c.ranked.rank] = "" if node is None else node["props"]["text"]
        return out

    want = {
        c.ranked.rank: candidate_label(c) if c.ranked.rank == 3 else f"#{c.ranked.rank}"
        for c in view.candidates
    }
    wait_until(lambda: texts() == want, 10, f"captions {want}")
    keep_shot(tab.page, "captions")


def test_after_a_try_only_the_tried_path_is_drawn(tabs, app):
    tab = tabs("tri")
    tab.press("2")
    wait_until(lambda: tab.session.view().selected == 2, 10, "rank 2 selected")
    tab.press("Enter")
    wait_until(lambda: tab.session.view().phase is Phase.JUDGING, 60, "the try")
    others = [r for r in range(1, app.resources.top_k + 1) if r != 2]
    wait_until(
        lambda: not any(_scene_has(tab.page, f"/label/candidates/{r}") for r in others),
        10,
        "the other candidates hidden",
    )
    assert _scene_has(tab.page, "/label/candidates/2/label")
    keep_shot(tab.page, "after_try")
    tab.press("n")  # back to choosing: every candidate again
    wait_until(lambda: _scene_has(tab.page, "/label/candidates/3/label"), 10, "all shown again")


def test_a_second_tab_of_the_same_browser_starts_framed(browser, app):
    first = open_tab(browser, app, "two")
    context = first.context
    try:
        page, server_tab = open_page(app, context)  # same browser: the name is remembered
        page.get_by_role("button", name="Take it over").click(timeout=30_000)
        wait_until(lambda: server_tab.ready.is_set(), 30, "the second tab's state")
        second = Tab(page, context, server_tab, [])
        assert_framed(second, "the second tab", "second_tab")
    finally:
        context.close()


def _inspect(tab, source: str, number: int = 0):
    """Inspect a state from the Inspect tab; the loaded view."""
    panel = tab.server_tab.inspect
    tab.page.get_by_role("tab", name="Inspect").click()
    panel.source.value = source
    panel.index.value = number
    before = tab.server_tab.inspector.view
    tab.page.get_by_role("button", name="Inspect", exact=True).click()
    return wait_until(
        lambda: (v := tab.server_tab.inspector.view) is not before and v, 60, "the inspected state"
    )


def test_inspect_says_why_a_number_does_not_load_and_keeps_the_state_it_showed(tabs):
    tab = tabs("inb")
    view = _inspect(tab, "test task", 1)
    panel = tab.server_tab.inspect
    shown = wait_until(
        lambda: c if "test task 1" in (c := panel.choices.content) else None, 20, "its heading"
    )
    # (A fraction never arrives: the field rounds what is typed to its step, and shows it.)
    for value, said in ((-1, "numbered 0-"), (10**6, "numbered 0-")):
        panel.index.value = value
        tab.page.get_by_role("button", name="Inspect", exact=True).click()
        tab.page.get_by_text(said).wait_for(timeout=10_000)
        assert tab.server_tab.inspector.view is view  # nothing else was loaded
        assert panel.choices.content == shown  # its heading and table stay
    panel.index.value = 2
    tab.page.get_by_role("button", name="Inspect", exact=True).click()
    wait_until(lambda: tab.server_tab.inspector.view is not view, 60, "test task 2")
    assert panel.error.content == ""


def test_inspect_draws_the_state_it_inspects_and_labelling_draws_its_own_again(tabs, app):
    tab = tabs("ins")
    page = tab.page
    view = _inspect(tab, "test task", 3)
    assert view.label == "test task 3"
    # The 3D view shows test task 3's rope (placed at rest from its start), not the labelling one.
    assert np.abs(view.nodes_k3 - app.start_nodes("test", 3)).max() < 0.02
    assert np.abs(view.nodes_k3 - tab.session.view().rope_nodes_k3).max() > 0.05
    wait_until(lambda: _scene_has(page, "/inspect/rope"), 10, "the inspected rope drawn")
    wait_until(lambda: not tab.server_tab.drawer.label_root.visible, 10, "labelling hidden")
    uv = tab.project(view.nodes_k3)
    panel = tab.panel_box()
    assert (uv[:, 0] > 0).all() and (uv[:, 0] < panel["x"]).all(), "the rope is framed"
    assert (uv[:, 1] > 0).all() and (uv[:, 1] < 760).all()
    keep_shot(page, "inspect_test_task_3")
    page.get_by_role("button", name="Back to the labelling view").click()
    wait_until(lambda: tab.server_tab.drawer.label_root.visible, 10, "the labelling view")
    wait_until(lambda: not _scene_has(page, "/inspect/rope"), 10, "the inspected rope gone")
    assert_framed(tab, "back from Inspect", "back_from_inspect")
    # A labelling key also brings the labelling view back.
    _inspect(tab, "training start", 5)
    wait_until(lambda: _scene_has(page, "/inspect/rope"), 10, "the inspected rope drawn")
    tab.press("2")
    wait_until(lambda: tab.server_tab.drawer.label_root.visible, 10, "the labelling view")
    wait_until(lambda: not _scene_has(page, "/inspect/rope"), 10, "the inspected rope gone")


PLOT_JS = """() => {
  const imgs = Array.from(document.querySelectorAll('img')).filter((i) => i.offsetParent);
  const big = imgs.sort((a, b) => b.naturalWidth - a.naturalWidth)[0];
  if (!big) return null;
  const r = big.getBoundingClientRect();
  return {width: r.width, height: r.height, natural: big.naturalWidth};
}"""


def test_contributions_plot_reads_at_panel_width_costs_have_a_heading_and_a_legend(tabs):
    from knotlab.app.web.inspect_panel import PLOT_DPI, PLOT_FONT_PT

    tab = tabs("plo")
    page = tab.page
    _inspect(tab, "current labelling state")
    panel = tab.server_tab.inspect
    wait_until(lambda: panel.plot.image.shape[0] > 100, 30, "the contribution bar plot")
    page.get_by_text("Registration costs").scroll_into_view_if_needed()
    shown = wait_until(
        lambda: (b := page.evaluate(PLOT_JS)) and b["natural"] == panel.plot.image.shape[1] and b,
        20,
        "the plot in the page",
    )
    box = tab.panel_box()
    assert shown["width"] > 0.85 * box["width"], f"the plot is {shown} in a {box} panel"
    text_px = PLOT_FONT_PT * PLOT_DPI / 72 * shown["width"] / shown["natural"]
    assert text_px >= 10, f"feature names are {text_px:.1f} px tall on screen"
    assert panel.compare.content.startswith("**Registration costs**")
    keep_shot(page, "inspect_plot")
    page.locator("label", has_text="Show A's registration in 3D").click()
    legend = page.get_by_text("A's demo cloud warped onto this rope")
    legend.wait_for(timeout=10_000)
    legend.scroll_into_view_if_needed()
    wait_until(lambda: _scene_has(page, "/inspect/registration/warped"), 10, "registration")
    # The camera frames the rope and both clouds, left of the panel.
    view = tab.server_tab.inspector.view
    reg = tab.server_tab.inspector.registration(panel._picked()[0])
    uv = tab.project(np.concatenate([view.nodes_k3, reg.demo_cloud_n3, reg.warped_n3]))
    box = tab.panel_box()
    assert (uv[:, 0] > 0).all() and (uv[:, 0] < box["x"]).all(), "framed left of the panel"
    assert (uv[:, 1] > 0).all() and (uv[:, 1] < 760).all(), "framed top to bottom"
    keep_shot(page, "inspect_legend")


def _status(tab) -> str:
    return tab.server_tab.panels.status.content


def test_a_new_rope_after_a_dead_end_says_nothing_about_the_old_rope(tabs):
    tab = tabs("ded")
    tab.press("Enter")
    wait_until(lambda: tab.session.view().phase is Phase.JUDGING, 60, "the try")
    tab.press("f")
    wait_until(lambda: "stored a dead end" in _status(tab), 20, "the dead end said")
    first = tab.session.view().task_id
    tab.press("r")
    wait_until(lambda: tab.session.view().task_id != first, 30, "a new rope")
    new = tab.session.view().task_id
    wait_until(lambda: "task `" + new in _status(tab), 10, "the new status")
    assert "dead end" not in _status(tab)

    def page_text() -> str:
        return tab.page.locator("body").inner_text()

    wait_until(lambda: new in page_text(), 10, "the new rope in the page")
    wait_until(lambda: "dead end" not in page_text(), 5, "no word of the old rope's dead end")


def test_the_name_prompt_is_not_shown_over_connecting(browser, app):
    context = browser.new_context(viewport={"width": 1280, "height": 760})
    try:
        page, _ = open_page(app, context)
        page.get_by_text("Who is labelling?").wait_for(timeout=30_000)
        wait_until(lambda: "waiting for your name" in page.locator("body").inner_text(), 20, "st")
        assert "Connecting..." not in page.locator("body").inner_text()
        keep_shot(page, "name_prompt")
    finally:
        context.close()


def _pixels_near(png: bytes, rgb: tuple[int, int, int], tol: int = 40) -> int:
    """How many pixels of a screenshot are within ``tol`` of a colour (each channel)."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    return int((np.abs(img - np.asarray(rgb)).max(axis=2) <= tol).sum())


def test_the_warped_demo_cloud_shows_over_the_rope(tabs):
    from knotlab.app.web.scene import rank_colour

    tab = tabs("war")
    tab.press("3")  # sky blue: no other candidate's colour, nor the rope's or the cloud's
    wait_until(lambda: tab.session.view().selected == 3, 10, "rank 3 selected")
    tab.settled_camera()
    tab.page.wait_for_timeout(500)
    before = _pixels_near(tab.page.screenshot(), rank_colour(3))
    tab.page.locator("label", has_text="Show warped demo cloud").click()
    wait_until(lambda: _scene_has(tab.page, "/label/warped"), 10, "the warped cloud")
    tab.page.wait_for_timeout(800)
    after = _pixels_near(keep_shot(tab.page, "warped_cloud"), rank_colour(3))
    assert after - before > 1500, f"the warped cloud adds {after - before} pixels of its colour"


def test_a_tab_whose_episode_was_taken_over_disables_new_rope_and_undo(browser, app):
    first = open_tab(browser, app, "ovr")
    context = browser.new_context(viewport={"width": 1280, "height": 760})
    try:
        page, second = open_page(app, context)
        give_name(page, "ovr")
        page.get_by_role("button", name="Take it over").click(timeout=20_000)
        wait_until(lambda: second.ready.is_set(), 30, "the episode in the second tab")
        first.page.get_by_text("taken over in another tab").wait_for(timeout=20_000)
        for name in ("New rope (R)", "Undo last label (U)", "Try (Enter)"):
            button = first.button(name)
            wait_until(lambda b=button: b.is_disabled(), 10, f"{name} disabled")
        panels = first.server_tab.panels
        assert all(command.disabled for command in panels.commands)  # the hotkeys too
        episode = second.session.episode.episode_id
        first.press("r")
        first.press("u")
        first.page.wait_for_timeout(500)
        assert second.session.episode.episode_id == episode
        assert app.store.episode(episode).status not in ("abandoned", "completed")
        keep_shot(first.page, "taken_over")
    finally:
        context.close()
        first.context.close()


def test_a_lost_server_shows_a_banner(browser, tmp_path):
    from tests.browser.conftest import start_app

    own = start_app(f"sqlite:///{tmp_path / 'gone.db'}")
    context = browser.new_context(viewport={"width": 1280, "height": 760})
    try:
        tab = open_tab(browser, own, "off", context=context)
        banner = tab.page.get_by_role("alert").filter(has_text="server is not reachable")
        assert not banner.is_visible()
        own.stop()
        banner.wait_for(state="visible", timeout=20_000)
        box = banner.bounding_box()
        assert box["width"] > 600 and box["y"] < 5, f"the banner is {box}"  # across the top
        keep_shot(tab.page, "offline")
    finally:
        context.close()
        own.stop()
        own.store.close()


def test_suggest_shows_progress_and_cancel_stops_it(tabs, app):
    tab = tabs("sug")
    page = tab.page
    panels = tab.server_tab.panels
    # Without precomputed scans (as for a library of one's own) Suggest scans every start:
    # long enough to watch its progress and cancel it.
    shipped = app.resources.start_scans
    app.resources.start_scans = ScanSummaryCache(shipped.identity)
    page.get_by_role("tab", name="Model").click()
    page.get_by_role("button", name="Suggest what to label next").click()
    wait_until(lambda: "scoring start" in panels.suggest_status.content, 60, "progress")
    app.resources.start_scans = shipped
    assert panels.suggest_bar.visible and 0 < panels.suggest_bar.value < 100
    keep_shot(page, "suggest_progress")
    page.get_by_role("button", name="Cancel suggesting").click()
    wait_until(lambda: "cancelled after" in panels.suggest_status.content, 10, "the cancel")
    assert not app._suggesting and not panels.suggest_bar.visible
    status = panels.suggest_status.content
    page.wait_for_timeout(1000)
    assert panels.suggest_status.content == status  # stopped: no more progress reports
    assert not panels.suggest_button.disabled  # and it can be started again
    page.get_by_text("cancelled after").wait_for(timeout=10_000)
    keep_shot(page, "suggest_cancelled")
    # With the shipped scans of the level's starts nothing is scanned: every start is a hit.
    misses = shipped.misses
    page.get_by_role("button", name="Suggest what to label next").click()
    wait_until(lambda: "starts ranked by" in panels.suggest_status.content, 60, "the ranking")
    assert shipped.misses == misses and shipped.hits >= 290
    assert len(app.suggested) >= 290


def test_the_lookahead_search_shows_progress_and_cancel_leaves_the_app_usable(tabs):
    tab = tabs("sea")
    page = tab.page
    view = _inspect(tab, "current labelling state")
    panel = tab.server_tab.inspect
    wait_until(lambda: "Registration costs" in panel.compare.content, 30, "the panel filled")
    page.get_by_role("button", name="Run lookahead(2, 5)").click()
    # The candidates can still be compared while it searches (the search holds the simulator).
    panel.cand_a.value = panel.cand_a.options[2]
    wait_until(lambda: f"`{panel.cand_a.options[2]}`" in panel.compare.content, 10, "A changed")
    wait_until(lambda: view.search_expansions >= 1, 120, "the first expansion")
    assert "expansions so far" in panel.search_status.content
    keep_shot(page, "search_progress")
    page.get_by_role("button", name="Cancel the search").click()
    wait_until(lambda: view.search_cancelled, 60, "the search to stop")
    assert view.search_progress == 1.0 and view.choices.lookahead is None
    assert view.search_expansions < 10  # it stopped before the whole search
    wait_until(lambda: "search cancelled" in panel.search_status.content, 10, "said")
    assert not panel.search_button.disabled
    keep_shot(page, "search_cancelled")
    # The app stays usable: the labeller's try runs on the same simulation workers.
    tab.press("Enter")
    wait_until(lambda: tab.session.view().phase is Phase.JUDGING, 90, "a try after the cancel")


def test_the_search_shows_each_levels_choice_and_the_labeller_may_keep_it(tabs):
    tab = tabs("any")
    page = tab.page
    view = _inspect(tab, "test task", 2)
    panel = tab.server_tab.inspect
    wait_until(lambda: "Registration costs" in panel.compare.content, 30, "the panel filled")
    wait_until(lambda: "| greedy Q | `" in panel.choices.content, 10, "greedy's choice at once")
    keep = page.get_by_role("button", name="Keep the choice so far")
    # The search waits after its first level until the labeller has clicked (a person is
    # slower than level 2 here; the test must not race it).
    clicked = threading.Event()
    shown = panel._on_search

    def held_after_level_1(v) -> None:
        shown(v)
        if v.search_progress < 1.0 and (v.choices.lookahead_levels or (0,))[0] == 1:
            clicked.wait(60)

    panel._on_search = held_after_level_1
    page.get_by_role("button", name="Run lookahead(2, 5)").click()
    wait_until(lambda: "searching, level" in panel.search_status.content, 30, "the search")
    assert keep.is_disabled()  # nothing to keep before the first level ends
    wait_until(lambda: "choice after level 1" in panel.search_status.content, 120, "level 1")
    so_far = view.choices.lookahead
    assert so_far is not None and view.choices.lookahead_levels[0] == 1
    assert "after level 1 of 2" in panel.choices.content
    keep_shot(page, "search_level_1")
    wait_until(lambda: not keep.is_disabled(), 10, "Keep enabled")
    keep.click()
    wait_until(lambda: "keeping its choice" in panel.search_status.content, 10, "the click")
    clicked.set()
    wait_until(lambda: view.search_progress == 1.0, 60, "the search to stop")
    assert view.choices.lookahead == so_far and view.choices.lookahead_levels == (1, 2)
    assert not view.search_cancelled
    wait_until(lambda: "stopped after level 1 of 2" in panel.search_status.content, 10, "said")
    assert f"`{tab.server_tab.inspector.res.library.keys[so_far]}` after level 1 of 2" in (
        panel.choices.content
    )
    page.get_by_text("stopped after level 1 of 2").wait_for(timeout=10_000)  # the page too
    keep_shot(page, "search_kept_level_1")


def test_inspect_simulates_a_candidate_in_the_model_and_in_a_world_unlike_it(tabs):
    tab = tabs("cmp")
    page = tab.page
    _inspect(tab, "test task", 1)
    panel = tab.server_tab.inspect
    panel.compare_world.value = "table_friction-50"
    button = page.get_by_role("button", name="Simulate A in the model and in that world")
    button.scroll_into_view_if_needed()
    button.click()
    text = wait_until(
        lambda: "apart on average" in panel.compare_result.content and panel.compare_result.content,
        60,
        "the side-by-side outcome",
    )
    assert "the agent's model" in text and "table_friction-50" in text
    assert "stage reached" in text and "crossing code" in text
    wait_until(lambda: _scene_has(page, "/inspect/compare/model"), 10, "the model's rope after")
    wait_until(lambda: _scene_has(page, "/inspect/compare/world"), 10, "the world's rope after")
    page.get_by_text("apart on average").scroll_into_view_if_needed()
    keep_shot(page, "inspect_model_and_world")
    # Another state clears the comparison: it belonged to the state it was made from.
    _inspect(tab, "test task", 2)
    wait_until(lambda: not _scene_has(page, "/inspect/compare/model"), 10, "comparison cleared")
    assert panel.compare_result.content == ""
