"""One model for both perturbation levels, or one per level: chosen on held-out training starts.

The shipped model was fitted on the main level's oracle labels only; the hard level's starts are
perturbed twice as far (rho 0.10 m against 0.05 m) and no hard-level label was ever seen. Each
level's oracle executions are split by the same seeded fifth as `bench/policy_states.py` (the
held-out starts are never trained on), and three models are fitted with the shipped model's
settings (C = 1000, D = 10, landmarks 50 + 20, the tried candidates):

- ``main``: the main level's training part (the shipped model's data: policy_states' round 0),
- ``hard``: the hard level's training part,
- ``both``: both training parts together,
- ``both+policy``: both, plus the main level's round-1 policy states (the oracle's labels of the
  states greedy reached from the main training starts, with their own tried candidates; the
  states reached from a held-out start are left out): every label made so far that no held-out
  start contributed to. The overhand knot's come from `bench/policy_states.py`
  (results/policy_states_main/), another task's from `knotlab label --oracle --from-policy
  greedy` exported to results/<task>/policy_states/round1.jsonl and tried by `knotlab labels
  tries` into tries_round1.jsonl there.

``--task`` fits another registered task's models the same way, from its own files under
``results/<task>/`` (labels_oracle_<level>.jsonl, tries_<level>.jsonl) with its shipped model's C
and D; ``both+policy`` is fitted where the task's policy-state labels exist.

Every model is scored on each level's held-out starts: greedy's success (episodes in
simulation, Wilson 95 % intervals) and top-1 / V-AUC on the held-out executions' labelled states.
The test sets are never touched. The choice rule, fixed before the run: per level, the model with
the higher greedy success on that level's held-out starts (ties: higher top-1); one model for
both levels when it is chosen on both.

Outputs in --out-dir (resumable: a fitted model and its scores are read back): model_<name>.npz,
levels.json (each model with its scores, wall time and the machine that scored it),
levels.png. Same seed, same files.

``--models NAME,...`` fits only those; ``--C X`` fits them with another slack weight, named
``NAME-CX`` (give them their own --out-dir: the choice rule reads every model in levels.json).

Usage: .venv/bin/python bench/level_models.py --out-dir results/level_models [--workers 2]
       .venv/bin/python bench/level_models.py --task figure8 --out-dir results/figure8/level_models
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Collection, Iterable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from policy_states import _read, fit, greedy_success  # noqa: E402

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import RopeTask  # noqa: E402
from knotlab.core.experiments.bench.report import wilson_interval  # noqa: E402
from knotlab.core.machine import machine_info  # noqa: E402
from knotlab.core.selection.labels import LabelledExecution  # noqa: E402
from knotlab.core.selection.model_selection import (  # noqa: E402
    featurize_executions,
    merge_training_data,
    ranking_metrics,
    split_executions,
)
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.tries import read_tries  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402

LEVELS = ("main", "hard")
MODELS = {
    "main": ("main",),
    "hard": ("hard",),
    "both": ("main", "hard"),
    "both+policy": ("main", "hard", "policy"),
}


def results_dir(task_name: str) -> Path:
    """Where a task's labels and tries are (scripts/table1.sh's layout): the overhand knot's in
    results/, every other task's in results/<task>/."""
    return ROOT / "results" if task_name == "overhand" else ROOT / "results" / task_name


def policy_states_dir(task_name: str) -> Path:
    """Where a task's round-1 policy-state labels are (round1.jsonl, tries_round1.jsonl)."""
    if task_name == "overhand":
        return ROOT / "results/policy_states_main"
    return results_dir(task_name) / "policy_states"


@dataclass(frozen=True)
class LevelSplit:
    """One level's oracle executions, split into training and held-out parts by the seed."""

    level: str
    train: tuple[LabelledExecution, ...]
    held_out: tuple[LabelledExecution, ...]
    held_out_starts: tuple[RopeTask, ...]


def reached_from_training(
    executions: Iterable[LabelledExecution], held_tasks: Collection[str]
) -> tuple[LabelledExecution, ...]:
    """The policy-state executions whose first state greedy reached from a training start."""
    return tuple(
        e for e in executions if e.metadata["reached_by"]["start_task_id"] not in held_tasks
    )


def level_split(task, level: str, labels: Path) -> LevelSplit:
    """The level's executions split as bench/policy_states.py splits them (seed 0, a fifth)."""
    executions = _read(labels)
    if not executions:
        raise SystemExit(
            f"{labels}: no labels (make them with `STOP=labels scripts/table1.sh "
            f"--task TASK {level}`)"
        )
    train_idx, val_idx = split_executions(len(executions), 0.2, 0)
    held = tuple(executions[i] for i in val_idx)
    held_ids = {e.task_id for e in held}
    starts = tuple(s for s in task.files.load_task_set(level, "train") if s.task_id in held_ids)
    return LevelSplit(level, tuple(executions[i] for i in train_idx), held, starts)


def held_out_ranking(model_path: Path, split: LevelSplit, library: DemoLibrary) -> dict:
    """Top-1 and V-AUC of a model on one level's held-out labelled states."""
    model = QModel.load(model_path)
    parts, _ = featurize_executions(
        split.held_out, library, workers=1, progress=False, landmarks=model.landmarks
    )
    data = merge_training_data([p for p in parts if p is not None])
    m = ranking_metrics(model, data)
    return {"top1": m["top1"], "value_auc": m["value_auc"], "n_states": m["n_states"]}


def main() -> int:
    """Fit the three models, score each on both levels' held-out starts, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--task", default="overhand")
    ap.add_argument("--models", default=None, help="NAME,NAME,... (default: every model)")
    ap.add_argument(
        "--C", type=float, default=None, help="slack weight (default: the shipped model's)"
    )
    args = ap.parse_args()
    task = get_task(args.task)
    files = results_dir(args.task)
    shipped = QModel.load(task.files.model_path).hyperparameters
    D = float(shipped["D"])
    C, suffix = slack_weight(shipped, args.C)
    library_path = task.files.library_path
    library = DemoLibrary.load(library_path)
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    path = out / "levels.json"
    report = json.loads(path.read_text()) if path.exists() else {"models": {}}
    for rec in report["models"].values():  # files from before models had a machine each
        rec.setdefault("machine", report.get("machine"))
    report.pop("machine", None)
    splits = {lv: level_split(task, lv, files / f"labels_oracle_{lv}.jsonl") for lv in LEVELS}
    tries: dict = {}
    for lv in LEVELS:
        tries.update(read_tries(files / f"tries_{lv}.jsonl"))
    models = dict(MODELS)
    held_tasks = {e.task_id for s in splits.values() for e in s.held_out}
    policy: tuple[LabelledExecution, ...] = ()
    policy_dir = policy_states_dir(args.task)
    if (policy_dir / "round1.jsonl").exists():
        tries.update(read_tries(policy_dir / "tries_round1.jsonl"))
        # A state greedy reached from a held-out start would leak that start into training.
        policy = reached_from_training(_read(policy_dir / "round1.jsonl"), held_tasks)
    else:
        del models["both+policy"]
    if args.models is not None:
        unknown = sorted(set(args.models.split(",")) - set(models))
        if unknown:
            raise SystemExit(f"--models: unknown {', '.join(unknown)}; known: {', '.join(models)}")
        models = {n: models[n] for n in args.models.split(",")}
    models = {name + suffix: levels for name, levels in models.items()}
    held_ids = frozenset(e.execution_id for s in splits.values() for e in s.held_out)
    for name, levels in models.items():
        rec = report["models"].get(name, {})
        model_path = out / f"model_{name}.npz"
        if not (model_path.exists() and rec.get("scores", {}).keys() >= set(LEVELS)):
            t0 = time.perf_counter()
            executions = [
                e for lv in levels for e in (policy if lv == "policy" else splits[lv].train)
            ]
            fit(executions, library, held_ids, tries, model_path, args.workers, C=C, D=D)
            rec = {
                "levels": list(levels),
                "model": str(model_path.relative_to(ROOT))
                if model_path.is_relative_to(ROOT)
                else str(model_path),
                "model_hash": QModel.load(model_path).content_hash(),
                "train_executions": len(executions),
                "train_states": sum(len(e.steps) for e in executions),
                "C": C,
                "D": D,
                "scores": {},
            }
            for lv in LEVELS:
                s = splits[lv]
                success = greedy_success(
                    library_path, model_path, list(s.held_out_starts), args.workers
                )
                rec["scores"][lv] = {
                    "greedy_success": success,
                    "starts": len(s.held_out_starts),
                    **held_out_ranking(model_path, s, library),
                }
            rec["wall_s"] = round(time.perf_counter() - t0, 1)
            # Where this model's scores were computed: a resume may add a model on another
            # machine, whose last bits (and so some episodes) differ from the others'.
            rec["machine"] = machine_info()
            report["models"][name] = rec
            path.write_text(json.dumps(report, indent=1, sort_keys=True))
        print(f"{name}: {json.dumps(rec['scores'])}", flush=True)
    report["task"] = args.task
    report["chosen"] = {lv: choose(report["models"], lv) for lv in LEVELS}
    path.write_text(json.dumps(report, indent=1, sort_keys=True))
    _plot(report, out / "levels.png")
    _table(report)
    return 0


def choose(models: dict, level: str) -> str:
    """The rule fixed before the run: higher held-out greedy success, then higher top-1."""
    return max(
        models,
        key=lambda n: (
            models[n]["scores"][level]["greedy_success"],
            models[n]["scores"][level]["top1"],
        ),
    )


def _variant(
    shipped: dict, key: str, requested: float | None, tag: str, default: float | None = None
) -> tuple[float, str]:
    """A hyper-parameter to fit with (default: the shipped model's, else ``default``) and the
    suffix its models' names take: "" for the shipped value, else "-<tag><value>"."""
    base = float(shipped[key] if default is None else shipped.get(key, default))
    value = base if requested is None else float(requested)
    return value, "" if value == base else f"-{tag}{value:g}"


def slack_weight(shipped: dict, requested: float | None) -> tuple[float, str]:
    """The slack weight C to fit with and its models' name suffix ("-C<value>" if not shipped)."""
    return _variant(shipped, "C", requested, "C")


def margin_weight(shipped: dict, requested: float | None) -> tuple[float, str]:
    """The margin scale to fit with (a model from before it was recorded: 1) and its models'
    name suffix ("-m<value>" if not shipped)."""
    return _variant(shipped, "margin_scale", requested, "m", default=1.0)


def _ordered(models: dict) -> list[str]:
    """The models in the fixed order (then any other slack weight's), not the file's sorted one."""
    return [n for n in MODELS if n in models] + sorted(set(models) - set(MODELS))


def _plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = report["models"]
    names = _ordered(models)
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / len(names)
    for i, name in enumerate(names):
        for j, lv in enumerate(LEVELS):
            sc = models[name]["scores"][lv]
            n = sc["starts"]
            k = round(sc["greedy_success"] * n)
            lo, hi = wilson_interval(k, n)
            x = j + (i - (len(names) - 1) / 2) * width
            ax.bar(x, k / n, width, color=f"C{i}", label=name if j == 0 else None)
            ax.plot([x, x], [lo, hi], color="black", lw=1.5)
    ax.set_xticks(range(len(LEVELS)), [f"{lv} level held-out starts" for lv in LEVELS])
    ax.set_ylabel("greedy success (Wilson 95 %)")
    ax.set_ylim(0, 1)
    ax.set_title(
        f"Which labels train the greedy policy ({report.get('task', 'overhand')}): by level"
    )
    ax.legend(title="trained on")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _table(report: dict) -> None:
    print(
        "| model | training states | "
        + " | ".join(f"{lv} greedy | {lv} top-1 | {lv} V-AUC" for lv in LEVELS)
        + " | scored on |"
    )
    print("|---|---|" + "---|" * (3 * len(LEVELS) + 1))
    for name in _ordered(report["models"]):
        rec = report["models"][name]
        cells = []
        for lv in LEVELS:
            sc = rec["scores"][lv]
            k, n = round(sc["greedy_success"] * sc["starts"]), sc["starts"]
            cells += [f"{k}/{n} = {k / n:.3f}", f"{sc['top1']:.3f}", f"{sc['value_auc']:.3f}"]
        kind = (rec.get("machine") or {}).get("vector_width", "?")
        print(f"| {name} | {rec['train_states']} | " + " | ".join(cells) + f" | {kind} |")
    print(f"chosen on validation: {report['chosen']}")


if __name__ == "__main__":
    raise SystemExit(main())
