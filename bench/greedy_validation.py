"""Greedy with several models on the same fresh validation starts: paired, with enough starts to
tell models apart.

The 60 held-out training starts of `bench/policy_states.py` and `bench/level_models.py` give
Wilson intervals ~22 points wide, too wide to choose a model by. This script draws N fresh starts
of a level's training distribution (the level's rho and centres, the seed stream
``level seed + VALIDATION_SEED_OFFSET``: neither the training, the control nor the test stream),
plays greedy with every model on every start (the same rope and simulator for all models, so the
comparison is paired), and prints successes, Wilson 95 % intervals and, against the first
model, paired wins / losses with a two-sided sign test. The test sets are never touched.

Outputs in --out-dir (resumable: episodes already in outcomes.jsonl are not rerun; the starts are
regenerated from the seed and checked against the recorded hash): outcomes.jsonl (one line per
model and start), summary.json and greedy_validation.png.

Usage: .venv/bin/python bench/greedy_validation.py [--task figure8] --level main --starts 200
       --models round0=results/policy_states_main/model_r0.npz,... --out-dir DIR [--workers 2]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import RopeTask, TaskSet, generate_tasks  # noqa: E402
from knotlab.core.experiments.bench.report import wilson_interval  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.parallel import PerProcess, imap_processes  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402
from knotlab.core.tasks.base import level_of  # noqa: E402

VALIDATION_SEED_OFFSET = 104729  # the validation starts' stream: the level's seed plus this


def parse_models(text: str) -> dict[str, Path]:
    """NAME=PATH,NAME=PATH (in order; the first is the reference of the paired comparisons)."""
    out: dict[str, Path] = {}
    for item in text.split(","):
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"--models: expected NAME=PATH, got {item!r}")
        if name in out:
            raise SystemExit(f"--models: {name!r} named twice")
        if not Path(path).exists():
            raise SystemExit(f"--models: {path} does not exist")
        out[name] = Path(path)
    return out


def validation_starts(task_name: str, level_name: str, n: int, workers: int) -> tuple[TaskSet, int]:
    """``n`` fresh starts of a level's training distribution on the validation seed stream
    (named ``LEVEL-val-NNNN``), and that stream's seed: the same for every script that asks."""
    task = get_task(task_name)
    library = DemoLibrary.load(str(task.files.library_path))
    level = level_of(task, level_name)
    seed = level.seed + VALIDATION_SEED_OFFSET
    drawn = generate_tasks(
        library.start_states(),
        n,
        split="train",  # the training distribution; its own seed stream keeps it apart
        rho=level.rho_m,
        seed=seed,
        n_centres=level.n_centres,
        level=level_name,
        workers=workers,
    )
    # Named apart from the real training starts (main-val-0000, ...).
    starts = TaskSet(
        [dataclasses.replace(t, task_id=t.task_id.replace("-train-", "-val-")) for t in drawn],
        {**drawn.metadata, "seed_offset": VALIDATION_SEED_OFFSET},
    )
    return starts, seed


def _build_agent(key: tuple[str, str]):
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    library_path, model_path, policy = key
    return RopeWorld(), Agent(DemoLibrary.load(library_path), QModel.load(model_path), policy)


_AGENTS = PerProcess(_build_agent)


def _episode(job: tuple[str, str, str, str, RopeTask]) -> dict:
    name, library_path, model_path, policy, start = job
    world, agent = _AGENTS.get((library_path, model_path, policy))
    result = agent.run_episode(world, start)
    return {
        "model": name,
        "task_id": start.task_id,
        "success": bool(result.success),
        "steps": len(result.steps),
        "failure_kind": None if result.failure_kind is None else str(result.failure_kind),
        "error": result.error,
    }


def sign_test(wins: int, losses: int) -> float:
    """Two-sided sign test p-value of wins against losses (ties dropped)."""
    from scipy.stats import binomtest

    n = wins + losses
    return 1.0 if n == 0 else float(binomtest(wins, n, 0.5).pvalue)


def summarise(lines: list[dict], names: list, key: str = "model") -> dict:
    """Per arm (``line[key]``, a model by default): successes, Wilson interval, and paired
    wins/losses against the first arm."""
    by = {n: {ln["task_id"]: ln["success"] for ln in lines if ln[key] == n} for n in names}
    ref = by[names[0]]
    out = {}
    for n in names:
        got = by[n]
        k = sum(got.values())
        lo, hi = wilson_interval(k, len(got)) if got else (float("nan"), float("nan"))
        common = sorted(set(got) & set(ref))
        wins = sum(got[t] and not ref[t] for t in common)
        losses = sum(ref[t] and not got[t] for t in common)
        out[n] = {
            "successes": k,
            "starts": len(got),
            "rate": k / len(got) if got else float("nan"),
            "wilson": [lo, hi],
            "wins_vs_first": wins,
            "losses_vs_first": losses,
            "sign_test_p": sign_test(wins, losses),
        }
    return out


def main() -> int:
    """Generate the starts, play greedy with every model, write the summary, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="overhand", help="whose library and levels (overhand)")
    ap.add_argument("--level", default="main")
    ap.add_argument("--starts", type=int, default=200)
    ap.add_argument("--models", required=True, help="NAME=PATH,... (first: the reference)")
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--policy", default="greedy", help="what every model plays: greedy (default), la2x5, ..."
    )
    args = ap.parse_args()
    print(machine_line())
    models = parse_models(args.models)
    library_path = str(get_task(args.task).files.library_path)
    starts, seed = validation_starts(args.task, args.level, args.starts, args.workers)
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    meta_path = out / "summary.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if old.get("starts_hash") != starts.content_hash() or old.get("level") != args.level:
            raise SystemExit(f"{out}: made with other starts; use another --out-dir")
        made_with = old.get("policy", "greedy")
        if made_with != args.policy:
            raise SystemExit(f"{out}: made with {made_with}; use another --out-dir")
    outcomes = out / "outcomes.jsonl"
    lines = [json.loads(x) for x in outcomes.read_text().splitlines()] if outcomes.exists() else []
    hashes = {name: QModel.load(path).content_hash() for name, path in models.items()}
    stale = sorted(
        {
            ln["model"]
            for ln in lines
            if hashes.get(ln["model"], ln["model_hash"]) != ln["model_hash"]
        }
    )
    if stale:  # a name now given to another file: its old episodes are not this model's
        raise SystemExit(
            f"{out}: {', '.join(stale)} ran with another model file; use another --out-dir"
        )
    done = {(ln["model"], ln["task_id"]) for ln in lines}
    jobs = [
        (name, library_path, str(path), args.policy, s)
        for name, path in models.items()
        for s in starts
        if (name, s.task_id) not in done
    ]
    with outcomes.open("a", encoding="utf-8") as fh:
        for _, line in imap_processes(
            _episode, jobs, workers=args.workers, desc=f"{args.policy} on {len(starts)} starts"
        ):
            line["model_hash"] = hashes[line["model"]]
            fh.write(json.dumps(line) + "\n")
            fh.flush()
            lines.append(line)
    names = list(models)
    summary = {
        "task": args.task,
        "level": args.level,
        "policy": args.policy,
        "seed": seed,
        "starts": args.starts,
        "starts_hash": starts.content_hash(),
        "models": {n: str(p) for n, p in models.items()},
        "machine": machine_info(),
        "results": summarise(lines, names),
    }
    errored = [ln for ln in lines if ln.get("error")]
    summary["errored_episodes"] = len(errored)
    meta_path.write_text(json.dumps(summary, indent=1, sort_keys=True))
    if errored:  # a run in which episodes errored is not a result
        for ln in errored[:5]:
            print(f"errored: {ln['model']} {ln['task_id']}: {ln['error']}", file=sys.stderr)
        print(f"{len(errored)} episodes errored: no table", file=sys.stderr)
        return 1
    _plot(summary, out / "greedy_validation.png")
    print_paired_table(summary["results"], "model", args.policy)
    return 0


def play_resumable(
    outcomes: Path,
    arms: list,
    starts: TaskSet,
    key: str,
    job_of: Callable[[Any, RopeTask], tuple],
    episode: Callable[[tuple], dict],
    workers: int,
) -> list[dict]:
    """Every arm on every start, skipping (arm, start) pairs already in ``outcomes`` (a JSON
    line each, ``line[key]`` naming the arm); new lines appended as they finish. All lines."""
    lines = [json.loads(x) for x in outcomes.read_text().splitlines()] if outcomes.exists() else []
    done = {(ln[key], ln["task_id"]) for ln in lines}
    jobs = [job_of(a, s) for a in arms for s in starts if (a, s.task_id) not in done]
    desc = f"{len(arms)} {key}s, {len(starts)} starts"
    with outcomes.open("a", encoding="utf-8") as fh:
        for _, line in imap_processes(episode, jobs, workers=workers, desc=desc):
            fh.write(json.dumps(line) + "\n")
            fh.flush()
            lines.append(line)
    return lines


def play_weight_arms(
    args: argparse.Namespace,
    *,
    inputs: list[Path],
    identity: dict[str, Any],
    job_of: Callable[[float, RopeTask], tuple],
    episode: Callable[[tuple], dict],
) -> int:
    """Greedy with a score bonus at each weight (0 first: greedy as it is), on the validation
    starts or a level's test tasks, resumable; summary.json records the starts, the model and
    ``identity`` (what else decides the episodes) and refuses a folder made with others.
    ``args``: task, level, starts, test, model, lams, out_dir, workers; ``inputs``: files that
    must exist. Prints the paired table; 1 if any episode errored (no table: not a result)."""
    for path in inputs:
        if not path.exists():
            raise SystemExit(f"{path} does not exist")
    task_name, level, n_starts, test = args.task, args.level, args.starts, args.test
    model, out_dir, workers = args.model, args.out_dir, args.workers
    weights = [float(x) for x in args.lams.split(",")]
    print(machine_line())
    task = get_task(task_name)
    if test:
        starts = task.files.load_task_set(level, "test")
        starts = type(starts)(list(starts)[:n_starts], starts.metadata)
    else:
        starts, _ = validation_starts(task_name, level, n_starts, workers)
    model_hash = QModel.load(model).content_hash()
    out_dir.mkdir(parents=True, exist_ok=True)
    meta_path = out_dir / "summary.json"
    recorded = {"starts_hash": starts.content_hash(), "model_hash": model_hash, **identity}
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if any(old.get(k) != v for k, v in recorded.items()):
            names = ", ".join(k.removesuffix("_hash") for k in recorded)
            raise SystemExit(f"{out_dir}: made with other {names}; use another dir")
    lines = play_resumable(
        out_dir / "outcomes.jsonl", weights, starts, "lam", job_of, episode, workers
    )
    results = {f"{w:g}": r for w, r in summarise(lines, weights, key="lam").items()}
    errored = [ln for ln in lines if ln.get("error")]
    meta = {
        "task": task_name,
        "level": level,
        "split": "test" if test else "validation",
        "starts": len(starts),
        "model": str(model),
        **recorded,
        "machine": machine_info(),
        "errored_episodes": len(errored),
        "results": results,
    }
    meta_path.write_text(json.dumps(meta, indent=1, sort_keys=True))
    if errored:  # a run in which episodes errored is not a result
        print(f"{len(errored)} episodes errored: no table", file=sys.stderr)
        return 1
    split = "test tasks" if test else "validation starts"
    print(f"{task_name}, {level} level, {len(starts)} {split}, model {model_hash}")
    print_paired_table(results, "prior weight")
    return 0


def print_paired_table(results: dict, arm: str, policy: str = "greedy") -> None:
    """The Markdown table of ``summarise``'s results, one row an arm."""
    print(f"| {arm} | {policy} success | Wilson 95 % | vs first: wins / losses | sign test p |")
    print("|---|---|---|---|---|")
    for n, r in results.items():
        lo, hi = r["wilson"]
        print(
            f"| {n} | {r['successes']}/{r['starts']} = {100 * r['rate']:.1f} % | "
            f"[{100 * lo:.1f}, {100 * hi:.1f}] | {r['wins_vs_first']} / "
            f"{r['losses_vs_first']} | {r['sign_test_p']:.3g} |"
        )


def _plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = summary["results"]
    names = list(res)
    fig, ax = plt.subplots(figsize=(max(4, 1.3 * len(names)), 4.2))
    for i, n in enumerate(names):
        r = res[n]
        ax.bar(i, r["rate"], color=f"C{i}")
        ax.plot([i, i], r["wilson"], color="black", lw=1.5)
    ax.set_xticks(range(len(names)), names, rotation=20, ha="right")  # long names must not overlap
    ax.set_ylim(0, 1)
    ax.set_ylabel(f"{summary.get('policy', 'greedy')} success (Wilson 95 %)")
    ax.set_title(
        f"{summary.get('task', 'overhand')}, {summary['level']} level, "
        f"{summary['starts']} fresh validation starts"
    )
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    raise SystemExit(main())
