"""Greedy success by cross-validation on the training starts: which feature set to train with.

The question: the learned greedy policy must beat nearest neighbour by a margin, and the lever
that gets it there must be chosen on training data only. This script splits the labelled
executions (one per training start) into K seeded folds; for every feature variant it fits one
model per fold on the other folds' labels and runs greedy on the fold's own training starts, so
every start is played by a model that never saw its label. NN runs on the same starts, so the
comparison is paired (same rope, same simulator). Without landmark states: landmarks are the
same for every demo of a state, so they never change greedy's choice, and leaving them out lets
one featurisation serve all folds.

Prints a table (successes, Wilson 95 %, paired wins and losses against NN and against the base
features) and, with ``--json``, one JSON object as the last line. Resumable: episodes already in
OUT/outcomes.jsonl are not rerun. Training starts only; never the test set.

Variants: base (the shipped features), rank (plus the cost-rank columns), and with "+floor" or
"+tries" the tried candidates of `knotlab labels tries` (results/tries_main.jsonl): "+floor" only
raises the margin of tried demos that did not advance; "+tries" also drops the rows against the
ones that did, as `knotlab train --tries` does.

Usage: .venv/bin/python bench/greedy_lever.py [--labels results/labels_oracle_main.jsonl]
       [--variants base,rank,base+floor,rank+floor,base+tries] [--folds 5] [--C 1000] [--D 10]
       [--outcomes results/tries_main.jsonl] [--out runs/greedy_lever] [--workers 2] [--json]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.app import defaults  # noqa: E402
from knotlab.core.agent import Agent  # noqa: E402
from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import TaskSet  # noqa: E402
from knotlab.core.experiments.bench import wilson_interval  # noqa: E402
from knotlab.core.machine import machine_line  # noqa: E402
from knotlab.core.parallel import PerProcess, imap_processes  # noqa: E402
from knotlab.core.selection.learner import MaxMarginQLearner  # noqa: E402
from knotlab.core.selection.model_selection import (  # noqa: E402
    featurize_executions,
    merge_training_data,
    ranking_metrics,
)
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.labeling_db.interchange import read_labels  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# variant -> (rank_features, how the tried candidates of `knotlab labels tries` are used)
# ("floor": only the tried candidates that did not advance get a margin floor; "tries": also no
# margin row against the ones that did, as `knotlab train --tries` does)
VARIANTS = {
    "base": (False, ""),
    "rank": (True, ""),
    "base+floor": (False, "floor"),
    "rank+floor": (True, "floor"),
    "base+tries": (False, "tries"),
}


@dataclass(frozen=True)
class Job:
    """One episode: a variant's fold model (or NN) on one training start."""

    variant: str  # "nn" or a VARIANTS key
    fold: int
    task_index: int


@dataclass(frozen=True, eq=False)
class Spec:
    """What a worker needs: the library, the task set and every fold model by (variant, fold)."""

    library: DemoLibrary
    tasks: TaskSet
    models: dict[tuple[str, int], QModel]


class _Worker:
    def __init__(self, spec: Spec) -> None:
        from knotlab.core.agent import Agent
        from knotlab.core.parallel import single_thread_blas
        from knotlab.core.world.sim import RopeWorld

        single_thread_blas()
        self.spec = spec
        self.world = RopeWorld()
        self.nn = Agent(spec.library)  # the variants' greedy agents share its caches
        self.agents: dict[tuple[str, int], Agent] = {}

    def agent(self, job: Job) -> Agent:
        """The job's agent: nearest neighbour, or greedy on the variant's model of the fold."""
        if job.variant == "nn":
            return self.nn
        key = (job.variant, job.fold)
        if key not in self.agents:
            self.agents[key] = self.nn.with_model(self.spec.models[key])
        return self.agents[key]

    def run(self, job: Job) -> dict:
        task = self.spec.tasks[job.task_index]
        record = self.agent(job).run_episode(self.world, task)
        out = record.summary()
        if out.get("error"):
            raise RuntimeError(f"{job}: episode errored: {out['error']}")
        return {
            "variant": job.variant,
            "fold": job.fold,
            "task_index": job.task_index,
            "task_id": task.task_id,
            "success": bool(out["success"]),
            "chosen": out.get("chosen"),
            "outcomes": out.get("outcomes"),
            "stages": out.get("stages"),
        }


_WORKER: PerProcess[_Worker] = PerProcess(_Worker)


def _init(spec: Spec) -> None:
    _WORKER.reset()
    _WORKER.get(spec)


def _run(job: Job) -> dict:
    return _WORKER.current().run(job)


def replace_states(part, **changes):
    """The training part with ``changes`` made to every state."""
    from dataclasses import replace

    from knotlab.core.selection.learner import TrainingData

    states = tuple(replace(s, **changes) for s in part.states)
    return TrainingData(states, part.bellman_pairs, part.goal_states, part.dead_ends_phi)


def fold_models(
    executions, library, variant: str, folds: np.ndarray, C: float, D: float, workers,
    parts_by_rank: dict, outcomes: dict,
):  # fmt: skip
    """One model per fold for a variant, and its held-out ranking metrics per fold."""
    rank, use_outcomes = VARIANTS[variant]
    if rank not in parts_by_rank:
        parts, warnings = featurize_executions(
            executions, library, workers=workers, progress=True, rank_features=rank
        )
        for w in warnings:
            print(f"warning: {w}")
        parts_by_rank[rank] = parts
    parts = parts_by_rank[rank]
    if use_outcomes:
        from knotlab.core.selection.tries import apply_tries

        parts = [
            None if p is None else apply_tries(p, e.execution_id, outcomes, library.keys)
            for p, e in zip(parts, executions, strict=True)
        ]
        if use_outcomes == "floor":
            parts = [None if p is None else replace_states(p, also_good_a=None) for p in parts]
    models, metrics = {}, {}
    for k in range(int(folds.max()) + 1):
        train = [p for p, f in zip(parts, folds, strict=True) if f != k and p is not None]
        held = [p for p, f in zip(parts, folds, strict=True) if f == k and p is not None]
        from knotlab.core.selection.features import LibraryFeaturizer

        spec_source = LibraryFeaturizer(library, rank_features=rank)
        model = MaxMarginQLearner(C=C, D=D).fit(merge_training_data(train), spec_source)
        models[(variant, k)] = model
        metrics[k] = ranking_metrics(model, merge_training_data(held))
        print(f"{variant} fold {k}: held-out top-1 {metrics[k]['top1']:.3f}")
    return models, metrics


def main() -> int:
    """Run the study and print its table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--labels", default=str(ROOT / "results/labels_oracle_main.jsonl"))
    ap.add_argument("--library", default=str(defaults.library_path()))
    ap.add_argument("--tasks", default=str(defaults.task_set_path("main", "train")))
    ap.add_argument("--variants", default="base,rank,base+floor,rank+floor,base+tries")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--C", type=float, default=1000.0)
    ap.add_argument("--D", type=float, default=10.0)
    ap.add_argument("--out", default="runs/greedy_lever")
    ap.add_argument("--outcomes", default=str(ROOT / "results/tries_main.jsonl"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; known: {sorted(VARIANTS)}")

    library = DemoLibrary.load(args.library)
    tasks = TaskSet.load(args.tasks)
    if tasks.split != "train":
        ap.error(f"{args.tasks} is a {tasks.split} set: this study runs on training starts only")
    executions = [item.execution for item in read_labels(args.labels)]
    by_id = {t.task_id: i for i, t in enumerate(tasks)}
    starts = []
    for e in executions:
        task_id = e.execution_id.split("-", 1)[1]  # oracle-main-train-0001 -> main-train-0001
        if task_id not in by_id:
            ap.error(f"execution {e.execution_id} has no start in {args.tasks}")
        starts.append(by_id[task_id])
    folds = np.random.default_rng(args.seed).permutation(len(executions)) % args.folds

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "outcomes.jsonl"
    done = {}
    if log_path.exists():
        for line in log_path.read_text().splitlines():
            r = json.loads(line)
            done[(r["variant"], r["task_index"])] = r

    outcomes = {}
    if any(VARIANTS[v][1] for v in variants):
        path = Path(args.outcomes)
        if not path.exists():
            ap.error(f"{path} not found: run `knotlab labels tries` first")
        from knotlab.core.selection.tries import read_tries

        outcomes = read_tries(path)
    models, metrics, parts_by_rank = {}, {}, {}
    for v in variants:
        if all((v, s) in done for s in starts):
            continue
        m, met = fold_models(
            executions, library, v, folds, args.C, args.D, args.workers, parts_by_rank, outcomes
        )
        models.update(m)
        metrics[v] = met
    jobs = [
        Job(v, int(f), s)
        for v in ["nn", *variants]
        for s, f in zip(starts, folds, strict=True)
        if (v, s) not in done
    ]
    spec = Spec(library, tasks, models)
    with log_path.open("a") as fh:
        for _, rec in imap_processes(
            _run, jobs, workers=args.workers, initializer=partial(_init, spec),
            desc="greedy lever episodes",
        ):  # fmt: skip
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            done[(rec["variant"], rec["task_index"])] = rec

    rows = []
    n = len(starts)
    print(f"\nGreedy by {args.folds}-fold cross-validation on {n} main training starts "
          f"(C = {args.C:g}, D = {args.D:g}, no landmarks; NN on the same starts)")  # fmt: skip
    print("| policy | successes | Wilson 95 % | vs NN: wins / losses | vs base: wins / losses |")
    print("|---|---|---|---|---|")
    for v in ["nn", *variants]:
        ok = np.array([done[(v, s)]["success"] for s in starts])
        nn = np.array([done[("nn", s)]["success"] for s in starts])
        lo, hi = wilson_interval(int(ok.sum()), n)
        vs_nn = f"{int((ok & ~nn).sum())} / {int((~ok & nn).sum())}" if v != "nn" else "-"
        vs_base = "-"
        if v not in ("nn", "base") and "base" in variants:
            base = np.array([done[("base", s)]["success"] for s in starts])
            vs_base = f"{int((ok & ~base).sum())} / {int((~ok & base).sum())}"
        print(f"| {v} | {int(ok.sum())}/{n} = {100 * ok.mean():.1f} % | "
              f"[{100 * lo:.1f}, {100 * hi:.1f}] | {vs_nn} | {vs_base} |")  # fmt: skip
        rows.append({"policy": v, "successes": int(ok.sum()), "n": n, "wilson": [lo, hi]})
    if args.json:
        print(json.dumps({"rows": rows, "folds": args.folds, "C": args.C, "D": args.D,
                          "heldout_ranking": metrics}))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
