"""Episodes and busy time per worker node (Ray) or process (local) of a bench results file.

Usage: .venv/bin/python bench/node_throughput.py OUTCOMES.jsonl [--json]
A bench run on a Ray cluster records the node of every episode; this prints, per node and
policy, the episodes it ran, their summed wall time, and episodes per busy hour, so a
cluster's throughput can be checked node by node.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path


def per_node(rows: list[dict]) -> dict[str, dict[str, list[float]]]:
    """node (or pid) -> policy -> episode wall times."""
    out: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        node = str(r.get("node") or f"pid {r.get('pid', '?')}")
        out[node][r["policy"]].append(float(r.get("wall_s", 0.0)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("outcomes", type=Path)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    try:
        rows = [json.loads(line) for line in args.outcomes.read_text().splitlines() if line]
    except (OSError, json.JSONDecodeError) as exc:
        raise SystemExit(f"node_throughput: cannot read {args.outcomes}: {exc}") from exc
    table = per_node(rows)
    print("| node | policy | episodes | busy s | episodes per busy hour |")
    print("|---|---|---|---|---|")
    summary = {}
    for node, policies in sorted(table.items()):
        for policy, walls in sorted(policies.items()):
            busy = sum(walls)
            rate = 3600 * len(walls) / busy if busy else float("nan")
            print(f"| {node[:12]} | {policy} | {len(walls)} | {busy:.0f} | {rate:.0f} |")
            summary[f"{node}/{policy}"] = {"episodes": len(walls), "busy_s": busy}
    if args.json:
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
