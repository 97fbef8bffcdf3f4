"""Active learning: does labelling the suggested starts first reach a good model with fewer labels?

The oracle's labels of the main training starts (results/labels_oracle_main.jsonl) stand in for
the expert: asking for a start's label means taking its oracle execution, so no simulation runs.
A fixed held-out split of the executions (``--split-seed``) is never labelled or scored; the rest
is the pool. Per curve seed, both orders start from the same seeded random seed set of
``--step`` executions and then add ``--step`` executions per round, up to ``--max-labels``:
- random: the next executions of a seeded random permutation of the pool;
- suggested: the pool's unlabelled starts ranked by `rank_for_labelling` (combined: NN/greedy
  disagreement first, then the smallest Q margin) under the model trained so far.
Every round refits `QModelSearch` (one (C, D), no internal validation split) and records top-1
agreement with the oracle on the held-out executions.

Landmarks default to none (``--landmarks 0,0``): with landmarks every round samples new landmark
states from its labels, so every state is featurised again (~0.3 s a state on one core), while
without them each state is featurised once and cached (on disk, under --out). Landmark columns
are the same for every demo of a state, so they shape the value, not the ranking top-1 measures.

Greedy success (``--greedy-tasks K``, default 0 = skip): for the first curve seed, at every
``--greedy-every``-th size, the round's model drives the greedy policy on the first K main-level
test tasks (`knotlab bench`, resumable under OUT's folder ``greedy/``), so the curve shows what a
label buys in knots tied, not only in agreement. The models are fitted on training labels only;
the test tasks only measure them.

Usage: python bench/active_learning.py [--labels results/labels_oracle_main.jsonl]
       [--step 20] [--max-labels 200] [--seeds 0,1] [--C 1000] [--D 10] [--landmarks 0,0]
       [--greedy-tasks 0] [--greedy-every 40] [--workers 2]
       [--out runs/active_learning/curve.png] [--json]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.app import defaults  # noqa: E402
from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.selection.acquisition import rank_for_labelling, score_state  # noqa: E402
from knotlab.core.selection.labels import LabelledExecution  # noqa: E402
from knotlab.core.selection.learner import TrainingData  # noqa: E402
from knotlab.core.selection.model_selection import (  # noqa: E402
    FeatureCache,
    QModelSearch,
    merge_training_data,
    ranking_metrics,
    split_executions,
)
from knotlab.core.selection.qmodel import QModel  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ORDERS = ("random", "suggested")


@dataclass(frozen=True)
class CurvePoint:
    """Held-out top-1 after training on ``n_labels`` executions chosen in ``order``."""

    seed: int
    order: str
    n_labels: int
    top1: float
    fit_s: float
    greedy_successes: int | None = None  # on the first --greedy-tasks test tasks, when run
    greedy_tasks: int | None = None


def _greedy_success(model: QModel, library: DemoLibrary, args, order: str, n: int) -> int:
    """Knots tied by greedy with ``model`` on the first --greedy-tasks main test tasks."""
    from knotlab.core.demos.tasks import TaskSet
    from knotlab.core.experiments.bench import run_bench

    out = Path(args.out).parent / "greedy" / f"{order}_{n:04d}"
    tasks = TaskSet.load(defaults.task_set_path("main", "test"))
    result = run_bench(
        out,
        library=library,
        task_set=tasks,
        policies=["greedy"],
        n_tasks=args.greedy_tasks,
        model=model,
        workers=args.workers,
        progress=False,
    )
    records = result.outcomes["greedy"]
    if any(r.get("failure_kind") == "error" for r in records):
        raise SystemExit(f"active_learning: greedy episodes errored in {out}: not a result")
    return sum(bool(r["success"]) for r in records)


def _atomic_write(path: Path, write) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def _load_cache(path: Path) -> FeatureCache:
    if path.exists():
        with open(path, "rb") as fh:
            cache = pickle.load(fh)
        if isinstance(cache, FeatureCache):
            return cache
    return FeatureCache()


def _save_cache(path: Path, cache: FeatureCache) -> None:
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            pickle.dump(cache, fh, protocol=pickle.HIGHEST_PROTOCOL)

    _atomic_write(path, write)


def _fit(
    labelled: list[LabelledExecution], library: DemoLibrary, args, cache: FeatureCache, seed: int
) -> tuple[QModel, float]:
    t0 = time.perf_counter()
    search = QModelSearch(
        C=[args.C],
        D=[args.D],
        landmarks=args.landmarks,
        validation_fraction=0.0,  # the held-out split is outside: every label trains
        random_state=seed,
        workers=1,
        progress=False,
        feature_cache=cache,
    ).fit(labelled, library)
    return search.best_model_, time.perf_counter() - t0


def _suggest(
    model: QModel,
    pool: list[LabelledExecution],
    parts: dict[str, TrainingData],
    taken: set[str],
    k: int,
    keys: tuple[str, ...],
    seed: int,
) -> list[str]:
    """The next ``k`` unlabelled pool executions in the suggested order (scored on step 0)."""
    scores = []
    for ex in pool:
        if ex.execution_id in taken:
            continue
        first = parts[ex.execution_id].states[0]
        q_a = model.q(first.phi_ad)
        # The oracle was shown candidates in registration-cost order: the first is NN's choice.
        nn = ex.steps[0].candidates[0] if ex.steps[0].candidates else keys[first.expert_action]
        choices = {"nn": nn, "greedy": keys[int(np.argmax(q_a))]}
        scores.append(score_state(ex.execution_id, q_a, choices))
    return [r.score.key for r in rank_for_labelling(scores, seed=seed)[:k]]


def run_curve(args) -> tuple[list[CurvePoint], dict]:
    """Every (seed, order, size) point of the learning curves, and what the run used."""
    from knotlab.labeling_db.interchange import read_labels

    library = DemoLibrary.load(args.library)
    executions = [
        s.execution
        for s in read_labels(args.labels)
        if s.execution.steps and s.execution.steps[0].outcome != "skipped"
    ]
    train_idx, val_idx = split_executions(
        len(executions), args.validation_fraction, args.split_seed
    )
    pool = [executions[i] for i in train_idx]
    held_out = [executions[i] for i in val_idx]
    if args.max_labels > len(pool):
        raise SystemExit(f"--max-labels {args.max_labels} exceeds the pool ({len(pool)})")
    digest = hashlib.sha256(Path(args.labels).read_bytes()).hexdigest()[:12]
    cache_path = Path(args.out).with_name(f"features_{digest}_{library.content_hash()}.pkl")
    cache = _load_cache(cache_path)
    t0 = time.perf_counter()
    # Featurise everything once (the landmark-free rows do not depend on the training set).
    all_parts, warnings = cache.featurize(executions, library, workers=1, progress=True)
    featurize_s = time.perf_counter() - t0
    _save_cache(cache_path, cache)
    parts = {
        ex.execution_id: p for ex, p in zip(executions, all_parts, strict=True) if p is not None
    }
    pool = [ex for ex in pool if ex.execution_id in parts]
    held = merge_training_data(
        [parts[ex.execution_id] for ex in held_out if ex.execution_id in parts]
    )
    sizes = list(range(args.step, args.max_labels + 1, args.step))
    points: list[CurvePoint] = []
    for seed in args.seeds:
        perm = [pool[i].execution_id for i in np.random.default_rng(seed).permutation(len(pool))]
        by_id = {ex.execution_id: ex for ex in pool}
        seed_set = perm[: args.step]
        model: QModel | None = None
        for order in ORDERS:
            labelled = list(seed_set)
            for n in sizes:
                if n > len(labelled):
                    if order == "random":
                        labelled = perm[:n]
                    else:
                        assert model is not None  # fitted on the seed set first
                        labelled += _suggest(
                            model, pool, parts, set(labelled), n - len(labelled),
                            library.keys, seed,
                        )  # fmt: skip
                model, fit_s = _fit([by_id[i] for i in labelled], library, args, cache, seed)
                top1 = ranking_metrics(model, held)["top1"]
                wins = tasks = None
                if args.greedy_tasks and seed == args.seeds[0] and n % args.greedy_every == 0:
                    wins, tasks = _greedy_success(model, library, args, order, n), args.greedy_tasks
                points.append(CurvePoint(seed, order, n, float(top1), fit_s, wins, tasks))
                greedy = "" if wins is None else f", greedy {wins}/{tasks} knots"
                print(f"seed {seed} {order:<9} {n:>4} labels: top-1 {top1:.3f}{greedy} "
                      f"({fit_s:.1f} s)")  # fmt: skip
    # Reference: how often the oracle took NN's choice (its first candidate) in held-out states.
    held_steps = [
        st for ex in held_out if ex.execution_id in parts for st in ex.steps if st.candidates
    ]
    nn_top1 = float(np.mean([st.candidates[0] == st.chosen_demo for st in held_steps]))
    info = {
        "nn_held_out_top1": nn_top1,
        "labels": str(args.labels),
        "library_hash": library.content_hash(),
        "n_executions": len(executions),
        "n_pool": len(pool),
        "n_held_out_executions": len(held_out),
        "n_held_out_states": len(held.states),
        "split_seed": args.split_seed,
        "C": args.C,
        "D": args.D,
        "landmarks": list(args.landmarks),
        "featurize_s": round(featurize_s, 1),
        "featurize_warnings": warnings,
        "machine": machine_info(),
    }
    return points, info


def summarise(points: list[CurvePoint]) -> dict:
    """Mean top-1 per (order, size) over seeds, and labels the suggested order needs to match
    the random order's final top-1 (None when it never does)."""
    sizes = sorted({p.n_labels for p in points})
    mean = {
        order: [
            float(np.mean([p.top1 for p in points if p.order == order and p.n_labels == n]))
            for n in sizes
        ]
        for order in ORDERS
    }
    target = mean["random"][-1]
    reach = next((n for n, t in zip(sizes, mean["suggested"], strict=True) if t >= target), None)
    greedy = {
        order: [
            [p.n_labels, p.greedy_successes, p.greedy_tasks]
            for p in sorted(points, key=lambda p: p.n_labels)
            if p.order == order and p.greedy_successes is not None
        ]
        for order in ORDERS
    }
    return {
        "sizes": sizes,
        "mean_top1": mean,
        "random_final_top1": target,
        "labels_to_reach": reach,
        "greedy_successes": greedy,
    }


def format_table(points: list[CurvePoint], summary: dict) -> str:
    """Plain-text curve: per size, each seed's top-1 in each order and the means."""
    seeds = sorted({p.seed for p in points})
    top = {(p.seed, p.order, p.n_labels): p.top1 for p in points}
    head = (
        f"{'labels':>6} "
        + " ".join(f"{o[:4]}{s:<3}" for o in ORDERS for s in seeds)
        + f" {'random':>7} {'suggest':>7}"
    )
    lines = [head, "-" * len(head)]
    for i, n in enumerate(summary["sizes"]):
        cells = " ".join(f"{top[(s, o, n)]:>7.3f}" for o in ORDERS for s in seeds)
        lines.append(
            f"{n:>6} {cells} {summary['mean_top1']['random'][i]:>7.3f} "
            f"{summary['mean_top1']['suggested'][i]:>7.3f}"
        )
    for order, rows in summary.get("greedy_successes", {}).items():
        if rows:
            cells = ", ".join(f"{n}: {k}/{t}" for n, k, t in rows)
            lines.append(f"greedy knots tied, {order} order (labels: successes/tasks): {cells}")
    reach = summary["labels_to_reach"]
    lines.append(
        f"random order's final top-1 {summary['random_final_top1']:.3f} at {summary['sizes'][-1]} "
        f"labels; suggested order reaches it at {reach if reach is not None else 'never'}"
    )
    return "\n".join(lines)


def plot_curve(points: list[CurvePoint], summary: dict, path: Path, title: str) -> Path:
    """Held-out top-1 against labels used, one line per order (mean) and per seed (thin)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    greedy = [p for p in points if p.greedy_successes is not None]
    fig = Figure(figsize=(11.0 if greedy else 6.0, 4.0), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if greedy else 1, 1)
    colours = {"random": "#4C72B0", "suggested": "#DD8452"}
    for order in ORDERS:
        for s in sorted({p.seed for p in points}):
            mine = [p for p in points if p.order == order and p.seed == s]
            ax.plot([p.n_labels for p in mine], [p.top1 for p in mine], color=colours[order],
                    alpha=0.3, lw=1)  # fmt: skip
        ax.plot(summary["sizes"], summary["mean_top1"][order], color=colours[order], lw=2.2,
                marker="o", label=f"{order} (mean)")  # fmt: skip
    ax.axhline(summary["random_final_top1"], color="grey", ls=":", lw=1)
    ax.set_xlabel("labelled executions")
    ax.set_ylabel("held-out top-1 agreement with the oracle")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    if greedy:
        from knotlab.core.experiments.bench import wilson_interval

        gx = fig.add_subplot(1, 2, 2)
        for order in ORDERS:
            mine = sorted((p for p in greedy if p.order == order), key=lambda p: p.n_labels)
            if not mine:
                continue
            rate = [p.greedy_successes / p.greedy_tasks for p in mine]  # type: ignore[operator]
            ci = [wilson_interval(p.greedy_successes, p.greedy_tasks) for p in mine]  # type: ignore[arg-type]
            xs = [p.n_labels for p in mine]
            gx.fill_between(xs, [c[0] for c in ci], [c[1] for c in ci], color=colours[order],
                            alpha=0.15)  # fmt: skip
            gx.plot(xs, rate, color=colours[order], lw=2.2, marker="o", label=order)
        gx.set_xlabel("labelled executions")
        gx.set_ylabel(f"greedy success, first {greedy[0].greedy_tasks} main test tasks")
        gx.set_title("what the labels buy in knots (Wilson 95 %)", fontsize=10)
        gx.grid(alpha=0.3)
        gx.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    _atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    return path


def _pair(text: str) -> tuple[int, int]:
    a, b = (int(v) for v in text.split(","))
    return a, b


def main() -> int:
    """Run both learning curves, print the table, save the plot (and a JSON beside it)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--labels", default=str(ROOT / "results" / "labels_oracle_main.jsonl"))
    ap.add_argument("--library", default=str(defaults.library_path()))
    ap.add_argument("--step", type=int, default=20, help="executions added per round (20)")
    ap.add_argument("--max-labels", type=int, default=200, help="last curve point (200)")
    ap.add_argument("--seeds", default="0,1", help="curve seeds (seed set, random order)")
    ap.add_argument("--split-seed", type=int, default=0, help="seed of the fixed held-out split")
    ap.add_argument("--validation-fraction", type=float, default=0.2)
    ap.add_argument("--C", type=float, default=1000.0)
    ap.add_argument("--D", type=float, default=10.0)
    ap.add_argument("--landmarks", type=_pair, default=(0, 0), help="labelled,dead-end (0,0)")
    ap.add_argument("--greedy-tasks", type=int, default=0, help="greedy on K test tasks (0)")
    ap.add_argument("--greedy-every", type=int, default=40, help="at every E-th size (40)")
    ap.add_argument("--workers", type=int, default=2, help="bench workers for greedy (2)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "active_learning" / "curve.png"))
    ap.add_argument("--json", action="store_true", help="print the summary as JSON last")
    args = ap.parse_args()
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    args.seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if args.step < 1 or args.max_labels < args.step:
        print("active_learning: error: need 1 <= --step <= --max-labels", file=sys.stderr)
        return 2
    if args.greedy_tasks < 0 or args.greedy_every < 1 or args.workers < 1:
        print("active_learning: error: need --greedy-tasks >= 0, --greedy-every and --workers "
              ">= 1", file=sys.stderr)  # fmt: skip
        return 2
    t0 = time.perf_counter()
    points, info = run_curve(args)
    summary = summarise(points)
    m = info["machine"]
    featurised = f"{info['featurize_s']} s" if info["featurize_s"] >= 1 else "cached"
    print(f"\nmachine: {m.get('cpu_model', m)}, {m.get('usable_cores', '?')} cores, "
          f"load {m.get('load_average_1m')}; "
          f"featurising {featurised}; "
          f"pool {info['n_pool']}, held out {info['n_held_out_executions']} executions "
          f"({info['n_held_out_states']} states); C={args.C:g} D={args.D:g} "
          f"landmarks {args.landmarks}")  # fmt: skip
    print(format_table(points, summary))
    print(f"reference: NN (lowest registration cost) held-out top-1 {info['nn_held_out_top1']:.3f}")
    out = Path(args.out)
    title = (
        f"Active learning on oracle labels: C={args.C:g}, D={args.D:g}, {len(args.seeds)} seeds,\n"
        f"{info['n_held_out_states']} held-out states; NN {info['nn_held_out_top1']:.3f}"
    )
    plot_curve(points, summary, out, title)
    record = {
        "info": info,
        "summary": summary,
        "points": [p.__dict__ for p in points],
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    _atomic_write(
        out.with_suffix(".json"), lambda tmp: tmp.write_text(json.dumps(record, indent=1))
    )
    print(f"plot: {out}   data: {out.with_suffix('.json')}   {record['wall_s']} s")
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
