"""Agreement between labellers: how often two experts choose the same demo in the same state.

A *visit* is one labeller in one state of one episode: the demo chosen there (if any) and whether
they marked a dead end from it. Two visits are of the same state when they share the start (task
id, or the store's start state id), the step index and, with ``match="path"`` (the default), the
demos chosen before it: the simulator is deterministic, so the same start and the same earlier
choices give the same rope. ``match="step"`` pairs visits by start and step index alone (looser:
after a first disagreement the ropes differ).

Per pair of labellers, over the states both visited:
- top-1 agreement p_o: the share of states where both chose the same demo;
- Cohen's kappa over the chosen demo, a categorical rating: kappa = (p_o - p_e) / (1 - p_e), with
  the chance agreement p_e = sum_k pA(k) pB(k) from each labeller's marginal share of demo k.
  p_e = 1 only when both chose one and the same demo in every shared state: kappa is then 0/0
  and reported as undefined (None), like with no shared state; top-1 (= 1) says all there is;
- dead ends: states both marked, only one marked, neither marked;
- the disagreements themselves.
The overlap policy decides, per start and seeded, which starts are offered to a second labeller.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Literal

from knotlab.core.errors import InvalidInputError
from knotlab.core.seeds import text_uniform

Match = Literal["path", "step"]
MATCHES: tuple[str, ...] = ("path", "step")


@dataclass(frozen=True)
class StateVisit:
    """One labeller in one state: the demo chosen (None: none accepted) and a dead-end mark."""

    labeller: str
    start: str  # task id, or "state:<id>" for a start state without one
    step_index: int
    path: tuple[str, ...] = ()  # demos this episode chose before this step
    chosen_demo: str | None = None
    dead_end: bool = False  # marked a dead end from this state (a try judged hopeless)

    def state_key(self, match: Match = "path") -> tuple:
        """What identifies the state across labellers under ``match``."""
        if match == "path":
            return (self.start, self.step_index, self.path)
        return (self.start, self.step_index)


@dataclass(frozen=True)
class Disagreement:
    """A shared state where the two labellers chose different demos."""

    start: str
    step_index: int
    path: tuple[str, ...]
    demo_a: str
    demo_b: str


@dataclass(frozen=True)
class PairAgreement:
    """Agreement of labellers a and b over the states both visited."""

    labeller_a: str
    labeller_b: str
    n_shared: int  # states both visited
    n_compared: int  # of those, states where both chose a demo
    n_agree: int
    top1: float | None  # n_agree / n_compared (None when nothing to compare)
    kappa: float | None  # Cohen's kappa (None: no comparison, or p_e = 1)
    chance: float | None  # p_e
    dead_end_both: int
    dead_end_only_a: int
    dead_end_only_b: int
    dead_end_neither: int
    disagreements: tuple[Disagreement, ...] = ()


def cohen_kappa(ratings_a: Sequence[str], ratings_b: Sequence[str]) -> tuple[float | None, float]:
    """Cohen's kappa and chance agreement p_e of two raters' categorical ratings of the same items.

    kappa = (p_o - p_e) / (1 - p_e), p_e = sum_k pA(k) pB(k); kappa is None when p_e = 1 (both
    raters used one and the same category throughout) or there are no items (p_e is then nan).
    """
    if len(ratings_a) != len(ratings_b):
        raise InvalidInputError(
            f"kappa needs ratings of the same items, got {len(ratings_a)} and {len(ratings_b)}"
        )
    n = len(ratings_a)
    if n == 0:
        return None, math.nan
    p_o = sum(a == b for a, b in zip(ratings_a, ratings_b, strict=True)) / n
    count_a, count_b = Counter(ratings_a), Counter(ratings_b)
    p_e = sum(count_a[k] * count_b[k] for k in count_a) / (n * n)
    if math.isclose(p_e, 1.0):
        return None, 1.0
    return (p_o - p_e) / (1.0 - p_e), p_e


def _latest_visits(
    visits: Sequence[StateVisit], match: Match
) -> dict[str, dict[tuple, StateVisit]]:
    """labeller -> state key -> visit; a labeller's later visit of a state replaces the earlier."""
    out: dict[str, dict[tuple, StateVisit]] = {}
    for v in visits:
        mine = out.setdefault(v.labeller, {})
        old = mine.get(v.state_key(match))
        # Keep the dead-end mark of an earlier visit: a mark is not undone by visiting again.
        mine[v.state_key(match)] = (
            v if old is None or not old.dead_end or v.dead_end else _with_dead_end(v)
        )
    return out


def _with_dead_end(v: StateVisit) -> StateVisit:
    return StateVisit(v.labeller, v.start, v.step_index, v.path, v.chosen_demo, True)


def pair_agreement(
    visits: Sequence[StateVisit], labeller_a: str, labeller_b: str, *, match: Match = "path"
) -> PairAgreement:
    """Agreement of two labellers over the states both visited (see module docstring)."""
    if match not in MATCHES:
        raise InvalidInputError(f"match must be one of {MATCHES}, got {match!r}")
    by = _latest_visits(visits, match)
    mine_a, mine_b = by.get(labeller_a, {}), by.get(labeller_b, {})
    shared = sorted(set(mine_a) & set(mine_b), key=repr)
    rated_a: list[str] = []
    rated_b: list[str] = []
    disagreements = []
    dead: Counter[tuple[bool, bool]] = Counter()
    for key in shared:
        va, vb = mine_a[key], mine_b[key]
        dead[(va.dead_end, vb.dead_end)] += 1
        if va.chosen_demo is None or vb.chosen_demo is None:
            continue
        rated_a.append(va.chosen_demo)
        rated_b.append(vb.chosen_demo)
        if va.chosen_demo != vb.chosen_demo:
            disagreements.append(
                Disagreement(va.start, va.step_index, va.path, va.chosen_demo, vb.chosen_demo)
            )
    n = len(rated_a)
    agree = n - len(disagreements)
    kappa, chance = cohen_kappa(rated_a, rated_b)
    return PairAgreement(
        labeller_a=labeller_a,
        labeller_b=labeller_b,
        n_shared=len(shared),
        n_compared=n,
        n_agree=agree,
        top1=agree / n if n else None,
        kappa=kappa,
        chance=chance if n else None,
        dead_end_both=dead[(True, True)],
        dead_end_only_a=dead[(True, False)],
        dead_end_only_b=dead[(False, True)],
        dead_end_neither=dead[(False, False)],
        disagreements=tuple(disagreements),
    )


def pairwise_agreement(
    visits: Sequence[StateVisit], *, match: Match = "path"
) -> list[PairAgreement]:
    """`pair_agreement` of every pair of labellers (sorted names), also pairs sharing nothing."""
    names = sorted({v.labeller for v in visits})
    return [pair_agreement(visits, a, b, match=match) for a, b in combinations(names, 2)]


@dataclass(frozen=True)
class OverlapPolicy:
    """Which starts are offered to a second labeller: a seeded share ``overlap`` of them.

    A start is in the overlap set iff u(seed, start key) < overlap, with u a uniform number fixed
    by the seed and the key alone: the decision never depends on claiming order or on who asks.
    """

    overlap: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.overlap) and 0.0 <= self.overlap <= 1.0):
            raise InvalidInputError(f"overlap must be a share in [0, 1], got {self.overlap}")

    def offers_second(self, start_key: str) -> bool:
        """True when the start ``start_key`` (a task id) should get a second labeller."""
        return text_uniform(self.seed, start_key) < self.overlap
