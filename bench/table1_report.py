"""Table I as markdown from committed runs: success, Wilson 95 %, times, paired comparisons.

Reads ``results/table1_<level>/outcomes.jsonl`` (every finished episode, whichever command ran
it), so partially finished runs are reported with their real counts; an errored episode is
counted and flagged, never hidden. Every pair of policies is also compared on the tasks both
ran: on how many one knots and the other does not, with an exact two-sided sign test.

Usage: .venv/bin/python bench/table1_report.py [--levels main,hard] [--first 125]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path

from scipy.stats import binomtest

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


def paired(a: list[dict], b: list[dict]) -> tuple[int, int, int, float]:
    """(tasks both ran, a-only knots, b-only knots, two-sided sign-test p) for two policies."""
    ok_a = {r["task_index"]: bool(r["success"]) for r in a}
    ok_b = {r["task_index"]: bool(r["success"]) for r in b}
    common = ok_a.keys() & ok_b.keys()
    wins = sum(ok_a[t] and not ok_b[t] for t in common)
    losses = sum(ok_b[t] and not ok_a[t] for t in common)
    p = binomtest(wins, wins + losses).pvalue if wins + losses else 1.0
    return len(common), wins, losses, float(p)


def _paired_table(runs: dict[str, list[dict]], policies: list[str]) -> None:
    print("| A vs B | tasks both ran | A knots, B not | B knots, A not | sign test p |")
    print("|---|---|---|---|---|")
    for pa, pb in itertools.combinations(policies, 2):
        n, wins, losses, p = paired(runs[pa], runs[pb])
        if n:
            print(f"| {pa} vs {pb} | {n} | {wins} | {losses} | {p:.2g} |")
    print()


def main() -> int:
    """Print per level: the table (with a first-K column), total episode time, paired tests."""
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
        policies = sorted(runs, key=lambda p: ORDER.index(p) if p in ORDER else 99)
        for policy in policies:
            recs = runs[policy]
            first = [r for r in recs if r.get("task_index", 0) < args.first]
            paper = PAPER_TABLE1.get(policy)
            decide = _mean([t for r in recs for t in r.get("decision_s", [])])
            wall = _mean([r["wall_s"] for r in recs])
            print(
                f"| {policy} | {_cell(recs)} | {_cell(first)} | "
                f"{'-' if paper is None else f'{100 * paper:.1f} %'} | {decide:.2f} | {wall:.1f} |"
            )
        hours = sum(r["wall_s"] for recs in runs.values() for r in recs) / 3600
        print(
            f"\n{hours:.1f} hours of episode time in all "
            f"(at best {hours / 2:.1f} of wall time on 2 workers).\n"
        )
        _paired_table(runs, policies)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
