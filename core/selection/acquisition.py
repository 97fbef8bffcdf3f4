"""What to label next: acquisition scores of unlabelled states, and the ranking they give.

Two signals, both from quantities the selection code already computes for a state:
- the Q margin Q(s, a1) - Q(s, a2) between the two best usable demos: a small margin means the
  model can hardly tell its first choice from its second, so the expert's answer moves it most
  (margin sampling);
- disagreement between policies (nearest neighbour, greedy, optionally lookahead): the fraction
  of policy pairs that choose different demos (query by committee with the policies as the
  committee). Where registration cost and the learned Q agree, a label teaches little.
The combined ranking puts more disagreement first, then the smaller margin; remaining ties are
broken by a seeded per-item number, so the order depends on the seed and the item keys only, not
on the order the items came in.
Shape suffix: a = demos (actions).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import TYPE_CHECKING, Literal

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.seeds import text_uniform
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.ranking import RegisteredDemos, demo_scores, rank_order

if TYPE_CHECKING:  # annotations only
    from knotlab.core.demos.tasks import RopeTask
    from knotlab.core.selection.features import LibraryFeaturizer
    from knotlab.core.selection.scan_cache import ScanSummaryCache

RankBy = Literal["combined", "margin", "disagreement"]
RANK_BY: tuple[str, ...] = ("combined", "margin", "disagreement")


def q_margin(q_a: np.ndarray) -> float:
    """Q(s, a1) - Q(s, a2) of the two best finite scores (inf with fewer than two usable demos)."""
    q = np.asarray(q_a, dtype=float)
    if q.ndim != 1:
        raise InvalidInputError(f"q_a must be one-dimensional, got shape {q.shape}")
    usable = np.sort(q[np.isfinite(q)])
    if len(usable) < 2:
        return math.inf  # nothing to choose between: labelling it teaches the ranking nothing
    return float(usable[-1] - usable[-2])


def choice_disagreement(choices: Mapping[str, int | str]) -> float:
    """Fraction of policy pairs choosing different demos (0 = all agree; 0 with < 2 policies)."""
    picks = list(choices.values())
    pairs = list(combinations(picks, 2))
    if not pairs:
        return 0.0
    return sum(a != b for a, b in pairs) / len(pairs)


@dataclass(frozen=True)
class AcquisitionScore:
    """One unlabelled state's scores: its key, the Q margin, the policies' choices."""

    key: str  # task id or store state id: what the tie-break is seeded by
    margin: float
    choices: dict[str, str] = field(default_factory=dict)  # policy name -> demo key

    @property
    def disagreement(self) -> float:
        """Fraction of policy pairs that disagree (see `choice_disagreement`)."""
        return choice_disagreement(self.choices)


def score_state(key: str, q_a: np.ndarray, choices: Mapping[str, str]) -> AcquisitionScore:
    """The acquisition score of one state from its Q vector and each policy's chosen demo."""
    return AcquisitionScore(key, q_margin(q_a), dict(choices))


@dataclass(frozen=True)
class RankedState:
    """A state's place in the labelling order (1 = label first) and its scores."""

    rank: int
    score: AcquisitionScore


def rank_for_labelling(
    scores: Sequence[AcquisitionScore], *, by: RankBy = "combined", seed: int = 0
) -> list[RankedState]:
    """States in the order to label them: most informative first (see module docstring)."""
    if by not in RANK_BY:
        raise InvalidInputError(f"rank by must be one of {RANK_BY}, got {by!r}")
    keys = [s.key for s in scores]
    if len(set(keys)) != len(keys):
        raise InvalidInputError("acquisition scores must have distinct keys")

    def sort_key(s: AcquisitionScore) -> tuple[float, ...]:
        tie = text_uniform(seed, s.key)
        if by == "margin":
            return (s.margin, tie)
        if by == "disagreement":
            return (-s.disagreement, tie)
        return (-s.disagreement, s.margin, tie)

    ordered = sorted(scores, key=sort_key)
    return [RankedState(i + 1, s) for i, s in enumerate(ordered)]


def score_scan(
    key: str, scan: RegisteredDemos, phi_ad: np.ndarray, model: QModel, demo_keys: Sequence[str]
) -> AcquisitionScore:
    """A state's score from its scan (or summary): Q margin, and the NN and greedy choices."""
    q_a = demo_scores(scan, phi_ad, model)
    choices = {}
    for name, order in (
        ("nn", rank_order(demo_scores(scan, None, None))),
        ("greedy", rank_order(q_a)),
    ):
        if len(order):
            choices[name] = demo_keys[int(order[0])]
    return score_state(key, q_a, choices)


def score_starts(
    starts: Sequence[tuple[str, np.ndarray]],
    featurizer: LibraryFeaturizer,
    model: QModel,
    scans: ScanSummaryCache,
    *,
    stop: Callable[[], bool] = lambda: False,
    report: Callable[[int, int], None] = lambda done, total: None,
) -> list[AcquisitionScore]:
    """`score_scan` of every keyed start cloud from its scan summary and landmark weights
    (taken from ``scans``, or computed and kept there); ``stop`` is asked before each start,
    ``report(done, total)`` after."""
    keys = featurizer.library.keys
    out = []
    for key, cloud in starts:
        if stop():
            break
        made = scans.features(featurizer, cloud)
        out.append(score_scan(key, made.summary, made.phi_ad, model, keys))
        report(len(out), len(starts))
    return out


def task_start_clouds(
    tasks: Iterable[RopeTask], featurizer: LibraryFeaturizer, *, progress: bool = True
) -> dict[str, np.ndarray]:
    """The observed cloud of every task's start state, keyed by task id (one world reset each)."""
    from tqdm import tqdm

    from knotlab.core.world.sim import RopeWorld

    out = {}
    with RopeWorld() as world:
        for task in tqdm(tasks, desc="observing starts", disable=not progress):
            world.reset(task.start_nodes_k3)
            out[task.task_id] = featurizer.observe(world)
    return out
