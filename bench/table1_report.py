"""Table I as markdown from committed runs: success, Wilson 95 %, decision and episode times.

Reads ``results/table1_<level>/outcomes.jsonl`` (every finished episode, whichever command ran
it), so partially finished runs are reported with their real counts; an errored episode is
counted and flagged, never hidden.

Usage: .venv/bin/python bench/table1_report.py [--levels main,hard] [--first 125]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from knotlab.core.experiments.bench import PAPER_TABLE1, wilson_interval

ROOT = Path(__file__).resolve().parents[1]
ORDER = ("nn", "greedy", "la1x10", "la2x5", "oracle")


def _rows(path: Path) -> dict[str, list[dict]]:
    by_policy: dict[str, list[dict]] = {}
    if not path.exists():
        return by_policy
    for line in path.read_text().splitlines():
        if line.strip():
            rec = json.loads(line)
            by_policy.setdefault(rec["policy"], []).append(rec)
    for recs in by_policy.values():
        recs.sort(key=lambda r: r.get("task_index", 0))
    return by_policy


def _cell(recs: list[dict]) -> str:
    if not recs:
        return "-"
    k, n = sum(r["success"] for r in recs), len(recs)
    lo, hi = wilson_interval(k, n)
    err = sum(r["failure_kind"] == "error" for r in recs)
    flag = f" ({err} errored)" if err else ""
    return f"{k}/{n} = {100 * k / n:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}]{flag}"


def _mean(values: list[float]) -> float:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return sum(vals) / len(vals) if vals else math.nan


def main() -> int:
    """Print one markdown table per level plus a first-K column for paired comparison."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", default="main,hard")
    ap.add_argument("--first", type=int, default=125, help="also report the first K tasks")
    args = ap.parse_args()
    for level in args.levels.split(","):
        runs = _rows(ROOT / "results" / f"table1_{level}" / "outcomes.jsonl")
        if not runs:
            print(f"## {level}: no runs yet\n")
            continue
        print(f"## {level} level (test set)\n")
        print(
            f"| policy | all tasks run | first {args.first} tasks | paper | decision s/step "
            "| mean episode s |"
        )
        print("|---|---|---|---|---|---|")
        for policy in sorted(runs, key=lambda p: ORDER.index(p) if p in ORDER else 99):
            recs = runs[policy]
            first = [r for r in recs if r.get("task_index", 0) < args.first]
            paper = PAPER_TABLE1.get(policy)
            decide = _mean([t for r in recs for t in r.get("decision_s", [])])
            wall = _mean([r["wall_s"] for r in recs])
            print(
                f"| {policy} | {_cell(recs)} | {_cell(first)} | "
                f"{'-' if paper is None else f'{100 * paper:.1f} %'} | {decide:.2f} | {wall:.1f} |"
            )
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
