"""What knowing the rope's stage would buy greedy: a diagnostic, not a policy to ship.

Greedy's failed episodes stall where it applies a demo of the *next* step to a rope whose last
step did not advance (e.g. at the figure-eight's stage 2 a step-3 demo, which never advances
there). The features see the rope only through registration costs, which do not tell a rope
before a step from the same rope after a failed try of it. This script plays, on the fresh
validation starts of `bench/greedy_validation.py` (same seed stream, never the test sets), each
arm paired on the same starts and simulator:

- ``greedy`` / ``nn``: the policy as shipped;
- ``greedy+stage`` / ``nn+stage``: the same scores, but only demos recorded at the step whose
  number is the rope's current stage (the task's stage read from the *true* rope, which no
  policy is given) are allowed, whenever one of them registered;
- ``greedy+behind`` / ``nn+behind``: past stage 0, no demo of a later step than the stage (the
  choices that never advanced in greedy's episodes); at stage 0 every demo.

The gap between an arm and its ``+stage`` twin is an upper bound on what a topology-aware feature
(the rope's crossings against each demo's) could buy that policy. Prints success, Wilson 95 %,
paired wins / losses against the first arm, and per arm the table of (stage before, demo step)
-> how often the step advanced. Outputs in --out-dir (resumable; starts hash-checked):
outcomes.jsonl, summary.json.

Usage: .venv/bin/python bench/stage_mask.py [--task figure8] --level main --starts 200
       --model results/figure8/level_models/model_both.npz --out-dir DIR
       [--arms greedy,greedy+stage,nn,nn+stage]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import collections  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from greedy_validation import (  # noqa: E402
    play_resumable,
    print_paired_table,
    summarise,
    validation_starts,
)

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import RopeTask  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.parallel import PerProcess  # noqa: E402
from knotlab.core.selection.decision import Decision, Policy, StepContext  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.ranking import rank_order  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402
from knotlab.core.tasks.base import Task  # noqa: E402

ARMS = ("greedy", "greedy+stage", "greedy+behind", "nn", "nn+stage", "nn+behind")


class StageMaskedPolicy(Policy):
    """``inner``'s scores, restricted to the demos of the step the true rope's stage names
    (``behind``: past stage 0, only demos of that step or earlier ones)."""

    def __init__(
        self, inner: Policy, task: Task, steps_a: np.ndarray, *, behind: bool = False
    ) -> None:
        self.inner, self.task, self.steps_a, self.behind = inner, task, steps_a, behind
        self.name = f"{inner.name}+{'behind' if behind else 'stage'}"

    def choose(self, ctx: StepContext) -> Decision:
        """The best allowed demo; the inner choice when no demo of that step registered."""
        decision = self.inner.choose(ctx)
        stage = self.task.stage(ctx.world.rope_nodes()).stage
        scores = np.array(decision.scores_a, dtype=float)
        allowed = (self.steps_a <= stage) | (stage == 0) if self.behind else self.steps_a == stage
        allowed &= np.isfinite(scores)
        if not allowed.any():
            return decision
        scores[~allowed] = -np.inf
        return Decision(int(rank_order(scores)[0]), scores, {"stage": stage})


def _build(key: tuple[str, str, str, str]):
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    task_name, library_path, model_path, arm = key
    library = DemoLibrary.load(library_path)
    policy = arm.split("+")[0]
    agent = Agent(library, QModel.load(model_path), policy, task=task_name)
    if "+" in arm:
        agent.policy = StageMaskedPolicy(
            agent.policy, agent.task, library.step_indices(), behind=arm.endswith("+behind")
        )
    return RopeWorld(), agent


_AGENTS = PerProcess(_build)


def _episode(job: tuple[str, str, str, str, RopeTask]) -> dict:
    task_name, library_path, model_path, arm, start = job
    world, agent = _AGENTS.get((task_name, library_path, model_path, arm))
    result = agent.run_episode(world, start)
    steps = agent.library.step_indices()
    before = [agent.task.stage(s.nodes_before_k3).stage for s in result.steps]
    return {
        "arm": arm,
        "task_id": start.task_id,
        "success": bool(result.success),
        "error": result.error,
        "transitions": [
            [b, int(steps[s.chosen]), int(s.stage)]
            for b, s in zip(before, result.steps, strict=True)
        ],
    }


def transition_table(lines: list[dict]) -> dict[tuple[int, int], tuple[int, int]]:
    """(stage before, demo step) -> (steps taken, steps that advanced the stage)."""
    out: dict[tuple[int, int], list[int]] = collections.defaultdict(lambda: [0, 0])
    for ln in lines:
        for before, step, after in ln["transitions"]:
            cell = out[(before, step)]
            cell[0] += 1
            cell[1] += int(after > before)
    return {k: (v[0], v[1]) for k, v in sorted(out.items())}


def main() -> int:
    """Play every arm on the validation starts, write the summary, print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="overhand")
    ap.add_argument("--level", default="main")
    ap.add_argument("--starts", type=int, default=200)
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--arms", default="greedy,greedy+stage", help=f"from {','.join(ARMS)}")
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    print(machine_line())
    arms = args.arms.split(",")
    unknown = [a for a in arms if a not in ARMS]
    if unknown:
        raise SystemExit(f"--arms: unknown {', '.join(unknown)}; expected from {', '.join(ARMS)}")
    if not args.model.exists():
        raise SystemExit(f"--model: {args.model} does not exist")
    library_path = str(get_task(args.task).files.library_path)
    starts, seed = validation_starts(args.task, args.level, args.starts, args.workers)
    model_hash = QModel.load(args.model).content_hash()
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    meta_path = out / "summary.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if (old.get("starts_hash"), old.get("model_hash")) != (starts.content_hash(), model_hash):
            raise SystemExit(f"{out}: made with other starts or another model; use another dir")
    lines = play_resumable(
        out / "outcomes.jsonl",
        arms,
        starts,
        "arm",
        lambda a, s: (args.task, library_path, str(args.model), a, s),
        _episode,
        args.workers,
    )
    results = summarise(lines, arms, key="arm")
    for a in arms:
        results[a]["transitions"] = [
            [b, st, n, adv]
            for (b, st), (n, adv) in transition_table(
                [ln for ln in lines if ln["arm"] == a]
            ).items()
        ]
    errored = [ln for ln in lines if ln.get("error")]
    meta_path.write_text(
        json.dumps(
            {
                "task": args.task,
                "level": args.level,
                "seed": seed,
                "starts": args.starts,
                "starts_hash": starts.content_hash(),
                "model": str(args.model),
                "model_hash": model_hash,
                "machine": machine_info(),
                "errored_episodes": len(errored),
                "results": results,
            },
            indent=1,
            sort_keys=True,
        )
    )
    if errored:  # a run in which episodes errored is not a result
        print(f"{len(errored)} episodes errored: no table", file=sys.stderr)
        return 1
    print(f"{args.task}, {args.level} level, {len(starts)} validation starts, model {model_hash}")
    print_paired_table(results, "arm")
    for a, r in results.items():
        cells = ", ".join(f"({b},{st}) {adv}/{n}" for b, st, n, adv in r["transitions"])
        print(f"{a}: (stage before, demo step) advanced/taken: {cells}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
