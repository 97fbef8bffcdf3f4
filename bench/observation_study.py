"""Observation-model study: NN and the simulation oracle on training starts, per observation model.

For each observation model (`core.world.observation`: centreline, cloud, tracked) a demo library is
generated with that model (same seed, so the same demos and start ropes; only the clouds differ)
and NN and the oracle run on the first training starts of the main level. Training starts only:
this study chooses the default, so it must never see the test set. Resumable (each model's
outcomes live in OUT/<model>/); prints a table with Wilson intervals and, per step, how often the
chosen transfer advanced the knot.

Usage: .venv/bin/python bench/observation_study.py [--starts 100] [--oracle-starts 100]
       [--models centreline,cloud,tracked] [--out runs/observation_study] [--workers 2]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

from knotlab.app import defaults  # noqa: E402
from knotlab.core.demos.generation import GenSettings, generate_library  # noqa: E402
from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import TaskSet  # noqa: E402
from knotlab.core.experiments.bench import run_bench, wilson_interval  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.world.observation import ObservationModel  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _library(model: ObservationModel, out: Path, workers: int) -> DemoLibrary:
    """The default library's demos observed with ``model`` (generated once, then reused)."""
    path = out / f"demos_{model.value}.npz"
    if path.exists():
        return DemoLibrary.load(path)
    report = generate_library(50, GenSettings(seed=0, observation=model), workers=workers)
    report.library.save(path)
    return report.library


def _step_rates(records: list[dict]) -> list[str]:
    """Per step i: advanced / reached, where advanced means the stage went up (or a knot)."""
    reached, advanced = Counter(), Counter()
    for r in records:
        prev = 0
        for i, (stage, outcome) in enumerate(zip(r["stages"], r["outcomes"], strict=True)):
            reached[i] += 1
            advanced[i] += int(outcome == "knot" or stage > prev)
            prev = stage
    return [f"{advanced[i]}/{reached[i]}" for i in range(3)]


def main() -> int:
    """Run the study and print its table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=100, help="training starts for NN (100)")
    ap.add_argument("--oracle-starts", type=int, default=100, help="of those, for the oracle")
    ap.add_argument("--models", default="centreline,cloud,tracked")
    ap.add_argument("--out", default=str(ROOT / "runs" / "observation_study"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true", help="also print the rows as JSON")
    args = ap.parse_args()
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tasks = TaskSet.load(defaults.task_set_path("main", "train"))
    policies = ["nn", "oracle"] if args.oracle_starts > 0 else ["nn"]
    rows = []
    for name in args.models.split(","):
        model = ObservationModel.parse(name.strip())
        library = _library(model, out, args.workers)
        res = run_bench(
            out / model.value,
            library=library,
            task_set=tasks,
            policies=policies,
            n_tasks=args.starts,
            first=args.oracle_starts if args.oracle_starts > 0 else None,
            workers=args.workers,
            training_study=True,
            arguments=vars(args),
        )
        for p in policies:
            recs = res.outcomes[p]
            k, n = sum(r["success"] for r in recs), len(recs)
            lo, hi = wilson_interval(k, n)
            errored = sum(r["failure_kind"] == "error" for r in recs)
            rows.append(
                {
                    "observation": model.value,
                    "policy": p,
                    "success": k,
                    "n": n,
                    "wilson": [round(lo, 3), round(hi, 3)],
                    "steps_advanced": _step_rates(recs),
                    "errored": errored,
                    "library_hash": library.content_hash(),
                }
            )
    m = machine_info()
    print(
        f"# observation-model study, main training starts; {m.get('cpu_model')}, "
        f"{args.workers} workers"
    )
    print(
        "| observation | policy | success | Wilson 95 % | step 1 adv. | step 2 adv. | step 3 adv. |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        lo, hi = r["wilson"]
        s1, s2, s3 = r["steps_advanced"]
        print(
            f"| {r['observation']} | {r['policy']} | {r['success']}/{r['n']} = "
            f"{r['success'] / r['n']:.0%} | [{lo:.0%}, {hi:.0%}] | {s1} | {s2} | {s3} |"
        )
    if any(r["errored"] for r in rows):
        print("episodes errored: " + json.dumps({r["observation"]: r["errored"] for r in rows}))
        return 1
    if args.json:
        print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
