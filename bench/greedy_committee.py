"""Greedy with a committee of Q-models against greedy with one, on fresh validation starts.

Each committee member ranks the state's demos with its own features (its landmarks) on the one
registration scan the agent made; the members' scores are combined per demo and greedy takes the
best. Two combinations: ``z`` (each member's Q standardised over the usable demos, then summed:
members count equally whatever their Q scale) and ``borda`` (each member's rank points, then
summed). An arm with one model is plain greedy. Starts: `bench/greedy_validation.py`'s fresh
validation stream of the level (never the test sets); every arm plays every start, so the
comparison is paired.

Outputs in --out-dir (resumable: arms' episodes already in outcomes.jsonl are not rerun):
outcomes.jsonl and summary.json (machine, arms and their model hashes, the table's numbers).

Usage: .venv/bin/python bench/greedy_committee.py [--task overhand] --level main --starts 200
       --arm ref=z:M1 --arm z5=z:M1,M2,M3 --arm borda5=borda:M1,M2,M3 --out-dir DIR
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from greedy_validation import (  # noqa: E402
    print_paired_table,
    summarise,
    validation_starts,
)

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.parallel import PerProcess, imap_processes  # noqa: E402
from knotlab.core.selection.decision import Decision, Policy, StepContext  # noqa: E402
from knotlab.core.selection.features import LibraryFeaturizer  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.ranking import demo_scores, rank_order  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402

COMBINATIONS = ("z", "borda")


@dataclass(frozen=True)
class Arm:
    """One arm: its name, how the members' scores combine and the members' model files."""

    name: str
    combine: str
    model_paths: tuple[str, ...]


def parse_arm(text: str) -> Arm:
    """NAME=COMBINE:PATH[,PATH...] -> Arm (exit naming the problem on bad input)."""
    name, sep, rest = text.partition("=")
    combine, sep2, paths = rest.partition(":")
    if not sep or not sep2 or not name or not paths:
        raise SystemExit(f"--arm: expected NAME=COMBINE:PATH[,PATH...], got {text!r}")
    if combine not in COMBINATIONS:
        raise SystemExit(f"--arm {name}: combination {combine!r} is not one of {COMBINATIONS}")
    model_paths = tuple(paths.split(","))
    for path in model_paths:
        if not Path(path).is_file():
            raise SystemExit(f"--arm {name}: {path} does not exist")
    return Arm(name, combine, model_paths)


def combine_scores(scores_ma: np.ndarray, combine: str) -> np.ndarray:
    """Members' scores (m, a; -inf = unusable) -> one score per demo (higher = better)."""
    total = np.zeros(scores_ma.shape[1])
    usable = np.all(np.isfinite(scores_ma), axis=0)
    for s in scores_ma:
        if combine == "z":
            ok = s[usable]
            total[usable] += (ok - ok.mean()) / (ok.std() + 1e-12) if ok.size else 0.0
        else:  # borda: the best usable demo gets 0, the next -1, ...
            order = rank_order(np.where(usable, s, -np.inf))
            total[order] -= np.arange(len(order), dtype=float)
    total[~usable] = -np.inf
    return total


class CommitteeGreedyPolicy(Policy):
    """argmax over demos of the members' combined scores (each member with its own features)."""

    name = "committee"

    def __init__(self, models: list[QModel], combine: str) -> None:
        self.models, self.combine = models, combine
        self._featurizers: list[LibraryFeaturizer] | None = None

    def choose(self, ctx: StepContext) -> Decision:
        """The best demo by the combined score (the members share the agent's scan)."""
        if self._featurizers is None:
            base = ctx.featurizer
            self._featurizers = [
                LibraryFeaturizer.for_model(
                    base.library, m, registrar=base.registrar, params=base.registrar.params
                )
                for m in self.models
            ]
        scores_ma = np.array(
            [
                demo_scores(ctx.scan, f.features_from_scan(ctx.scan, ctx.cloud_n3), m)
                for m, f in zip(self.models, self._featurizers, strict=True)
            ]
        )
        total = combine_scores(scores_ma, self.combine)
        order = rank_order(total)
        return Decision(int(order[0]) if len(order) else 0, total)


def _build_agent(key: tuple[str, str, str, tuple[str, ...]]):
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    task, library_path, combine, paths = key
    models = [QModel.load(p) for p in paths]
    agent = Agent(DemoLibrary.load(library_path), models[0], "greedy", task=task)
    if len(models) > 1:
        agent.policy = CommitteeGreedyPolicy(models, combine)
    return RopeWorld(), agent


_AGENTS = PerProcess(_build_agent)


def _episode(job: tuple) -> dict:
    name, task, library_path, combine, paths, start = job
    world, agent = _AGENTS.get((task, library_path, combine, paths))
    result = agent.run_episode(world, start)
    return {
        "arm": name,
        "task_id": start.task_id,
        "success": bool(result.success),
        "steps": len(result.steps),
        "error": result.error,
    }


def main() -> int:
    """Play every arm on the validation starts, write the summary, print the paired table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="overhand")
    ap.add_argument("--level", default="main")
    ap.add_argument("--starts", type=int, default=200)
    ap.add_argument("--arm", action="append", required=True, help="NAME=COMBINE:PATH[,PATH...]")
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    arms = [parse_arm(a) for a in args.arm]
    if len({a.name for a in arms}) != len(arms):
        raise SystemExit("--arm: an arm name is given twice")
    print(machine_line())
    library_path = str(get_task(args.task).files.library_path)
    starts, seed = validation_starts(args.task, args.level, args.starts, args.workers)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    outcomes = args.out_dir / "outcomes.jsonl"
    hashes = {a.name: [QModel.load(p).content_hash() for p in a.model_paths] for a in arms}
    lines = [json.loads(x) for x in outcomes.read_text().splitlines()] if outcomes.exists() else []
    stale = sorted(
        {ln["arm"] for ln in lines if hashes.get(ln["arm"], ln["hashes"]) != ln["hashes"]}
    )
    if stale:
        raise SystemExit(
            f"{args.out_dir}: {', '.join(stale)} ran with other models; use another --out-dir"
        )
    done = {(ln["arm"], ln["task_id"]) for ln in lines}
    jobs = [
        (a.name, args.task, library_path, a.combine, a.model_paths, s)
        for a in arms
        for s in starts
        if (a.name, s.task_id) not in done
    ]
    with outcomes.open("a", encoding="utf-8") as fh:
        for _, line in imap_processes(_episode, jobs, workers=args.workers, desc="committees"):
            line["hashes"] = hashes[line["arm"]]
            fh.write(json.dumps(line) + "\n")
            fh.flush()
            lines.append(line)
    names = [a.name for a in arms]
    results = summarise(lines, names, key="arm")
    errored = sum(1 for ln in lines if ln.get("error"))
    summary = {
        "task": args.task,
        "level": args.level,
        "seed": seed,
        "starts_hash": starts.content_hash(),
        "arms": {a.name: {"combine": a.combine, "models": list(a.model_paths)} for a in arms},
        "machine": machine_info(),
        "errored_episodes": errored,
        "results": results,
    }
    (args.out_dir / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True))
    if errored:  # a run in which episodes errored is not a result
        print(f"{errored} episodes errored: no table", file=sys.stderr)
        return 1
    print_paired_table(results, "arm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
