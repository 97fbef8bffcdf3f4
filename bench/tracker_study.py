"""How well each rope tracker follows the rope, on training starts (never on test tasks).

Plays ``--policies`` (default NN and greedy) on the first ``--starts`` training starts of a level
with every ``--estimators`` (perfect, tracker: one camera frame after each step, video: the
camera followed at 30 frames a second through each motion), one resumable bench folder each
(``OUT/<estimator>/``, simulations shared between a task's policies), and prints per estimator and
policy the success rate (Wilson 95 %, paired against the perfect estimate with a sign test) and
the tracker's mean node and shape errors (mm) at each decision. This is where a tracker's
settings are chosen; the test-set study is `bench/robustness.py` (settings ``tracker``,
``video``).

Usage:
  .venv/bin/python bench/tracker_study.py --starts 40 --out-dir results/tracker_study
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from collections.abc import Iterable  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robustness import _outcomes  # noqa: E402

from knotlab.core.experiments.bench.report import wilson_interval  # noqa: E402
from knotlab.core.experiments.robustness import paired_row  # noqa: E402
from knotlab.core.machine import machine_line  # noqa: E402


def run(args: argparse.Namespace, estimators: list[str], policies: list[str]) -> None:
    """Play (or resume) every estimator's folder."""
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.demos.tasks import TaskSet
    from knotlab.core.experiments.bench import run_bench
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.tasks import get_task
    from knotlab.core.world.estimate import EstimatorKind

    spec = get_task(args.task)
    for name in estimators:
        print(f"== {name}: {', '.join(policies)} on {args.starts} training starts")
        run_bench(
            args.out_dir / name,
            library=DemoLibrary.load(spec.files.library_path),
            task_set=TaskSet.load(spec.files.task_set_path(args.level, "train")),
            policies=policies,
            n_tasks=args.starts,
            model=QModel.load(spec.files.model_path),
            seed=args.seed,
            workers=args.workers,
            arguments={"study": "tracker_study", "estimator": name, "argv": sys.argv},
            share_simulations=True,
            training_study=True,
            estimator=EstimatorKind.parse(name),
            progress=not args.no_progress,
        )


def report(out_dir: Path, estimators: list[str], policies: list[str]) -> None:
    """Print success and per-decision error for every estimator and policy."""
    base = _outcomes(out_dir / "perfect" / "outcomes.jsonl")
    print(
        "\n| estimator | policy | n | success | 95 % Wilson | perfect | lost | gained | p "
        "| errored | node error (mm) at decision 1 / 2 / 3 / 4 / 5 | shape error (mm), same "
        "| the rope's crossings (% of estimates), same |"
    )
    print("|---|---|---:|---:|---|---:|---:|---:|---:|---:|---|---|---|")
    for name in estimators:
        rows = _outcomes(out_dir / name / "outcomes.jsonl")
        for policy in policies:
            mine = rows.get(policy, {})
            if not mine:
                continue
            row = paired_row(name, policy, list(mine.values()), base.get(policy, {}))
            lo, hi = wilson_interval(sum(bool(r["success"]) for r in mine.values()), len(mine))
            errors = _per_decision(mine.values(), "estimate_error_mm")
            shapes = _per_decision(mine.values(), "estimate_shape_mm")
            crossings = _per_decision(mine.values(), "estimate_crossings_right", percent=True)
            rate = 100 * sum(bool(r["success"]) for r in mine.values()) / len(mine)
            print(
                f"| {name} | {policy} | {len(mine)} | {rate:.1f} % | [{100 * lo:.1f}, "
                f"{100 * hi:.1f}] | {100 * row.matched_rate:.1f} % | {row.lost} | {row.gained} | "
                f"{row.p_value:.3g} | {row.errored} | {errors} | {shapes} | {crossings} |"
            )


def _per_decision(records: Iterable[dict], key: str, percent: bool = False) -> str:
    """The mean of a per-step list over the episodes, at each of the first five decisions
    (``percent``: a list of booleans, as the share true)."""
    per_step: list[list[float]] = [[] for _ in range(5)]
    for r in records:
        for i, e in enumerate(r.get(key, [])[:5]):
            per_step[i].append(float(e))
    scale, fmt = (100.0, ".0f") if percent else (1.0, ".1f")
    return " / ".join(f"{scale * statistics.fmean(e):{fmt}}" if e else "-" for e in per_step)


def main() -> int:
    """Run (unless --report) and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out-dir", type=Path, default=ROOT / "results" / "tracker_study")
    ap.add_argument("--estimators", default="perfect,tracker,video")
    ap.add_argument("--policies", default="nn,greedy")
    ap.add_argument("--starts", type=int, default=40, help="the first N training starts")
    ap.add_argument("--task", default="overhand")
    ap.add_argument("--level", default="main")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--report", action="store_true", help="only print the table")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args()
    estimators = [e for e in args.estimators.split(",") if e]
    policies = [p for p in args.policies.split(",") if p]
    print(machine_line())
    if not args.report:
        run(args, estimators, policies)
    report(args.out_dir, estimators, policies)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
