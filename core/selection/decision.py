"""What a policy sees and answers: the step's context, the decision, the `Policy` interface.

Every policy answers ``choose(ctx) -> Decision`` for one state. Policies that simulate candidate
actions (lookahead, oracle) leave the world in the state they found it and hand back the outcome
of the chosen action, so the episode does not simulate it twice.
Shape suffix: a = demos (actions), n = cloud points.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.execution.memo import OutcomeMemo
from knotlab.core.registration import ScanResult
from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.world.protocol import World


@dataclass
class StepContext:
    """Everything a policy may look at to choose the next demo."""

    world: World
    cloud_n3: np.ndarray
    scan: ScanResult
    featurizer: LibraryFeaturizer
    transferer: DemoTransferer
    step_index: int
    steps_left: int
    # Outcomes shared with other policies on the same task (a bench run with
    # --share-simulations); None: each policy keeps its own (the lookahead's) or none.
    memo: OutcomeMemo | None = None
    _phi_ad: np.ndarray | None = None
    # A search that works in levels (lookahead) reports its choice so far after each finished
    # level (an anytime search: the app shows it at once); the final decision is the same.
    on_level: Callable[[LevelDecision], None] | None = None

    @property
    def phi_ad(self) -> np.ndarray:
        """Features of every demo in this state (computed once, on first use)."""
        if self._phi_ad is None:
            self._phi_ad = self.featurizer.features_from_scan(self.scan, self.cloud_n3)
        return self._phi_ad


@dataclass
class Decision:
    """The chosen demo, every demo's score (higher = better) and what the search saw."""

    action: int
    scores_a: np.ndarray
    info: dict = field(default_factory=dict)
    outcome: ActionOutcome | None = None  # set when the policy already simulated the choice


@dataclass(frozen=True)
class LevelDecision:
    """A levelled search's decision if it stopped after ``level`` of its ``levels`` levels."""

    level: int
    levels: int
    decision: Decision


class Policy(ABC):
    """Chooses which library demo to transfer in a state."""

    name: str = "policy"

    @abstractmethod
    def choose(self, ctx: StepContext) -> Decision:
        """Pick a demo for the state in ``ctx``."""
