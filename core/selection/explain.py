"""Why a policy chose a demo: Q split into per-feature contributions, and the three policies'
choices for one state side by side (nearest neighbour, greedy Q, lookahead beam search).
Shape suffixes: a = demos, d = features.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from knotlab.core.selection.qmodel import QModel
from knotlab.core.tasks import DEFAULT_TASK, get_task


@dataclass(frozen=True)
class Contribution:
    """One feature's share of Q(s, a): weight times standardised feature."""

    name: str
    value: float  # the raw feature
    contribution: float  # w_j * (phi_j - mean_j) / scale_j


def feature_contributions(
    model: QModel, phi_d: np.ndarray, names: tuple[str, ...] | list[str]
) -> list[Contribution]:
    """Every feature's contribution to Q(s, a), largest magnitude first (they sum to Q - bias)."""
    phi = np.asarray(phi_d, dtype=float)
    z = (phi - model.feature_mean_d) / model.feature_scale_d
    contrib = model.weights_d * z
    order = np.argsort(-np.abs(contrib), kind="stable")
    return [Contribution(str(names[j]), float(phi[j]), float(contrib[j])) for j in order]


@dataclass
class PolicyChoices:
    """The demo each policy picks in one state (lookahead filled in when its search ends)."""

    nn: int
    greedy: int | None
    lookahead: int | None = None
    lookahead_name: str = ""
    lookahead_info: dict = field(default_factory=dict)
    # (levels finished, levels planned) while the search runs or when a person kept its choice
    # before the end; None once the whole search decided.
    lookahead_levels: tuple[int, int] | None = None

    def agree(self) -> bool:
        """True when every policy that has chosen picked the same demo."""
        picks = {p for p in (self.nn, self.greedy, self.lookahead) if p is not None}
        return len(picks) == 1


def lookahead_tree(info: dict, keys: tuple[str, ...]) -> list[tuple[str, int, float]]:
    """The search's root candidates as (demo key, depth reached, backed-up value), best first."""
    backed = info.get("backed_up", {})
    rows = [(keys[int(a)], int(d), float(v)) for a, (d, v) in backed.items()]
    return sorted(rows, key=lambda r: (-r[1], -r[2]))


def search_tree_lines(
    info: dict, keys: tuple[str, ...], max_lines: int = 60, stage_names: tuple[str, ...] = ()
) -> list[str]:
    """The lookahead's whole tree as a nested markdown list, in the order it was searched.

    One line per expansion: the demo, its Q at the parent, the stage its simulation reached,
    the child's value V = max Q there (none past the horizon or after a failure), and a mark
    where the knot was found; children are indented under their parent. ``stage_names``: the
    task's (default: the overhand knot's).
    """
    names = stage_names or get_task(DEFAULT_TASK).stage_names
    tree = info.get("tree") or []
    children: dict[int, list[dict]] = {}
    for entry in tree:
        children.setdefault(int(entry["parent"]), []).append(entry)
    lines: list[str] = []

    def emit(parent: int, depth: int) -> None:
        for e in children.get(parent, []):
            if len(lines) >= max_lines:
                return
            value = "-" if e.get("value") is None else f"{e['value']:.2f}"
            knot = " **knot**" if e.get("knot") else ""
            failed = f" ({e['failure']})" if e.get("failure") else ""
            memo = " (reused)" if e.get("reused") else ""
            lines.append(
                f"{'  ' * depth}- `{keys[int(e['action'])]}` Q {e['q']:.2f} -> stage "
                f"{stage_name(e.get('stage'), names)}, V {value}{knot}{failed}{memo}"
            )
            emit(int(e["node"]), depth + 1)

    emit(0, 0)
    if len(tree) > len(lines):
        lines.append(f"- ... {len(tree) - len(lines)} more expansions")
    return lines


def stage_name(stage: int | None, names: tuple[str, ...]) -> str:
    """A task's name for stage number ``stage`` ("?" when unknown, the number if out of range)."""
    if stage is None:
        return "?"
    return names[int(stage)] if 0 <= int(stage) < len(names) else str(stage)
