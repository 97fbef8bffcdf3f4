"""Learner benchmark: QP size and fit time of MaxMarginQLearner for 300 labelled states x 148 demos.

Features have the featurizer's shape (d = 14 + n_demos: 3 costs, 6 quadratic terms, grasp
distance, 3 phase weights, phase match, one-hot of the demo). By default they are synthetic but
shaped like real ones (demos of the state's own step cost less, the expert is a cheap same-step
demo, margins 1-5 cm within the step and 10-30 cm across steps); with ``--library PATH`` they come
from the real featurizer on library clouds jittered by 5 mm (one scan per state, ~0.2 s each).
States are grouped into 3-step executions (Bellman rows along them, a goal row at the end) plus
``--dead-ends`` dead-end states.

Usage: .venv/bin/python bench/learning.py [--states 300] [--demos 148] [--dead-ends 30]
       [--repeats 3] [--C 1] [--D 1] [--library PATH] [--json]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.core.machine import machine_line  # noqa: E402
from knotlab.core.selection.learner import LabelledState, MaxMarginQLearner, TrainingData  # noqa: E402

N_STEPS = 3  # demo steps per execution (the overhand knot)
N_BASE = 14  # non-indicator feature columns


class _Spec:
    """Stands in for the featurizer: only its spec (indicator columns) matters to fit()."""

    def __init__(self, n_demos: int) -> None:
        self._mask = [False] * N_BASE + [True] * n_demos

    def spec(self) -> dict:
        return {"feature_set": "bench-synthetic", "indicator_mask": self._mask}


def _synthetic_state(rng, step: int, n_demos: int) -> tuple[np.ndarray, int, np.ndarray]:
    steps_a = np.arange(n_demos) % N_STEPS
    same = steps_a == step
    c1 = rng.lognormal(np.where(same, -4.5, -3.5), 0.4)  # mapping error
    c2 = rng.lognormal(np.where(same, 0.0, 0.8), 0.4)  # bending f
    c3 = rng.lognormal(np.where(same, 0.1, 0.9), 0.4)  # bending g
    c = np.column_stack([c1, c2, c3])
    quad = np.column_stack([c[:, i] * c[:, j] for i in range(3) for j in range(i, 3)])
    grasp = np.abs(rng.normal(np.where(same, 0.005, 0.03), 0.01))
    phase = np.full(N_STEPS, 0.05)
    phase[step] = 0.9
    phase = rng.dirichlet(phase * 50)
    match = phase[steps_a]
    phi = np.column_stack(
        [c, quad, grasp, np.broadcast_to(phase, (n_demos, N_STEPS)), match, np.eye(n_demos)]
    )
    cand = np.flatnonzero(same)
    expert = int(cand[np.argsort(c1[cand] + 0.002 * c2[cand])[rng.integers(0, 3)]])
    margins = np.where(same, rng.uniform(0.01, 0.05, n_demos), rng.uniform(0.1, 0.3, n_demos))
    margins[expert] = 0.0
    return phi, expert, margins


def synthetic_data(n_states: int, n_demos: int, n_dead: int, seed: int) -> TrainingData:
    """Executions of 3 steps (the last one ties the knot) and dead ends, synthetic features."""
    rng = np.random.default_rng(seed)
    states, pairs, goals = [], [], []
    for i in range(n_states):
        e, step = divmod(i, N_STEPS)
        phi, expert, margins = _synthetic_state(rng, step, n_demos)
        states.append(LabelledState(phi, expert, margins, e, step))
        if step > 0:
            pairs.append((i - 1, i))
        if step == N_STEPS - 1:
            goals.append(i)
    dead = [_synthetic_state(rng, int(rng.integers(N_STEPS)), n_demos)[0] for _ in range(n_dead)]
    return TrainingData(tuple(states), tuple(pairs), tuple(goals), tuple(dead))


def real_data(library_path: str, n_states: int, n_dead: int, seed: int):
    """States = library clouds jittered by 5 mm, expert = the demo the cloud came from."""
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.selection.features import LibraryFeaturizer

    lib = DemoLibrary.load(library_path)
    fz = LibraryFeaturizer(lib)
    rng = np.random.default_rng(seed)
    by_start: dict[int, list[int]] = {}
    for a, seg in enumerate(lib):
        by_start.setdefault(seg.start_index, []).append(a)
    starts = [sorted(v, key=lambda a: lib[a].step_index) for v in by_start.values()]
    states, pairs, goals, dead = [], [], [], []
    t0 = time.perf_counter()
    e = 0
    while len(states) < n_states:
        chain = starts[int(rng.integers(len(starts)))]
        for k, a in enumerate(chain):
            if len(states) >= n_states:
                break
            cloud = lib[a].pre_cloud_n3 + rng.normal(0, 0.005, lib[a].pre_cloud_n3.shape)
            phi, scan = fz.features(cloud)
            states.append(LabelledState(phi, a, fz.margins(scan, a), e, k))
            if k > 0:
                pairs.append((len(states) - 2, len(states) - 1))
            if k == len(chain) - 1:
                goals.append(len(states) - 1)
        e += 1
    for _ in range(n_dead):
        a = int(rng.integers(len(lib)))
        cloud = lib[a].pre_cloud_n3 + rng.normal(0, 0.03, lib[a].pre_cloud_n3.shape)
        dead.append(fz.features(cloud)[0])
    scan_s = time.perf_counter() - t0
    data = TrainingData(tuple(states), tuple(pairs), tuple(goals), tuple(dead))
    return data, fz, scan_s


def main(argv: list[str] | None = None) -> int:
    """Fit the QP --repeats times; print its size and the median fit time."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--states", type=int, default=300)
    ap.add_argument("--demos", type=int, default=148)
    ap.add_argument("--dead-ends", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--C", type=float, default=1.0)
    ap.add_argument("--D", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--library", default=None, help="use real scans of this library's clouds")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    print(f"machine: {machine_line()}")  # every figure names its CPU kind

    scan_s = None
    if args.library:
        data, featurizer, scan_s = real_data(args.library, args.states, args.dead_ends, args.seed)
        source = f"real scans of {args.library}"
    else:
        data = synthetic_data(args.states, args.demos, args.dead_ends, args.seed)
        featurizer = _Spec(args.demos)
        source = "synthetic"
    n_actions = data.states[0].phi_ad.shape[0]
    times, model = [], None
    for _ in range(args.repeats):
        learner = MaxMarginQLearner(C=args.C, D=args.D)
        t0 = time.perf_counter()
        model = learner.fit(data, featurizer)
        times.append(time.perf_counter() - t0)
    m = model.metrics
    result = {
        "source": source,
        "states": len(data.states),
        "demos": n_actions,
        "features": data.n_features,
        "variables": m["n_variables"],
        "margin_rows": m["n_margin_rows"],
        "bellman_rows": m["n_bellman_rows"],
        "dead_ends": m["n_dead_ends"],
        "dead_end_rows": m["n_dead_ends"] * n_actions,
        "C": args.C,
        "D": args.D,
        "fit_s_median": statistics.median(times),
        "fit_s_all": [round(t, 3) for t in times],
        "train_top1": m["train_top1"],
        "train_mean_expert_rank": m["train_mean_expert_rank"],
        "scan_s": scan_s,
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
        },
    }
    result["solve_s_last"] = m.get("solve_seconds")  # cvxpy solve only, last repeat
    print(f"MaxMarginQLearner QP ({source}); {platform.platform()}, {os.cpu_count()} CPUs")
    print(f"{'quantity':<28} value")
    print("-" * 44)
    for key in (
        "states",
        "demos",
        "features",
        "variables",
        "margin_rows",
        "bellman_rows",
        "dead_ends",
        "dead_end_rows",
    ):
        print(f"{key:<28} {result[key]}")
    print(f"{'fit s (median of ' + str(args.repeats) + ')':<28} {result['fit_s_median']:.2f}")
    print(f"{'train top-1':<28} {result['train_top1']:.3f}")
    if scan_s is not None:
        print(f"{'scan + features s (all)':<28} {scan_s:.1f}")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
