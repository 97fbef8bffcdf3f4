"""Learning curve of policy-state labelling (DAgger-style) against more oracle trajectories.

Rounds: round 0 is the model fitted on the oracle's own executions of the level's training starts
(the shipped model's data and settings: 240 training executions, 60 held out by the seeded split,
C = 1000, D = 10, landmarks 50 + 20, the tried candidates). Round r rolls greedy with model r-1
out on the 240 training starts, the oracle labels every state it reaches after the start
(`core.experiments.policy_states`), and model r is fitted on the oracle executions plus every
policy-state label so far. The control adds the same number of labelled states from the oracle's
own executions of extra training starts (perturbed with another seed), so a gain can be told
apart from the number of labels. Every model is scored on the same 60 held-out training starts:
greedy's success (episodes in simulation) and top-1 agreement with the oracle's labelled states.
The test sets are never touched here. Where ``tries_round<r>.jsonl`` exists in --out-dir (the
policy states' own tried candidates, `knotlab labels tries`), round r is fitted once more with
them (point ``round<r>+tries``): without them a policy state's margin rows ask the oracle's demo
to beat every other demo, including ones that would have done as well.

Outputs in --out-dir (resumable: a finished round or arm is read back, a started labelling round
continues): round<r>.jsonl (policy-state labels, knotlab's labels format, provenance in each
execution's metadata `reached_by`), control.jsonl, model_r<r>.npz, model_control.npz,
curve.json and curve.png. Same seed, same files: every rollout, search and fit is seeded.

Usage: .venv/bin/python bench/policy_states.py --rounds 2 --out-dir results/policy_states_main
       [--level main] [--control] [--workers 2]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import RopeTask, generate_tasks  # noqa: E402
from knotlab.core.experiments.bench.report import wilson_interval  # noqa: E402
from knotlab.core.experiments.labeller import oracle_label_tasks  # noqa: E402
from knotlab.core.experiments.policy_states import (  # noqa: E402
    REACHED_BY,
    label_policy_state_tasks,
)
from knotlab.core.machine import machine_info  # noqa: E402
from knotlab.core.parallel import PerProcess, imap_processes  # noqa: E402
from knotlab.core.selection.labels import LabelledExecution  # noqa: E402
from knotlab.core.selection.model_selection import QModelSearch, split_executions  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.tries import read_tries  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402
from knotlab.core.tasks.base import level_of  # noqa: E402
from knotlab.labeling_db.interchange import read_labels, write_labels  # noqa: E402
from knotlab.labeling_db.records import StoredExecution  # noqa: E402

CONTROL_SEED_OFFSET = 7919  # extra training starts: the level's seed plus this (another stream)


# ----------------------------------------------------------------------------- label files
def _append(path: Path, executions: list[LabelledExecution]) -> None:
    """Append executions to a labels JSONL file (header written on creation)."""
    buf = io.StringIO()
    now = datetime.now(UTC)  # when it was labelled (the labels format requires it)
    items = [StoredExecution(e, started_at=now, finished_at=now) for e in executions]
    write_labels(items, buf, "jsonl")
    lines = buf.getvalue().splitlines(keepends=True)
    with path.open("a", encoding="utf-8") as fh:
        fh.writelines(lines if fh.tell() == 0 else lines[1:])
        fh.flush()
        os.fsync(fh.fileno())


def _read(path: Path) -> list[LabelledExecution]:
    return [item.execution for item in read_labels(path)] if path.exists() else []


def _states(executions: list[LabelledExecution]) -> int:
    return sum(len(e.steps) for e in executions)


# ----------------------------------------------------------------------------- evaluation
def _build_agent(key: tuple[str, str]):
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    library_path, model_path = key
    library = DemoLibrary.load(library_path)
    return RopeWorld(), Agent(library, QModel.load(model_path), "greedy")


_AGENTS = PerProcess(_build_agent)


def _episode(job: tuple[str, str, RopeTask]) -> bool:
    world, agent = _AGENTS.get((job[0], job[1]))
    return bool(agent.run_episode(world, job[2]).success)


def greedy_success(library: Path, model: Path, starts: list[RopeTask], workers: int) -> float:
    """Greedy's success rate on ``starts`` with ``model`` (episodes in simulation)."""
    jobs = [(str(library), str(model), s) for s in starts]
    wins = sum(
        ok
        for _, ok in imap_processes(
            _episode, jobs, workers=workers, desc=f"greedy on {len(starts)} held-out starts"
        )
    )
    return wins / len(starts)


# ----------------------------------------------------------------------------- fitting
def fit(
    executions: list[LabelledExecution],
    library: DemoLibrary,
    held_out: frozenset[str],
    tries: dict,
    out: Path,
    workers: int,
    C: float = 1000.0,
    D: float = 10.0,
    margin_scale: float = 1.0,
) -> tuple[Path, dict]:
    """Fit with the shipped model's settings (C, D, margin scale) on everything but the
    held-out executions."""
    search = QModelSearch(
        C=(C,),
        D=(D,),
        margin_scale=margin_scale,
        landmarks=(50, 20),
        tries=tries,
        validation_ids=held_out,
        random_state=0,
        workers=workers,
    )
    search.fit(executions, library)
    model = search.best_model_
    model = dataclasses.replace(model, metrics={**model.metrics, "training_run": search.info_})
    model.save(out)
    return out, dict(search.validation_ or {})


# ----------------------------------------------------------------------------- main
def main() -> int:
    """Run the rounds (and the control), write curve.json and curve.png, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--level", default="main")
    ap.add_argument("--labels", type=Path, default=ROOT / "results/labels_oracle_main.jsonl")
    ap.add_argument("--tries", type=Path, default=ROOT / "results/tries_main.jsonl")
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--control", action="store_true", help="also the same-count oracle control")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()

    task = get_task("overhand")
    library_path = task.files.library_path
    library = DemoLibrary.load(library_path)
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    curve_path = out / "curve.json"
    curve = json.loads(curve_path.read_text()) if curve_path.exists() else {"points": {}}
    curve["machine"] = machine_info()

    oracle = _read(args.labels)
    train_idx, val_idx = split_executions(len(oracle), 0.2, 0)
    held_out = frozenset(oracle[i].execution_id for i in val_idx)
    train_ids = {oracle[i].task_id for i in train_idx}
    val_ids = {oracle[i].task_id for i in val_idx}
    starts = list(task.files.load_task_set(args.level, "train"))
    train_starts = [s for s in starts if s.task_id in train_ids]
    val_starts = [s for s in starts if s.task_id in val_ids]
    tries = read_tries(args.tries)
    print(
        f"{len(oracle)} oracle executions: {len(train_starts)} training starts, "
        f"{len(val_starts)} held out; {_states([oracle[i] for i in train_idx])} training states",
        flush=True,
    )

    def point(
        name: str, executions: list[LabelledExecution], model_path: Path, extra_tries=None
    ) -> dict:
        if name in curve["points"] and model_path.exists():
            return curve["points"][name]
        t0 = time.perf_counter()
        fit_tries = {**tries, **(extra_tries or {})}
        _, validation = fit(executions, library, held_out, fit_tries, model_path, args.workers)
        success = greedy_success(library_path, model_path, val_starts, args.workers)
        train_states = _states([e for e in executions if e.execution_id not in held_out])
        rec = {
            "model": str(
                model_path.relative_to(ROOT) if model_path.is_relative_to(ROOT) else model_path
            ),
            "model_hash": QModel.load(model_path).content_hash(),
            "train_states": train_states,
            "train_executions": sum(e.execution_id not in held_out for e in executions),
            "validation_top1": validation.get("top1"),
            "validation_value_auc": validation.get("value_auc"),
            "validation_greedy_success": success,
            "validation_starts": len(val_starts),
            "tried_states": len(fit_tries),
            "wall_s": round(time.perf_counter() - t0, 1),
        }
        curve["points"][name] = rec
        curve_path.write_text(json.dumps(curve, indent=1, sort_keys=True))
        print(f"{name}: {json.dumps(rec)}", flush=True)
        return rec

    labels = list(oracle)
    point("round0", labels, out / "model_r0.npz")
    for r in range(1, args.rounds + 1):
        prev = out / f"model_r{r - 1}.npz"
        path = out / f"round{r}.jsonl"
        have = _read(path)
        done = {e.metadata[REACHED_BY]["start_task_id"] for e in have}
        todo = [s for s in train_starts if s.task_id not in done]
        t0 = time.perf_counter()
        rollouts = curve.setdefault("rollouts", {}).setdefault(f"round{r}", {})
        for res in label_policy_state_tasks(
            library_path, prev, todo, round_index=r, workers=args.workers
        ):
            _append(path, list(res.executions))
            rollouts[res.task_id] = [res.rollout_knot, res.rollout_steps, res.simulations]
        curve["rollouts"][f"round{r}"] = rollouts
        curve.setdefault("label_wall_s", {})[f"round{r}"] = round(time.perf_counter() - t0, 1)
        labels += _read(path)
        point(f"round{r}", labels, out / f"model_r{r}.npz")
        # The policy states' own tried candidates (`knotlab labels tries --labels round<r>.jsonl
        # --out tries_round<r>.jsonl`), when made: the same labels, margin rows that follow them.
        round_tries = out / f"tries_round{r}.jsonl"
        if round_tries.exists():
            point(f"round{r}+tries", labels, out / f"model_r{r}_tries.npz", read_tries(round_tries))
        if r == 1 and args.control:
            target = _states(_read(path))
            control = _control(task, library, args.level, target, out, args.workers)
            point("control", list(oracle) + control, out / "model_control.npz")
    curve_path.write_text(json.dumps(curve, indent=1, sort_keys=True))
    _plot(curve, out / "curve.png")
    _table(curve)
    return 0


def _control(task, library, level_name: str, target: int, out: Path, workers: int):
    """Oracle executions of extra training starts until ``target`` labelled states."""
    path = out / "control.jsonl"
    have = _read(path)
    level = level_of(task, level_name)
    n = math.ceil(target / 2.4) + 10  # the oracle labels ~2.9 states per start on main
    seed = level.seed + CONTROL_SEED_OFFSET
    extra = generate_tasks(
        library.start_states(),
        n,
        split="train",
        rho=level.rho_m,
        seed=seed,
        n_centres=level.n_centres,
        level=level_name,
        workers=workers,
    )
    done = {e.execution_id for e in have}
    todo = [t for t in extra if f"extra{seed}-{t.task_id}" not in done]
    for res in oracle_label_tasks(task.files.library_path, todo, workers=workers):
        ex = res.execution
        _append(
            path,
            [
                dataclasses.replace(
                    ex,
                    execution_id=f"extra{seed}-{ex.task_id}",
                    task_id=f"extra{seed}-{ex.task_id}",
                )
            ],
        )
    chosen, states = [], 0
    for ex in sorted(_read(path), key=lambda e: e.execution_id):
        if states >= target:
            break
        chosen.append(ex)
        states += len(ex.steps)
    return chosen


_NUDGE = {"C2": 40, "C3": -40}  # x offsets (states) of points drawn at the same count


def _plot(curve: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = curve["points"]
    rounds = sorted((k for k in pts if k[5:].isdigit()), key=lambda k: int(k[5:]))
    with_tries = sorted(k for k in pts if k.startswith("round") and k.endswith("+tries"))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, label in (
        (axes[0], "validation_greedy_success", "greedy success, 60 held-out starts (Wilson 95 %)"),
        (axes[1], "validation_top1", "top-1 agreement with the oracle, held-out states"),
    ):
        xs = [pts[k]["train_states"] for k in rounds]
        ax.plot(xs, [pts[k][key] for k in rounds], "o-", label="policy-state rounds")
        if key == "validation_greedy_success":  # 60 episodes: show how wide that is
            marked = [(k, "C0") for k in rounds] + [(k, "C2") for k in with_tries]
            for name, colour in [*marked, ("control", "C3")]:
                if name in pts:
                    p = pts[name]
                    n = p["validation_starts"]
                    lo, hi = wilson_interval(round(p[key] * n), n)
                    x = p["train_states"] + _NUDGE.get(colour, 0)  # same counts: side by side
                    ax.plot([x] * 2, [lo, hi], color=colour, alpha=0.4, lw=4)
        for k, x in zip(rounds, xs, strict=True):
            ax.annotate(k, (x, pts[k][key]), textcoords="offset points", xytext=(4, 4))
        for k in with_tries:
            ax.plot(
                pts[k]["train_states"] + _NUDGE["C2"],
                pts[k][key],
                "D",
                color="C2",
                label="policy states with their tried candidates" if k == with_tries[0] else None,
            )
            ax.annotate(
                k,
                (pts[k]["train_states"] + _NUDGE["C2"], pts[k][key]),
                textcoords="offset points",
                xytext=(4, -12),
            )
        if "control" in pts:
            ax.plot(
                pts["control"]["train_states"] + _NUDGE["C3"],
                pts["control"][key],
                "s",
                color="C3",
                label="same count of oracle-trajectory labels",
            )
        ax.set_xlabel("labelled training states")
        ax.set_title(label)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _table(curve: dict) -> None:
    pts = curve["points"]
    print("| model | training states | val greedy success | val top-1 | val V-AUC |")
    print("|---|---|---|---|---|")
    for k, p in pts.items():
        print(
            f"| {k} | {p['train_states']} | {p['validation_greedy_success']:.3f} "
            f"({p['validation_starts']} starts) | {p['validation_top1']:.3f} | "
            f"{p['validation_value_auc']:.3f} |"
        )


if __name__ == "__main__":
    raise SystemExit(main())
