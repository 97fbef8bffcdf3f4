"""Are the features task-independent? One task's learned weights ranking another task's demos.

The paper's claim, tested on the figure-eight knot (the target) with the overhand knot's labels
(the source). Every model ranks the target's demos with greedy on the target's test tasks:

- ``per-task``: the target's own model (its shipped one, all columns: costs, demo one-hots,
  landmarks); its outcomes are read from --reference-dir when that run used the same model;
- ``source as shipped``: the source task's shipped model, its weights on the portable columns
  (core/selection/transfer.py) moved onto the target's library, the rest 0: no retraining;
- ``source portable``: refitted on the source's labels, portable columns only (C chosen on the
  source's validation split): the source's knowledge in the form that can move;
- ``target portable``: the same fit on the target's labels (C chosen on the target's
  validation split): what the portable columns alone can do for this task;
- ``shared``: one fit on both tasks' labels pooled, portable columns (C chosen on the target's
  validation split): the model a lab would keep for both tasks.

"Within 5 points" compares ``shared`` against ``per-task``. Splits are the trainer's (by
execution, seed 0, a fifth held out); the test tasks are never used to choose anything.
Labels' tried candidates are applied when given (--source-tries, --target-tries).

Outputs in --out-dir (resumable: models and finished episodes are read back): model_<arm>.npz,
fit.json (validation metrics, chosen C), greedy_<arm>/ (a `knotlab bench` folder each),
transfer.json and transfer.png (success with Wilson intervals; paired against per-task).
Same inputs, same files: the fits are deterministic (seeded split, a convex QP), the episodes
are the bench's (seeded per task).

Usage: .venv/bin/python bench/task_transfer.py --out-dir results/figure8/transfer --tasks 500
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.experiments.bench.report import wilson_interval  # noqa: E402
from knotlab.core.machine import machine_info  # noqa: E402
from knotlab.core.selection.features import LibraryFeaturizer  # noqa: E402
from knotlab.core.selection.learner import MaxMarginQLearner, TrainingData  # noqa: E402
from knotlab.core.selection.model_selection import (  # noqa: E402
    featurize_executions,
    merge_training_data,
    ranking_metrics,
    split_executions,
)
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.transfer import (  # noqa: E402
    PortableColumns,
    pool_portable,
    pool_with_own_columns,
    transplant,
)
from knotlab.core.selection.tries import apply_tries, read_tries  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402
from knotlab.labeling_db.interchange import read_labels  # noqa: E402

ARMS = (
    "per-task",
    "source as shipped",
    "source portable",
    "target portable",
    "shared",
    "target + demos",
    "shared + demos",
)
FITTED = ("source portable", "target portable", "shared", "target + demos", "shared + demos")


def slug(arm: str) -> str:
    """File-name form of an arm's name."""
    return arm.replace(" + ", "+").replace(" ", "_")


def featurised(labels: Path, tries: Path | None, library: DemoLibrary, workers: int):
    """Training and validation QP inputs of a labels file (the trainer's split), no landmarks."""
    executions = [item.execution for item in read_labels(labels)]
    parts, warnings = featurize_executions(executions, library, workers=workers)
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    if tries is not None:
        by_state = read_tries(tries)
        keys = tuple(library.keys)
        parts = [
            None if p is None else apply_tries(p, e.execution_id, by_state, keys)
            for p, e in zip(parts, executions, strict=True)
        ]
    train_idx, val_idx = split_executions(len(executions), 0.2, 0)
    train = merge_training_data([parts[i] for i in train_idx if parts[i] is not None])
    val = merge_training_data([parts[i] for i in val_idx if parts[i] is not None])
    return train, val


def fit_portable(
    train: TrainingData,
    columns: PortableColumns,
    validate: Callable[[QModel], dict],
    c_values: list[float],
) -> tuple[QModel, list[dict]]:
    """Fit on the given columns for each C (D = 1), the best by validation top-1 then rank."""
    sweep = []
    for c in c_values:
        model = MaxMarginQLearner(C=c, D=1.0).fit(train, columns)
        m = validate(model)
        sweep.append((model, {"C": c, **m}))
    best = max(sweep, key=lambda x: (x[1]["top1"], -x[1]["mean_expert_rank"]))
    return best[0], [s for _, s in sweep]


def main() -> int:
    """Fit the arms, play greedy with each on the target's test tasks, report."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", default="overhand")
    ap.add_argument("--target", default="figure8")
    ap.add_argument("--source-labels", type=Path, default=ROOT / "results/labels_oracle_main.jsonl")
    ap.add_argument("--source-tries", type=Path, default=ROOT / "results/tries_main.jsonl")
    ap.add_argument(
        "--target-labels", type=Path, default=ROOT / "results/figure8/labels_oracle_main.jsonl"
    )
    ap.add_argument("--target-tries", type=Path, default=None)
    ap.add_argument("--reference-dir", type=Path, default=ROOT / "results/figure8/table1_main")
    ap.add_argument("--C", default="10,100,1000")
    ap.add_argument("--level", default="main")
    ap.add_argument("--tasks", type=int, default=500)
    ap.add_argument("--arms", default=",".join(ARMS), help="which arms to play (comma list)")
    ap.add_argument(
        "--extra",
        action="append",
        default=[],
        metavar="NAME=PATH",
        help="another model of the target task to play and report beside the arms",
    )
    ap.add_argument("--report", action="store_true", help="play nothing: report what ran")
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    c_values = [float(c) for c in args.C.split(",")]
    source, target = get_task(args.source), get_task(args.target)
    src_lib = DemoLibrary.load(source.files.library_path)
    tgt_lib = DemoLibrary.load(target.files.library_path)
    tgt_spec = LibraryFeaturizer(tgt_lib).feature_spec
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    fit_path = out / "fit.json"
    report = json.loads(fit_path.read_text()) if fit_path.exists() else {"arms": {}}
    extra = dict(item.split("=", 1) for item in args.extra)
    models = {
        "per-task": target.files.model_path,
        **{a: out / f"model_{slug(a)}.npz" for a in ARMS[1:]},
    }
    extra_models = {name: Path(path) for name, path in extra.items()}
    if not models["source as shipped"].exists():
        shipped = QModel.load(source.files.model_path)
        transplant(shipped, tgt_spec).save(models["source as shipped"])
    if not all(models[a].exists() for a in FITTED):
        t0 = time.perf_counter()
        s_train, s_val = featurised(args.source_labels, args.source_tries, src_lib, args.workers)
        t_train, t_val = featurised(args.target_labels, args.target_tries, tgt_lib, args.workers)
        src_spec = LibraryFeaturizer(src_lib).feature_spec
        s_train_p, cols = pool_portable([(s_train, src_spec)])
        s_val_p, _ = pool_portable([(s_val, src_spec)])
        t_train_p, _ = pool_portable([(t_train, tgt_spec)])
        t_val_p, _ = pool_portable([(t_val, tgt_spec)])
        both_p, _ = pool_portable([(s_train, src_spec), (t_train, tgt_spec)])
        own_t, cols_t = pool_with_own_columns([(args.target, t_train, tgt_spec)])
        own_both, cols_both = pool_with_own_columns(
            [(args.source, s_train, src_spec), (args.target, t_train, tgt_spec)]
        )
        carry = {f"{args.target}:{n}": n for n in tgt_spec.names if n.startswith("demo[")}

        def on_target(model: QModel) -> dict:  # the target's held-out states, all its columns
            return ranking_metrics(transplant(model, tgt_spec, also=carry), t_val)

        plan = {
            "source portable": (s_train_p, cols, lambda m: ranking_metrics(m, s_val_p)),
            "target portable": (t_train_p, cols, lambda m: ranking_metrics(m, t_val_p)),
            "shared": (both_p, cols, lambda m: ranking_metrics(m, t_val_p)),
            "target + demos": (own_t, cols_t, on_target),
            "shared + demos": (own_both, cols_both, on_target),
        }
        for arm, (train, columns, validate) in plan.items():
            if models[arm].exists():
                continue
            model, sweep = fit_portable(train, columns, validate, c_values)
            transplant(model, tgt_spec, also=carry if "demos" in arm else None).save(models[arm])
            report["arms"][arm] = {
                "sweep": sweep,
                "chosen_C": model.hyperparameters["C"],
                "train_states": len(train.states),
                "validated_on": "source" if arm == "source portable" else "target",
            }
        # (summed over the runs that fitted something: arms added later fit in a later run)
        spent = time.perf_counter() - t0
        report["featurize_and_fit_s"] = round(report.get("featurize_and_fit_s", 0.0) + spent, 1)
        report["target_validation_states"] = len(t_val.states)
        fit_path.write_text(json.dumps(report, indent=1, sort_keys=True))
    todo = {**models, **extra_models}
    scored = report.setdefault("target_validation", {})
    if any(arm not in scored for arm in todo):
        todo = {a: p for a, p in todo.items() if a not in scored}
        scored.update(target_validation(todo, args.target_labels, tgt_lib, args.workers))
        fit_path.write_text(json.dumps(report, indent=1, sort_keys=True))
    models = {**models, **extra_models}

    play = [a.strip() for a in args.arms.split(",") if a.strip()]
    outcomes: dict[str, dict[str, bool]] = {}
    for arm in models:
        folder = out / f"greedy_{slug(arm)}"
        path = models[arm]
        if arm == "per-task" and _same_model(args.reference_dir, path):
            folder = args.reference_dir
        elif not args.report and (arm in play or arm in extra_models):
            cmd = [
                str(ROOT / ".venv/bin/knotlab"), "bench", "--task", args.target,
                "--policies", "greedy", "--tasks", str(args.tasks), "--level", args.level,
                "--model", str(path), "--out-dir", str(folder), "--force",
                "--workers", str(args.workers),
            ]  # fmt: skip
            subprocess.run(cmd, check=True)
        if (folder / "outcomes.jsonl").exists():  # an arm not played (yet) is left out
            outcomes[arm] = _greedy_outcomes(folder, args.tasks)
    nn = _policy_outcomes(args.reference_dir, "nn", args.tasks)
    summary = _summarise(outcomes, nn)
    result = {
        "source": args.source,
        "target": args.target,
        "level": args.level,
        "tasks": args.tasks,
        "models": {
            a: {"path": _rel(p), "hash": QModel.load(p).content_hash()} for a, p in models.items()
        },
        "fit": report,
        "greedy": summary,
        "machine": machine_info(),
    }
    (out / "transfer.json").write_text(json.dumps(result, indent=1, sort_keys=True))
    _table(result)
    _plot(result, out / "transfer.png")
    return 0


def target_validation(
    models: dict[str, Path], labels: Path, library: DemoLibrary, workers: int
) -> dict[str, dict]:
    """Every arm's ranking metrics on the target's held-out labelled states (the trainer's
    split); each model featurised as it ranks (the per-task model with its landmarks)."""
    executions = [item.execution for item in read_labels(labels)]
    _, val_idx = split_executions(len(executions), 0.2, 0)
    held = [executions[i] for i in val_idx]
    data_by_landmarks: dict[str | None, TrainingData] = {}
    out = {}
    for arm, path in models.items():
        model = QModel.load(path)
        key = model.feature_spec.landmark_hash
        if key not in data_by_landmarks:
            parts, _ = featurize_executions(
                held, library, workers=workers, progress=False, landmarks=model.landmarks
            )
            data_by_landmarks[key] = merge_training_data([p for p in parts if p is not None])
        m = ranking_metrics(model, data_by_landmarks[key])
        out[arm] = {k: m[k] for k in ("top1", "top3", "mean_expert_rank", "value_auc", "n_states")}
    return out


def _rel(path: Path) -> str:
    path = Path(path).resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def _same_model(folder: Path, model_path: Path) -> bool:
    """Did the bench run in ``folder`` rank with this model?"""
    results = folder / "results.json"
    if not results.exists():
        return False
    return (
        json.loads(results.read_text()).get("model_hash") == QModel.load(model_path).content_hash()
    )


def _policy_outcomes(folder: Path, policy: str, n_tasks: int) -> dict[str, bool]:
    """Task id -> success of one policy's episodes in a bench folder (the first n_tasks tasks);
    a folder whose episodes errored is not a result."""
    lines = [json.loads(x) for x in (folder / "outcomes.jsonl").read_text().splitlines()]
    got = {r["task_id"]: r for r in lines if r["policy"] == policy}
    errored = [t for t, r in got.items() if r.get("error")]
    if errored:
        raise SystemExit(f"{folder}: {len(errored)} {policy} episodes errored (e.g. {errored[0]})")
    ids = sorted(got)[:n_tasks]
    return {t: bool(got[t]["success"]) for t in ids}


def _greedy_outcomes(folder: Path, n_tasks: int) -> dict[str, bool]:
    return _policy_outcomes(folder, "greedy", n_tasks)


def _summarise(outcomes: dict[str, dict[str, bool]], nn: dict[str, bool]) -> dict:
    """Per arm: successes, Wilson interval, paired against per-task and against NN."""
    from scipy.stats import binomtest

    ref = outcomes.get("per-task", nn)
    out = {}
    for arm, got in {**outcomes, "nn": nn}.items():
        k, n = sum(got.values()), len(got)
        lo, hi = wilson_interval(k, n) if n else (float("nan"), float("nan"))
        row = {"successes": k, "n": n, "rate": k / n if n else float("nan"), "wilson": [lo, hi]}
        for name, other in (("per_task", ref), ("nn", nn)):
            common = sorted(set(got) & set(other))
            wins = sum(got[t] and not other[t] for t in common)
            losses = sum(other[t] and not got[t] for t in common)
            p = binomtest(wins, wins + losses).pvalue if wins + losses else 1.0
            row[f"vs_{name}"] = {
                "n": len(common),
                "points": 100
                * (sum(got[t] for t in common) - sum(other[t] for t in common))
                / max(len(common), 1),
                "wins": wins,
                "losses": losses,
                "p": float(p),
            }
        out[arm] = row
    return out


def _table(result: dict) -> None:
    val = result["fit"].get("target_validation", {})
    print(
        f"greedy on the {result['target']} {result['level']} test tasks "
        f"(source task: {result['source']})"
    )
    print("| arm | greedy success | Wilson 95 % | vs per-task (points; wins / losses; p) "
          "| vs NN (points; p) | val top-1 |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for arm, r in result["greedy"].items():
        lo, hi = r["wilson"]
        vp, vn = r["vs_per_task"], r["vs_nn"]
        top1 = val.get(arm, {}).get("top1")
        print(
            f"| {arm} | {r['successes']}/{r['n']} = {100 * r['rate']:.1f} % | "
            f"[{100 * lo:.1f}, {100 * hi:.1f}] | {vp['points']:+.1f}; {vp['wins']} / "
            f"{vp['losses']}; {vp['p']:.3g} | {vn['points']:+.1f}; {vn['p']:.3g} | "
            + ("-" if top1 is None else f"{top1:.3f}")
            + " |"
        )


def _plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["greedy"]
    names = list(rows)
    fig, ax = plt.subplots(figsize=(8, 4))
    palette = [f"C{k}" for k in range(10) if k != 7]  # C7 is the grey kept for NN
    for i, arm in enumerate(names):
        r = rows[arm]
        lo, hi = r["wilson"]
        ax.bar(i, r["rate"], color="#7f7f7f" if arm == "nn" else palette[i % len(palette)])
        ax.plot([i, i], [lo, hi], color="black", lw=1.5)
        ax.text(i, hi + 0.01, f"{100 * r['rate']:.1f} %", ha="center", fontsize=9)
    ax.set_xticks(range(len(names)), [n.replace(" ", "\n") for n in names], fontsize=9)
    ax.axhline(rows["nn"]["rate"], color="#7f7f7f", ls="--", lw=1)  # nearest neighbour
    ax.set_ylabel("greedy success (Wilson 95 %)")
    ax.set_ylim(0, 1)
    ax.set_title(
        f"{result['target']} {result['level']} test, {result['tasks']} tasks: "
        f"weights from {result['source']}, shared, per task"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
