"""Table I as markdown from committed runs: success, Wilson 95 %, times, paired comparisons.

Reads ``results/table1_<level>/outcomes.jsonl`` (every finished episode, whichever command ran
it), so partially finished runs are reported with their real counts; an errored episode is
counted and flagged, never hidden. Every pair of policies is also compared on the tasks both
ran: on how many one knots and the other does not, with an exact two-sided sign test.

With ``--run table1_shared`` it reads ``results/table1_shared_<level>/`` instead, adds the wall
time of the resumed segments in its ``segments.log`` (scripts/table1_shared.sh), and with
``--against table1`` compares it task by task with the committed run.

Usage: .venv/bin/python bench/table1_report.py [--levels main,hard] [--first 125]
       [--run table1_shared] [--against table1]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from scipy.stats import binomtest

from knotlab.core.experiments.bench import wilson_interval

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


@dataclass(frozen=True)
class Segment:
    """One resumed stretch of a run, from segments.log (seconds None: never stopped cleanly)."""

    start: str
    cpu: str
    workers: int
    commit: str
    seconds: int | None


_START = re.compile(r"^start (\S+) cpu='([^']*)' workers=(\d+) commit=(\S+)")
_STOP = re.compile(r"^(?:stop|end) +\S+ seconds=(\d+)")


def read_segments(text: str) -> list[Segment]:
    """The segments of a segments.log: each start line with the seconds of the stop/end after it."""
    segments: list[Segment] = []
    for line in text.splitlines():
        if start := _START.match(line):
            segments.append(Segment(*start.group(1, 2), int(start.group(3)), start.group(4), None))
        elif (stop := _STOP.match(line)) and segments and segments[-1].seconds is None:
            last = segments[-1]
            segments[-1] = Segment(
                last.start, last.cpu, last.workers, last.commit, int(stop.group(1))
            )
    return segments


def _segments_summary(path: Path) -> float | None:
    """Print the run's segments and return their summed seconds (None without a log)."""
    if not path.exists():
        return None
    segments = read_segments(path.read_text())
    total = sum(s.seconds or 0 for s in segments)
    cpus = sorted({(s.cpu, s.workers) for s in segments})
    open_ = sum(s.seconds is None for s in segments)
    print(
        f"Wall time: {len(segments)} segments, {total:,} s = {total / 3600:.2f} h "
        f"({', '.join(f'{c}, {w} workers' for c, w in cpus)})"
        + (f"; {open_} segment(s) without a stop line, not counted" if open_ else "")
        + ("; **segments from different machines do not add up**" if len(cpus) > 1 else "")
        + "\n"
    )
    return float(total)


def agreement(a: list[dict], b: list[dict]) -> tuple[int, int, int, int, int]:
    """(tasks both ran, same success, same choices at every step, knots in a, knots in b) on
    those tasks, for one policy in two runs."""
    by_task = {r["task_index"]: r for r in b}
    pairs = [(r, by_task[r["task_index"]]) for r in a if r["task_index"] in by_task]
    same_success = sum(bool(x["success"]) == bool(y["success"]) for x, y in pairs)
    same_chosen = sum(x.get("chosen") == y.get("chosen") for x, y in pairs)
    knots_a = sum(bool(x["success"]) for x, _ in pairs)
    knots_b = sum(bool(y["success"]) for _, y in pairs)
    return len(pairs), same_success, same_chosen, knots_a, knots_b


def _agreement_table(runs: dict[str, list[dict]], other: dict[str, list[dict]], name: str) -> None:
    print(f"Against `results/{name}_*` (the same tasks):\n")
    print("| policy | tasks both ran | same success | same demo every step | knots here / there |")
    print("|---|---|---|---|---|")
    for policy, recs in runs.items():
        if policy not in other:
            continue
        n, same, chosen, here, there = agreement(recs, other[policy])
        print(f"| {policy} | {n} | {same} | {chosen} | {here} / {there} |")
    print()


def _paired_table(runs: dict[str, list[dict]], policies: list[str]) -> None:
    print("| A vs B | tasks both ran | A knots, B not | B knots, A not | sign test p |")
    print("|---|---|---|---|---|")
    for pa, pb in itertools.combinations(policies, 2):
        n, wins, losses, p = paired(runs[pa], runs[pb])
        if n:
            print(f"| {pa} vs {pb} | {n} | {wins} | {losses} | {p:.2g} |")
    print()


def _reference_rates(out: Path) -> dict[str, float]:
    """The published rates of the run's task (the paper's Table I for the overhand knot; none
    for another task, whose runs record their task)."""
    from knotlab.core.tasks import DEFAULT_TASK, get_task

    results = out / "results.json"
    task = json.loads(results.read_text()).get("task") if results.exists() else None
    return dict(get_task(task or DEFAULT_TASK).reference_rates)


def main() -> int:
    """Print per level: the table (with a first-K column), total episode time, paired tests."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", default="main,hard")
    ap.add_argument("--first", type=int, default=125, help="also report the first K tasks")
    ap.add_argument("--run", default="table1", help="results/<RUN>_<level>/ (default table1)")
    ap.add_argument("--against", default=None, help="compare task by task with results/<RUN>_*")
    args = ap.parse_args()
    total_s = 0.0
    for level in args.levels.split(","):
        out = ROOT / "results" / f"{args.run}_{level}"
        runs = _rows(out / "outcomes.jsonl")
        if not runs:
            print(f"## {level}: no runs yet\n")
            continue
        print(f"## {level} level (test set, results/{args.run}_{level})\n")
        total_s += _segments_summary(out / "segments.log") or 0.0
        print(
            f"| policy | all tasks run | first {args.first} tasks | paper | decision s/step "
            "| mean episode s |"
        )
        print("|---|---|---|---|---|---|")
        policies = sorted(runs, key=lambda p: ORDER.index(p) if p in ORDER else 99)
        reference = _reference_rates(out)
        for policy in policies:
            recs = runs[policy]
            first = [r for r in recs if r.get("task_index", 0) < args.first]
            paper = reference.get(policy)
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
        if args.against:
            other = _rows(ROOT / "results" / f"{args.against}_{level}" / "outcomes.jsonl")
            _agreement_table({p: runs[p] for p in policies}, other, args.against)
    if total_s:
        print(f"Segments of all levels: {total_s:,.0f} s = {total_s / 3600:.2f} h of wall time.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
