"""Latency of the labelling app as a labeller feels it, in headless Chromium on this machine.

Prints: page ready (goto until the first state's candidates are in the scene); new state to
candidates drawn (R: claim a start, observe, scan the library, rank, draw; median and p95);
Enter to the first animation frame; accept to the next state drawn; Suggest over all unlabelled
starts (first click, then again). Then, with 3 more labellers at once (driven server-side by
threads: try, judge, next, with --think s between their actions; tabs of the same browser, or
each in its own browser with --own-browsers; their screens rendered on this machine, or with
--others-screens elsewhere hidden as on their own machines): new state, Enter, accept, Suggest
and a first visit's page ready. New states are measured back to back (skipping through starts)
and after the labeller looks at each for --look s. Targets: candidates drawn within 0.3 s
median, 0.5 s p95; accept within 1 s; page ready within 3 s; Suggest within 10 s; with 4
labellers the same within 2x.
Usage: python bench/app_latency.py [--samples 20] [--tries 5] [--others-screens elsewhere]
       [--visits 3] [--first-visits 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from knotlab.core.machine import machine_line
from tests.browser.conftest import CHROMIUM, CHROMIUM_ARGS, open_tab, start_app, wait_until


def _status(page) -> str:
    return page.evaluate("() => document.body.innerText")


SERVER: dict[str, list[float]] = {}  # server-side share of each measure (rank + draw calls)


def measure_new_state(tab, n: int, label: str = "", look: float = 0.0) -> list[float]:
    """Seconds from pressing R to the new start's candidates drawn (status text changed);
    ``look``: seconds the labeller looks at each drawn state before the next R (0: back to back,
    as when skipping through starts; the previous state's last frames are still rendering)."""
    out = []
    server = SERVER.setdefault(label, [])
    for _ in range(n):
        time.sleep(look)
        before = tab.session.view().task_id
        tab.focus_canvas()
        t0 = time.perf_counter()
        tab.page.keyboard.press("r")
        wait_until(lambda b=before: tab.session.view().task_id != b, 10, "new state")
        new = tab.session.view().task_id
        tab.page.wait_for_function(
            "(t) => document.body.innerText.includes(t) && window.__viserSceneTree"
            " && window.__viserSceneTree.getState()['/label/candidates/1/label']",
            arg=new,
            timeout=10000,
        )
        out.append(time.perf_counter() - t0)
        server.append(tab.server_tab.timings.get("action_to_drawn_s", float("nan")))
    return out


ACCEPTED: dict[str, list[float]] = {}  # the server's share of each accept
RANKED: dict[str, list[float]] = {}  # of which ranking the next state (its scan, if not ready)


def measure_accept(tab, n: int, label: str = "") -> list[float]:
    """Seconds from Y (accept a try) to the next state's candidates drawn in the browser."""
    out = []
    server, ranked = ACCEPTED.setdefault(label, []), RANKED.setdefault(label, [])
    while len(out) < n:
        tab.focus_canvas()
        tab.page.keyboard.press("Enter")
        wait_until(lambda: tab.session.view().phase.value == "judging", 60, "try end")
        if not tab.session.view().last_try.acceptable:
            tab.page.keyboard.press("n")
            wait_until(lambda: tab.session.view().phase.value == "choosing", 20, "reject")
            continue
        time.sleep(0.5)  # the expert looks at the result (and the scan-ahead runs)
        before = (tab.session.view().task_id, tab.session.view().step_index)
        t0 = time.perf_counter()
        tab.page.keyboard.press("y")
        wait_until(
            lambda b=before: (tab.session.view().task_id, tab.session.view().step_index) != b,
            20,
            "next state",
        )
        view = tab.session.view()
        tab.page.wait_for_function(
            "(t) => document.body.innerText.includes(t)",
            arg=f"step {view.step_index + 1} of",
            timeout=10000,
        )
        out.append(time.perf_counter() - t0)
        server.append(tab.server_tab.timings.get("action_to_drawn_s", float("nan")))
        ranked.append(tab.session.rank_s)
    return out


SIMULATED: dict[str, list[float]] = {}  # server side: Enter to the first simulated frame sent


def measure_try(tab, n: int, label: str = "") -> list[float]:
    """Seconds from Enter to the first animation frame in the browser (a gripper drawn: the
    path's start at once, then the simulated frames)."""
    out = []
    simulated = SIMULATED.setdefault(label, [])
    for _ in range(n):
        tab.focus_canvas()
        t0 = time.perf_counter()
        tab.page.keyboard.press("Enter")
        tab.page.wait_for_function(
            "() => { const s = window.__viserSceneTree && window.__viserSceneTree.getState();"
            " return s && (s['/label/grippers/left'] || s['/label/grippers/right']); }",
            timeout=20000,
        )
        out.append(time.perf_counter() - t0)
        wait_until(lambda: tab.session.view().phase.value == "judging", 60, "try end")
        simulated.append(tab.server_tab.timings.get("try_to_first_frame_s", float("nan")))
        tab.page.keyboard.press("r")
        wait_until(lambda: tab.session.view().phase.value == "choosing", 20, "next")
    return out


def measure_suggest(tab, app, n: int) -> list[float]:
    """Seconds from clicking Suggest to every unlabelled start ranked (first click: no landmark
    weights known yet; later ones: all known)."""
    page, panels = tab.page, tab.server_tab.panels
    page.get_by_role("tab", name="Model").click()
    out = []
    for _ in range(n):
        panels.suggest_status.content = ""  # the last result's text: the wait sees a new one
        t0 = time.perf_counter()
        page.get_by_role("button", name="Suggest what to label next").click()
        wait_until(lambda: "starts ranked by" in panels.suggest_status.content, 300, "the order")
        out.append(time.perf_counter() - t0)
        wait_until(lambda: not app._suggesting, 10, "the end")
    page.get_by_role("tab", name="Label").click()
    return out


DRAWN_JS = (
    "() => window.__viserSceneTree &&"
    " window.__viserSceneTree.getState()['/label/candidates/1/label']"
)


def _page_ready(times: list[float], open_it):
    """Open a tab (``open_it``: a new browser types its name, a known one is remembered), wait
    until its first state's candidates are drawn, append the seconds to ``times``."""
    t0 = time.perf_counter()
    tab = open_it()
    tab.page.wait_for_function(DRAWN_JS, timeout=30000)
    times.append(time.perf_counter() - t0)
    return tab


# The other labellers' pages behave as a hidden tab does in Chromium (document.hidden, no
# animation frames: viser then applies each message batch at once without rendering): their
# screens are elsewhere, as on their own machines, while the server does all their work. Headless
# Chromium shows every page, so the bench says it with an init script.
HIDDEN_PAGE_JS = """
Object.defineProperty(document, 'hidden', {get: () => true});
Object.defineProperty(document, 'visibilityState', {get: () => 'hidden'});
window.requestAnimationFrame = () => 0;
"""


def _other_context(host, screens: str):
    """A browser context for one of the 3 other labellers (``screens``: here or elsewhere)."""
    ctx = host.new_context(viewport={"width": 1280, "height": 760})
    if screens == "elsewhere":
        ctx.add_init_script(HIDDEN_PAGE_JS)
    return ctx


def _busy_labeller(tab, stop: threading.Event, think: float) -> None:
    """Another expert: try, judge, next; ``think`` s between actions (0: flat out)."""
    s = tab.server_tab
    while not stop.wait(think):
        s.try_selected()
        if stop.is_set():
            break
        view = s.session.view()
        if view.last_try is not None and view.last_try.acceptable:
            s._act(lambda sess: sess.accept())
        else:
            s._act(lambda sess: sess.resample())


def _row(name: str, xs: list[float]) -> str:
    a = np.asarray(xs)
    return (
        f"| {name} | {len(a)} | {np.median(a):.3f} | {np.percentile(a, 95):.3f} | {a.max():.3f} |"
    )


def main() -> int:
    """Run the measurements and print the table."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=20, help="new states measured per setting")
    p.add_argument("--tries", type=int, default=5, help="tries measured per setting")
    p.add_argument("--think", type=float, default=2.0, help="s the 3 other experts wait per action")
    p.add_argument("--sim-workers", type=int, default=2, help="try processes of the app")
    p.add_argument(
        "--full-scans",
        action="store_true",
        help="rank every shown start from a full library scan (the app before summary ranking)",
    )
    p.add_argument(
        "--own-browsers",
        action="store_true",
        help="the 3 other labellers each in their own Chromium (as on their own machines), not"
        " as tabs of the measured labeller's browser (whose one software-GL process renders all)",
    )
    p.add_argument(
        "--others-screens",
        choices=("here", "elsewhere"),
        default="here",
        help="where the 3 other labellers' screens render: here (on this machine's cores, in"
        " software WebGL) or elsewhere (their pages hidden: the server does all their work, this"
        " machine renders only the measured labeller's tab)",
    )
    p.add_argument(
        "--look",
        type=float,
        default=0.5,
        help="s a labeller looks at a state before the next R (the 'after looking' rows)",
    )
    p.add_argument(
        "--visits",
        type=int,
        default=3,
        help="first and returning visits measured alone (the first is the browser's and the"
        " server's very first page; a median of 3 moves by a few tenths between runs)",
    )
    p.add_argument(
        "--first-visits",
        type=int,
        default=3,
        help="first visits measured while the 3 others label (one lands anywhere in their"
        " try-judge-next cycle, 4-7 s on a 2-core box: 3 cannot tell 6 s from 7)",
    )
    args = p.parse_args()
    if args.first_visits < 1:
        p.error("--first-visits must be at least 1")
    if args.visits < 1:
        p.error("--visits must be at least 1")
    print(machine_line())
    if args.full_scans:  # an A/B switch for this measurement only
        from knotlab.app.web import session

        session.summary_scan = lambda *_a, **_k: None
    print("shown starts ranked from:", "full scans" if args.full_scans else "start-scan summaries")
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        app = start_app(f"sqlite:///{Path(tmp) / 'latency.db'}", sim_workers=args.sim_workers)
        try:
            first, again = [], []
            for i in range(args.visits):
                tab = _page_ready(first, lambda i=i: open_tab(browser, app, f"probe{i}"))
                tab.page.close()
                tab = _page_ready(
                    again, lambda c=tab.context: open_tab(browser, app, None, context=c)
                )
                if i < args.visits - 1:
                    tab.context.close()
            rows = [
                _row("page ready, first visit (name typed at once)", first),
                _row("page ready, returning labeller", again),
                _row(
                    "new state to candidates drawn, 1 tab",
                    measure_new_state(tab, args.samples, "1"),
                ),
                _row("  server share (session + draw calls), 1 tab", SERVER["1"]),
                _row(
                    f"new state to candidates drawn, 1 tab, after looking {args.look} s",
                    measure_new_state(tab, args.samples, "1 look", look=args.look),
                ),
                _row("Enter to first animation frame, 1 tab", measure_try(tab, args.tries, "1")),
                _row("  first simulated frame sent (server), 1 tab", SIMULATED["1"]),
                _row("accept (Y) to next state drawn, 1 tab", measure_accept(tab, args.tries, "1")),
                _row("  server share (accept + draw calls), 1 tab", ACCEPTED["1"]),
                _row("    of which ranking the next state, 1 tab", RANKED["1"]),
            ]
            suggest = measure_suggest(tab, app, 3)
            rows += [
                _row("Suggest, all unlabelled starts, first click", suggest[:1]),
                _row("Suggest again (same model)", suggest[1:]),
            ]
            hosts = (
                [pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS) for _ in range(3)]
                if args.own_browsers
                else [browser] * 3
            )
            print(
                "3 other labellers:",
                "own browsers" if args.own_browsers else "tabs of one browser",
                f"(their screens {args.others_screens})",
            )
            others = [
                open_tab(
                    hosts[i],
                    app,
                    f"busy{i}",
                    context=_other_context(hosts[i], args.others_screens),
                )
                for i in range(3)
            ]
            stop = threading.Event()
            threads = [
                threading.Thread(target=_busy_labeller, args=(o, stop, args.think), daemon=True)
                for o in others
            ]
            for t in threads:
                t.start()
            rows += [
                _row(
                    "new state to candidates drawn, 4 tabs",
                    measure_new_state(tab, args.samples, "4"),
                ),
                _row("  server share (session + draw calls), 4 tabs", SERVER["4"]),
                _row(
                    f"new state to candidates drawn, 4 tabs, after looking {args.look} s",
                    measure_new_state(tab, args.samples, "4 look", look=args.look),
                ),
                _row("Enter to first animation frame, 4 tabs", measure_try(tab, args.tries, "4")),
                _row("  first simulated frame sent (server), 4 tabs", SIMULATED["4"]),
                _row(
                    "accept (Y) to next state drawn, 4 tabs", measure_accept(tab, args.tries, "4")
                ),
                _row("  server share (accept + draw calls), 4 tabs", ACCEPTED["4"]),
                _row("    of which ranking the next state, 4 tabs", RANKED["4"]),
            ]
            suggest = measure_suggest(tab, app, 2)
            rows.append(_row("Suggest again, 4 tabs", suggest))
            busy_ready: list[float] = []
            for i in range(args.first_visits):
                late = _page_ready(busy_ready, lambda i=i: open_tab(browser, app, f"late{i}"))
                late.context.close()
            rows.append(_row("page ready, first visit, 3 others labelling", busy_ready))
            stop.set()
            for t in threads:
                t.join(30)
            for host in hosts:
                if host is not browser:
                    host.close()
        finally:
            app.stop()
            browser.close()
    print("| measure | n | median s | p95 s | max s |")
    print("|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
