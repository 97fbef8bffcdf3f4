"""`knotlab labels agreement`: how often labellers chose the same demo in the same state."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math

from knotlab.app.options import add_db_argument, add_flag, db_url
from knotlab.core.errors import InvalidInputError, KnotlabError
from knotlab.core.selection.agreement import MATCHES, PairAgreement


def _num(value: float | None, fmt: str = ".3f") -> str:
    return "n/a" if value is None or not math.isfinite(value) else format(value, fmt)


def format_agreement(pairs: list[PairAgreement], *, max_disagreements: int = 20) -> str:
    """A per-pair table, then each pair's disagreements (at most ``max_disagreements`` each)."""
    head = (
        f"{'labeller a':<14} {'labeller b':<14} {'shared':>6} {'compared':>8} {'top-1':>6} "
        f"{'kappa':>6} {'p_e':>6}  dead ends (both/only a/only b/neither)"
    )
    lines = [head, "-" * len(head)]
    for p in pairs:
        lines.append(
            f"{p.labeller_a:<14} {p.labeller_b:<14} {p.n_shared:>6} {p.n_compared:>8} "
            f"{_num(p.top1):>6} {_num(p.kappa):>6} {_num(p.chance):>6}  "
            f"{p.dead_end_both}/{p.dead_end_only_a}/{p.dead_end_only_b}/{p.dead_end_neither}"
        )
    for p in pairs:
        if not p.disagreements:
            continue
        lines += ["", f"disagreements of {p.labeller_a} and {p.labeller_b}:"]
        for d in p.disagreements[:max_disagreements]:
            after = " after " + ",".join(d.path) if d.path else ""
            lines.append(f"  {d.start} step {d.step_index}{after}: {d.demo_a} vs {d.demo_b}")
        if len(p.disagreements) > max_disagreements:
            lines.append(f"  ... and {len(p.disagreements) - max_disagreements} more (--json)")
    return "\n".join(lines)


def _run(args: argparse.Namespace) -> int:
    from knotlab.core.selection.agreement import pairwise_agreement
    from knotlab.labeling_db.errors import LabelingDbError
    from knotlab.labeling_db.store import open_store

    try:
        with open_store(db_url(args), create=False, auto_upgrade=False) as store:
            visits = store.state_visits()
    except LabelingDbError as exc:
        if isinstance(exc, KnotlabError):
            raise
        raise InvalidInputError(str(exc)) from exc
    pairs = pairwise_agreement(visits, match=args.match)
    if args.json:
        print(json.dumps([dataclasses.asdict(p) for p in pairs], allow_nan=False, default=str))
        return 0
    if not pairs:
        labellers = sorted({v.labeller for v in visits})
        print(f"fewer than two labellers with labels ({', '.join(labellers) or 'none'})")
        return 0
    print(format_agreement(pairs))
    return 0


def register_agreement(sub: argparse._SubParsersAction) -> None:
    """Add `agreement` to the `knotlab labels` actions."""
    p = sub.add_parser(
        "agreement",
        help="per pair of labellers: top-1 agreement, Cohen's kappa, dead ends, disagreements",
    )
    p.add_argument(
        "--match",
        choices=MATCHES,
        default="path",
        help="same state = same start, step and earlier choices (path, default) or start and "
        "step only (step)",
    )
    add_flag(p, "--json", detail="the pairs")
    add_db_argument(p)
    p.set_defaults(func=_run)
