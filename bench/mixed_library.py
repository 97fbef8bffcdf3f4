"""Two tasks' demos in one library: does nearest-neighbour selection pick the right task's demo?

The overhand knot's and the figure-eight's shipped libraries are pooled (150 + 160 segments).
Every segment's pre-step cloud is a query (leave one demo out: the query's own demonstration is
removed from the pool); the registration scan ranks the pool by nearest-neighbour cost (the
features' main term), and the table says how often the first-ranked segment is of the query's
task, and of its task and step, per task and step. A start rope does not say which knot it is
for, so step 1 is expected near chance; later states carry the task's own shapes.

Usage: .venv/bin/python bench/mixed_library.py [--json]
Prints the machine line, the table, and with --json one JSON object as the last line.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.machine import machine_line  # noqa: E402
from knotlab.core.registration.library_scan import LibraryRegistrar  # noqa: E402
from knotlab.core.tasks import get_task, task_names  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Scan every pooled segment's cloud against the rest; print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    print(f"machine: {machine_line()}")
    pool: list[tuple[str, int, int, np.ndarray]] = []  # task, demo, step, cloud
    hashes = {}
    for name in task_names():
        library = DemoLibrary.load(get_task(name).files.library_path)
        hashes[name] = library.content_hash()
        pool += [(name, s.start_index, s.step_index, s.pre_cloud_n3) for s in library.segments]
    clouds = [c for *_, c in pool]
    tasks = np.array([t for t, *_ in pool])
    demos = np.array([f"{t}:{d}" for t, d, *_ in pool])
    steps = np.array([s for _, _, s, _ in pool])
    registrar = LibraryRegistrar()
    hits: dict[tuple[str, int], list[tuple[bool, bool]]] = defaultdict(list)
    wall0 = time.perf_counter()
    for task, demo, step, cloud in tqdm(pool, desc="queries"):
        cost = registrar.scan(cloud, clouds, key="pooled").nn_cost_a.copy()
        cost[demos == f"{task}:{demo}"] = np.inf  # leave the query's own demonstration out
        best = int(np.argmin(cost))
        hits[(task, step)].append(
            (bool(tasks[best] == task), bool(tasks[best] == task and steps[best] == step))
        )
    wall = time.perf_counter() - wall0
    rows = []
    for (task, step), got in sorted(hits.items()):
        n = len(got)
        rows.append(
            {
                "task": task,
                "step": step + 1,
                "queries": n,
                "same_task": sum(a for a, _ in got) / n,
                "same_task_and_step": sum(b for _, b in got) / n,
            }
        )
    share = {t: float(np.mean(tasks == t)) for t in hashes}
    print(
        f"pool: {len(pool)} segments "
        f"({', '.join(f'{t} {hashes[t]}' for t in hashes)}); {wall:.0f} s"
    )
    print(
        f"{'task':<10} {'step':>4} {'queries':>7} {'top-1 same task':>16} "
        f"{'same task and step':>19}"
    )
    for r in rows:
        print(
            f"{r['task']:<10} {r['step']:>4} {r['queries']:>7} {r['same_task']:>16.1%} "
            f"{r['same_task_and_step']:>19.1%}"
        )
    print("chance of the same task: " + ", ".join(f"{t} {v:.1%}" for t, v in share.items()))
    if args.json:
        print(json.dumps({"rows": rows, "libraries": hashes, "chance": share, "wall_s": wall}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
