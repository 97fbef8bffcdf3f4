"""Labelling-database speed: label inserts (one per transaction, and batched) and query latency.

Builds 10,000 labels (2,000 executions x 5 steps, 150-point clouds) in a fresh database and times
    single    human-style labelling: one `add_label` transaction per label (on a subset, --single)
    batched   `add_executions` in one transaction (as the oracle labeller and imports write)
    queries   training export (all 10,000 labels as LabelledExecution), next unlabelled state,
              a labeller's progress (medians of --repeats runs)
on a SQLite file, and on PostgreSQL when --pg-url is given or the server binaries are installed
(a throwaway server is started, as the tests do). Prints a table; --json adds one JSON object on
the last line.

    .venv/bin/python bench/db.py [--labels 10000] [--single 1000] [--no-pg] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sqlite3
import statistics
import sys
import tempfile
import time

import numpy as np

from knotlab.core.machine import machine_line
from knotlab.core.selection.labels import LabelledExecution, LabelledStep
from knotlab.labeling_db.store import StateProvenance, open_store

STEPS = 5


def _executions(n_labels: int, n_points: int, seed: int = 0) -> list[LabelledExecution]:
    rng = np.random.default_rng(seed)
    out = []
    for e in range(n_labels // STEPS):
        steps = tuple(
            LabelledStep(
                step_index=i,
                cloud_n3=rng.normal(size=(n_points, 3)),
                chosen_demo=f"s{i:03d}-t0",
                outcome="knot" if i == STEPS - 1 else "progressed",
                rope_nodes_k3=rng.normal(size=(40, 3)),
                candidates=tuple(f"s{j:03d}-t0" for j in range(8)),
                candidate_scores_c=rng.normal(size=8),
                model_version="bench",
            )
            for i in range(STEPS)
        )
        out.append(
            LabelledExecution(f"bench-{e}", "oracle", "oracle", steps, True, task_id=f"t{e}")
        )
    return out


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1000)
    return statistics.median(times)


def bench_backend(url: str, *, n_labels: int, n_single: int, n_points: int, repeats: int) -> dict:
    """Time inserts and queries against the empty database at `url`."""
    store = open_store(url)
    executions = _executions(n_labels, n_points)
    # single: one label per transaction, as the web app writes
    rng = np.random.default_rng(1)
    clouds = [rng.normal(size=(n_points, 3)) for _ in range(n_single // STEPS + 1)]
    store.add_start_states(
        clouds, provenance=[StateProvenance("bench", 0, i) for i in range(len(clouds))]
    )
    t = time.perf_counter()
    done = 0
    while done < n_single:
        ep = store.start_episode("bench-human")
        for i in range(min(STEPS, n_single - done)):
            store.add_label(ep.episode_id, LabelledStep(i, clouds[0], f"s{i:03d}-t0", "progressed"))
            done += 1
        store.finish_episode(ep.episode_id)
    single_s = time.perf_counter() - t
    # batched: all executions in one transaction, written 200 executions per flush
    t = time.perf_counter()
    store.add_executions(executions, batch_size=200)
    batched_s = time.perf_counter() - t
    total = store.stats()["labels"]
    res = {
        "labels_total": total,
        "single_labels": n_single,
        "single_labels_per_s": n_single / single_s,
        "single_ms_per_label": 1000 * single_s / n_single,
        "batched_labels": n_labels,
        "batched_labels_per_s": n_labels / batched_s,
        "training_export_ms": _median_ms(store.training_executions, repeats),
        "next_unlabelled_ms": _median_ms(store.next_unlabelled_state, repeats * 10),
        "progress_ms": _median_ms(lambda: store.progress("bench-human"), repeats * 10),
        "undo_ms": _median_ms(lambda: store.undo_last_label("bench-human"), min(repeats, 3)),
    }
    store.close()
    return res


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--labels", type=int, default=10_000, help="labels inserted in batches")
    ap.add_argument("--single", type=int, default=1_000, help="labels inserted one at a time")
    ap.add_argument("--points", type=int, default=150, help="cloud points per state")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--pg-url", default=None, help="an EMPTY PostgreSQL database to use")
    ap.add_argument("--no-pg", action="store_true", help="SQLite only")
    ap.add_argument("--json", action="store_true", help="also print one JSON object, last line")
    args = ap.parse_args(argv)
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    kw = {"n_labels": args.labels, "n_single": args.single, "n_points": args.points,
          "repeats": args.repeats}  # fmt: skip
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="knotlab-bench-") as tmp:
        results["sqlite"] = bench_backend(f"sqlite:///{tmp}/bench.db", **kw)
        results["sqlite"]["file_mb"] = os.path.getsize(f"{tmp}/bench.db") / 1e6
    if not args.no_pg:
        if args.pg_url:
            results["postgresql"] = bench_backend(args.pg_url, **kw)
        else:
            from tests.db_fixtures import PostgresServer, postgres_bindir

            bindir = postgres_bindir()
            if bindir is not None:
                server = PostgresServer(bindir)
                try:
                    server.start()
                    results["postgresql"] = bench_backend(server.create_database(), **kw)
                    results["postgresql"]["note"] = "throwaway server, fsync=off"
                finally:
                    server.stop()
    machine = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "sqlite": sqlite3.sqlite_version,
    }
    print(f"knotlab labelling DB benchmark  ({machine['platform']}, {machine['cpus']} CPUs, "
          f"Python {machine['python']}, SQLite {machine['sqlite']})")  # fmt: skip
    rows = [
        ("single insert (1 txn/label)", "single_labels_per_s", "labels/s"),
        ("single insert latency", "single_ms_per_label", "ms/label"),
        (f"batched insert ({args.labels} labels)", "batched_labels_per_s", "labels/s"),
        ("training export (all labels)", "training_export_ms", "ms"),
        ("next unlabelled state", "next_unlabelled_ms", "ms"),
        ("labeller progress", "progress_ms", "ms"),
        ("undo last label", "undo_ms", "ms"),
    ]
    backends = list(results)
    print(f"{'metric':<36}" + "".join(f"{b:>14}" for b in backends) + "  unit")
    for name, key, unit in rows:
        vals = "".join(f"{results[b][key]:>14.1f}" for b in backends)
        print(f"{name:<36}{vals}  {unit}")
    counts = ", ".join(f"{b}={results[b]['labels_total']}" for b in backends)
    print(f"(labels in DB: {counts}; medians of {args.repeats}+ runs; PostgreSQL is local)")
    if args.json:
        print(json.dumps({"machine": machine, "args": vars(args), "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
