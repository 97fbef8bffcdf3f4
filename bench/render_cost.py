"""What one labelling tab costs headless Chromium's GPU process, with the table drawn lit or lite.

Headless Chromium renders WebGL in software, in one GPU process for every tab. An idle viser
tab is redrawn about once a second, so that process's CPU share with one idle tab open is about
the cost of one frame. The table (and its grid) is swapped in place between the app's two ways
of drawing it (`add_table(lite=False)`: physically based material, shader grid; `lite=True`:
toon material, grid as line segments), alternating, --repeats times, --seconds each.
Usage: python bench/render_cost.py [--repeats 3] [--seconds 12]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from knotlab.app.web.scene import add_table
from knotlab.core.machine import machine_line
from tests.browser.conftest import CHROMIUM, CHROMIUM_ARGS, open_tab, start_app


def gpu_process_ids() -> list[str]:
    """The process ids of Chromium's GPU processes."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if b"--type=gpu-process" in (entry / "cmdline").read_bytes():
                    found.append(entry.name)
            except OSError:  # gone meanwhile
                pass
    return found


def _cpu_ticks(pid: str) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # utime + stime


def cpu_share(pids: list[str], seconds: float) -> float:
    """The processes' CPU time over ``seconds`` of wall time (1.0 = one core)."""
    before, t0 = [_cpu_ticks(p) for p in pids], time.perf_counter()
    time.sleep(seconds)
    after, wall = [_cpu_ticks(p) for p in pids], time.perf_counter() - t0
    return sum(b - a for a, b in zip(before, after, strict=True)) / os.sysconf("SC_CLK_TCK") / wall


def main() -> int:
    """Measure and print the table."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seconds", type=float, default=12.0)
    args = p.parse_args()
    from playwright.sync_api import sync_playwright

    print(machine_line())
    shares: dict[str, list[float]] = {"lit (standard material, shader grid)": [], "lite": []}
    with tempfile.TemporaryDirectory() as tmp:
        app = start_app(f"sqlite:///{Path(tmp) / 'render.db'}")
        try:
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                tab = open_tab(browser, app, "render")
                scene = tab.server_tab.drawer.scene
                time.sleep(3)  # the first state's drawing settles
                pids = gpu_process_ids()
                for _ in range(args.repeats):
                    for name, lite in zip(shares, (False, True), strict=True):
                        scene.remove_by_name("/grid")
                        add_table(scene, lite=lite)
                        time.sleep(2)
                        shares[name].append(cpu_share(pids, args.seconds))
                browser.close()
        finally:
            app.stop()
    print("| table | GPU process, % of a core (one idle tab, ~1 frame/s) | runs |")
    print("|---|---|---|")
    for name, xs in shares.items():
        a = 100 * np.asarray(xs)
        print(f"| {name} | {a.mean():.1f} (min {a.min():.1f}, max {a.max():.1f}) | {len(a)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
