"""Greedy with an empirical per-demo prior from the tried candidates: does a direct estimate of
"which demos transfer" help where the learned demo one-hots do not?

The tried candidates of the training labels (``knotlab labels tries``: the 5 cheapest demos of
every labelled state, each simulated once) say how often each demo advanced the rope's stage. A
model's demo one-hots can express any per-demo offset, but the max-margin fit learns them from
which demo the oracle *labelled* (the cheapest that works), not from how often each one works.
This script adds ``lam * logit(rate_a)`` to greedy's Q, with ``rate_a`` the demo's smoothed advance
rate over the tries files given ((advanced + 1) / (tried + 2); demos never tried: the pooled
rate), and plays each ``lam`` on the fresh validation starts of `bench/greedy_validation.py`
(never the test sets; choose ``lam`` there), or on a level's test tasks with ``--test`` once it
is chosen. Paired against the first arm (``lam`` 0 is greedy as shipped).
Outputs in --out-dir (resumable; starts hash-checked): outcomes.jsonl, summary.json.

Usage: .venv/bin/python bench/demo_prior.py --task figure8 --level main --starts 200
       --model results/figure8/level_models/model_both.npz
       --tries results/figure8/tries_main.jsonl,results/figure8/tries_hard.jsonl
       --lams 0,1,2 --out-dir DIR [--test]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from greedy_validation import play_weight_arms  # noqa: E402

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import RopeTask  # noqa: E402
from knotlab.core.parallel import PerProcess  # noqa: E402
from knotlab.core.selection.decision import Decision, Policy, StepContext  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.ranking import rank_order  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402


def advance_rates(tries_lines: list[dict], keys: list[str]) -> np.ndarray:
    """Every demo's smoothed advance rate over the tried candidates, in library order."""
    tried = dict.fromkeys(keys, 0)
    advanced = dict.fromkeys(keys, 0)
    for line in tries_lines:
        for t in line["tried"]:
            if t["demo"] in tried:
                tried[t["demo"]] += 1
                advanced[t["demo"]] += int(t["knot"] or t["stage"] > line["stage_before"])
    pooled = (sum(advanced.values()) + 1) / (sum(tried.values()) + 2)
    return np.array(
        [(advanced[k] + 1) / (tried[k] + 2) if tried[k] else pooled for k in keys], dtype=float
    )


class PriorPolicy(Policy):
    """Greedy on Q(s, a) + lam * logit(rate_a)."""

    def __init__(self, inner: Policy, rate_a: np.ndarray, lam: float) -> None:
        self.inner, self.lam = inner, lam
        self.bonus_a = lam * np.log(rate_a / (1.0 - rate_a))
        self.name = f"{inner.name}+prior{lam:g}"

    def choose(self, ctx: StepContext) -> Decision:
        """The best demo by the shifted score (the inner scores keep -inf where not usable)."""
        decision = self.inner.choose(ctx)
        scores = np.asarray(decision.scores_a, dtype=float) + self.bonus_a
        return Decision(int(rank_order(scores)[0]), scores)


def _build(key: tuple[str, str, str, str, float]):
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    task_name, library_path, model_path, tries, lam = key
    library = DemoLibrary.load(library_path)
    agent = Agent(library, QModel.load(model_path), "greedy", task=task_name)
    if lam:
        lines = [json.loads(x) for p in tries.split(",") for x in Path(p).read_text().splitlines()]
        agent.policy = PriorPolicy(agent.policy, advance_rates(lines, list(library.keys)), lam)
    return RopeWorld(), agent


_AGENTS = PerProcess(_build)


def _episode(job: tuple[str, str, str, str, float, RopeTask]) -> dict:
    task_name, library_path, model_path, tries, lam, start = job
    world, agent = _AGENTS.get((task_name, library_path, model_path, tries, lam))
    result = agent.run_episode(world, start)
    return {
        "lam": lam,
        "task_id": start.task_id,
        "success": bool(result.success),
        "error": result.error,
        "chosen": [s.chosen_key for s in result.steps],
        "stages": [int(s.stage) for s in result.steps],
    }


def main() -> int:
    """Play every lam on the validation starts (or the test tasks), print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="overhand")
    ap.add_argument("--level", default="main")
    ap.add_argument("--starts", type=int, default=200)
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--tries", required=True, help="tries files, comma-separated")
    ap.add_argument("--lams", default="0,1,2", help="prior weights; the first is the reference")
    ap.add_argument("--test", action="store_true", help="the level's test tasks, not validation")
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    library_path = str(get_task(args.task).files.library_path)
    return play_weight_arms(
        args,
        inputs=[args.model, *map(Path, args.tries.split(","))],
        identity={"tries": args.tries},
        job_of=lambda a, s: (args.task, library_path, str(args.model), args.tries, a, s),
        episode=_episode,
    )


if __name__ == "__main__":
    sys.exit(main())
