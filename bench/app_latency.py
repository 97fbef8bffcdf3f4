"""Latency of the labelling app as a labeller feels it, in headless Chromium on this machine.

Prints: page ready (goto until the first state's candidates are in the scene); new state to
candidates drawn (R: claim a start, observe, scan the library, rank, draw; median and p95);
Enter to the first animation frame; and the same two with 3 more tabs labelling at once
(driven server-side by threads: try, judge, next, as fast as the app allows).
Targets (issue "The labelling app"): candidates drawn within 0.3 s median, 0.5 s p95; page
ready within 3 s. Usage: python bench/app_latency.py [--samples 20] [--tries 5]
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

from tests.browser.conftest import CHROMIUM, CHROMIUM_ARGS, open_tab, start_app, wait_until


def _status(page) -> str:
    return page.evaluate("() => document.body.innerText")


def measure_new_state(tab, n: int) -> list[float]:
    """Seconds from pressing R to the new start's candidates drawn (status text changed)."""
    out = []
    for _ in range(n):
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
    return out


def measure_try(tab, n: int) -> list[float]:
    """Seconds from Enter to the first animation frame in the browser (a gripper drawn)."""
    out = []
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
        tab.page.keyboard.press("r")
        wait_until(lambda: tab.session.view().phase.value == "choosing", 20, "next")
    return out


def _busy_labeller(tab, stop: threading.Event) -> None:
    s = tab.server_tab
    while not stop.is_set():
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
    args = p.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        app = start_app(f"sqlite:///{Path(tmp) / 'latency.db'}")
        try:
            ready = []
            for i in range(3):
                t0 = time.perf_counter()
                tab = open_tab(browser, app, f"probe{i}")
                tab.page.wait_for_function(
                    "() => window.__viserSceneTree &&"
                    " window.__viserSceneTree.getState()['/label/candidates/1/label']",
                    timeout=20000,
                )
                ready.append(time.perf_counter() - t0)
                if i < 2:
                    tab.context.close()
            rows = [_row("page ready (goto to candidates drawn)", ready)]
            rows.append(
                _row("new state to candidates drawn, 1 tab", measure_new_state(tab, args.samples))
            )
            rows.append(_row("Enter to first animation frame, 1 tab", measure_try(tab, args.tries)))
            others = [open_tab(browser, app, f"busy{i}") for i in range(3)]
            stop = threading.Event()
            threads = [
                threading.Thread(target=_busy_labeller, args=(o, stop), daemon=True) for o in others
            ]
            for t in threads:
                t.start()
            rows.append(
                _row("new state to candidates drawn, 4 tabs", measure_new_state(tab, args.samples))
            )
            rows.append(
                _row("Enter to first animation frame, 4 tabs", measure_try(tab, args.tries))
            )
            stop.set()
            for t in threads:
                t.join(30)
        finally:
            app.stop()
            browser.close()
    print("| measure | n | median s | p95 s | max s |")
    print("|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
