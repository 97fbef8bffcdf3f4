"""Choose the ensemble lookaheads' members and spread on training starts, never on test tasks.

The robust (``rla<D>x<W>k<K>[s<P>]``) and adaptive (``ala<D>x<W>k<K>[s<P>]``) lookaheads have two
hyper-parameters, the number of members K and their spread P. This script plays each candidate
configuration, and the plain ``la<D>x<W>`` as the baseline, on the first ``--starts`` training
starts of a level in a world unlike the agent's model (``--setting``, e.g. combined25), as one
resumable bench folder per setting (``OUT/<setting>/``: `knotlab bench --world-params`, the same
files; simulations shared between a task's policies). The rule, fixed before any run: the highest
success among the configurations whose median decision time is at most ``--max-time`` times the
plain lookahead's on the same tasks; ties go to fewer members, then to the earlier listed. It
prints the table (Wilson 95 % intervals, paired against the plain lookahead with a sign test,
decision-time ratio) and writes ``OUT/<setting>/choice.json``.

Usage:
  .venv/bin/python bench/robust_tuning.py --setting combined25 \\
      --configs ala2x5k2,ala2x5k4,ala2x5k8,rla2x5k2 --starts 60 --out-dir results/robust_tuning
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robustness import _outcomes  # noqa: E402

from knotlab.core.experiments.bench.report import wilson_interval  # noqa: E402
from knotlab.core.machine import machine_line  # noqa: E402
from knotlab.core.selection.policies import policy_config  # noqa: E402


@dataclass(frozen=True)
class ConfigScore:
    """One configuration on the training starts, against the plain lookahead."""

    policy: str
    members: int
    spread: float
    n: int
    successes: int
    wins: int  # tasks it knotted and the plain lookahead did not
    losses: int
    median_decision_s: float
    time_ratio: float  # its median decision time over the plain lookahead's

    @property
    def rate(self) -> float:
        """Success rate."""
        return self.successes / self.n if self.n else 0.0


def baseline_of(policy: str) -> str:
    """The plain lookahead an ensemble configuration extends (ala2x5k4s50 -> la2x5)."""
    match = re.fullmatch(r"[ra]la(\d+)x(\d+)k.*", policy)
    if match is None:
        raise SystemExit(f"{policy}: not a robust (rla..) or adaptive (ala..) lookahead")
    return f"la{match[1]}x{match[2]}"


def score(policy: str, recs: dict[str, dict], base: dict[str, dict]) -> ConfigScore:
    """A configuration's success, paired wins and losses and time ratio on the common tasks."""
    config = policy_config(policy)
    common = sorted(set(recs) & set(base))
    wins = sum(recs[t]["success"] and not base[t]["success"] for t in common)
    losses = sum(base[t]["success"] and not recs[t]["success"] for t in common)

    def median_time(records: dict[str, dict]) -> float:
        times = [d for t in common for d in records[t].get("decision_s", [])]
        return statistics.median(times) if times else float("nan")

    mine, plain = median_time(recs), median_time(base)
    return ConfigScore(
        policy,
        config.members,
        config.spread,
        len(common),
        sum(bool(recs[t]["success"]) for t in common),
        wins,
        losses,
        mine,
        mine / plain if plain > 0 else float("inf"),
    )


def choose(scores: list[ConfigScore], max_time: float) -> ConfigScore | None:
    """The rule: highest success within the time budget; ties to fewer members, then order."""
    allowed = [s for s in scores if s.time_ratio <= max_time]
    if not allowed:
        return None
    best = max(s.successes for s in allowed)
    tied = [s for s in allowed if s.successes == best]
    return min(tied, key=lambda s: (s.members, scores.index(s)))


def report(folder: Path, configs: list[str], max_time: float) -> ConfigScore | None:
    """Print the table for one setting's folder and write its choice.json."""
    from scipy.stats import binomtest

    outcomes = _outcomes(folder / "outcomes.jsonl")
    scores = []
    for policy in configs:
        base = outcomes.get(baseline_of(policy), {})
        if policy in outcomes and base:
            scores.append(score(policy, outcomes[policy], base))
    print(f"\n{folder.name}: ensemble configurations on training starts (paired with la)\n")
    print("| policy | K | spread | n | success | Wilson 95 % | wins / losses | p | time x plain |")
    print("|---|---:|---:|---:|---:|---|---|---:|---:|")
    for s in scores:
        lo, hi = wilson_interval(s.successes, s.n)
        p = binomtest(s.wins, s.wins + s.losses).pvalue if s.wins + s.losses else 1.0
        print(
            f"| {s.policy} | {s.members} | {100 * s.spread:.0f} % | {s.n} | "
            f"{s.successes}/{s.n} = {100 * s.rate:.1f} % | [{100 * lo:.1f}, {100 * hi:.1f}] | "
            f"{s.wins} / {s.losses} | {p:.3g} | {s.time_ratio:.2f} |"
        )
    chosen = choose(scores, max_time)
    if chosen is None:
        print(f"\nno configuration within {max_time:g}x the plain lookahead's decision time")
    else:
        print(f"\nchosen: {chosen.policy} (rule: best success within {max_time:g}x the time)")
    (folder / "choice.json").write_text(
        json.dumps(
            {
                "chosen": None if chosen is None else chosen.policy,
                "max_time": max_time,
                "scores": [asdict(s) for s in scores],
            },
            indent=1,
        )
        + "\n"
    )
    return chosen


def main() -> int:
    """Play every configuration and the plain lookahead on the training starts; choose."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--setting", default="combined25", help="the world (a mismatch setting)")
    ap.add_argument("--configs", default="ala2x5k2,ala2x5k4,ala2x5k8,rla2x5k2")
    ap.add_argument("--starts", type=int, default=60, help="the first N training starts")
    ap.add_argument("--level", default="main")
    ap.add_argument("--task", default="overhand")
    ap.add_argument("--max-time", type=float, default=2.0, help="x the plain lookahead's time")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--report", action="store_true", help="play nothing: report what ran")
    ap.add_argument("--out-dir", type=Path, required=True)
    args = ap.parse_args()
    configs = [c for c in args.configs.split(",") if c]
    for c in configs:
        if policy_config(c).kind not in ("robust", "adaptive"):
            raise SystemExit(f"{c}: not a robust (rla..) or adaptive (ala..) lookahead")
    folder = args.out_dir / args.setting
    print(machine_line())
    if not args.report:
        from knotlab.core.demos.library import DemoLibrary
        from knotlab.core.demos.tasks import TaskSet
        from knotlab.core.experiments.bench import run_bench
        from knotlab.core.selection.qmodel import QModel
        from knotlab.core.tasks import get_task
        from knotlab.core.world.mismatch import parse_setting

        spec = get_task(args.task)
        plain = sorted({baseline_of(c) for c in configs})
        run_bench(
            folder,
            library=DemoLibrary.load(spec.files.library_path),
            task_set=TaskSet.load(spec.files.task_set_path(args.level, "train")),
            policies=[*plain, *configs],
            n_tasks=args.starts,
            model=QModel.load(spec.files.model_path),
            seed=args.seed,
            workers=args.workers,
            arguments={"study": "robust_tuning", "setting": args.setting, "argv": sys.argv},
            share_simulations=True,
            training_study=True,
            world=parse_setting(args.setting, seed=args.seed),
        )
    return 0 if report(folder, configs, args.max_time) is not None else 1


if __name__ == "__main__":
    raise SystemExit(main())
