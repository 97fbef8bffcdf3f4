"""Run one knot-tying episode (at most 5 steps) with any policy, recording every step.

A failed registration, a misgrasp, a simulation blow-up or a numerical error inside a step is a
recorded step outcome, never an exception that would end a long benchmark: the episode ends as a
failure with a ``failure_kind`` and the error message kept in the record.
Shape suffixes: n = cloud points, k = rope nodes, a = demos.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from core.errors import KnotlabError
from core.features import LibraryFeaturizer
from core.planner import ActionOutcome, DemoTransferer, apply_demo
from core.policies import Policy, StepContext
from core.trajectory import GripperTrajectory

log = logging.getLogger(__name__)

MAX_STEPS = 5
FAILURE_KINDS: tuple[str, ...] = (
    "no_knot",  # ran out of steps
    "misgrasp",
    "registration",
    "exploded",
    "error",  # a numerical error inside a step
)
_NUMERIC_ERRORS = (KnotlabError, FloatingPointError, np.linalg.LinAlgError, ValueError)


@dataclass
class StepRecord:
    """One decision and its execution."""

    step_index: int
    cloud_n3: np.ndarray
    nodes_before_k3: np.ndarray
    chosen: int
    chosen_key: str
    scores_a: np.ndarray
    nn_cost_a: np.ndarray
    trajectory: GripperTrajectory | None
    outcome: str  # progressed | knot | misgrasp | registration | exploded | error
    knot: bool
    stage: int
    gauss_code: str
    failure: str | None
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


@dataclass
class EpisodeRecord:
    """A whole episode: success, steps, failure kind and time."""

    task_id: str
    policy: str
    success: bool
    steps: list[StepRecord]
    failure_kind: str | None
    error: str | None = None
    wall_s: float = 0.0

    @property
    def n_steps(self) -> int:
        """Steps executed."""
        return len(self.steps)

    def decision_times(self) -> list[float]:
        """Seconds spent choosing (scan + features + policy) at each step."""
        return [s.timings.get("decide_s", float("nan")) for s in self.steps]

    def summary(self) -> dict:
        """JSON-able per-task outcome for results files."""
        return {
            "task_id": self.task_id,
            "policy": self.policy,
            "success": self.success,
            "n_steps": self.n_steps,
            "failure_kind": self.failure_kind,
            "error": self.error,
            "wall_s": round(self.wall_s, 4),
            "decision_s": [round(t, 4) for t in self.decision_times()],
            "chosen": [s.chosen_key for s in self.steps],
            "outcomes": [s.outcome for s in self.steps],
            "stages": [s.stage for s in self.steps],
        }


def _step_seed(seed: int, step: int) -> int:
    return int(np.random.SeedSequence([int(seed), int(step)]).generate_state(1)[0])


def _classify(outcome: ActionOutcome) -> str:
    if outcome.knot:
        return "knot"
    failure = outcome.failure or ""
    if failure.startswith("registration") or failure.startswith("warp"):
        return "registration"
    if outcome.exploded:
        return "exploded"
    if failure.startswith("misgrasp"):
        return "misgrasp"
    return "progressed"


def run_episode(
    world,
    start_nodes_k3: np.ndarray,
    policy: Policy,
    featurizer: LibraryFeaturizer,
    transferer: DemoTransferer,
    *,
    task_id: str = "task",
    seed: int = 0,
    max_steps: int = MAX_STEPS,
    observe_noise: float = 0.0,
) -> EpisodeRecord:
    """Reset the world to the start rope and act with ``policy`` until a knot or ``max_steps``."""
    t_episode = time.perf_counter()
    steps: list[StepRecord] = []
    failure_kind: str | None = "no_knot"
    error: str | None = None
    try:
        world.reset(start_nodes_k3)
    except _NUMERIC_ERRORS as exc:  # a bad start state is this episode's failure, not the run's
        log.warning("task %s: cannot reset to its start state: %s", task_id, exc)
        return EpisodeRecord(
            task_id,
            policy.name,
            False,
            [],
            "error",
            f"{type(exc).__name__}: {exc}",
            time.perf_counter() - t_episode,
        )
    keys = featurizer.library.keys
    for step in range(max_steps):
        nodes_before = world.rope_nodes()
        try:
            t0 = time.perf_counter()
            cloud = featurizer.observe(world, noise=observe_noise, seed=_step_seed(seed, step))
            scan = featurizer.scan(cloud)
            t_scan = time.perf_counter() - t0
            ctx = StepContext(world, cloud, scan, featurizer, transferer, step, max_steps - step)
            decision = policy.choose(ctx)
            t_decide = time.perf_counter() - t0
            if decision.outcome is not None:
                world.restore(decision.outcome.snapshot_after)
                outcome = decision.outcome
            else:
                outcome = apply_demo(world, transferer, cloud, decision.action)
        except _NUMERIC_ERRORS as exc:
            log.warning("task %s step %d: %s: %s", task_id, step, type(exc).__name__, exc)
            failure_kind, error = "error", f"{type(exc).__name__}: {exc}"
            break
        kind = _classify(outcome)
        steps.append(
            StepRecord(
                step_index=step,
                cloud_n3=cloud,
                nodes_before_k3=nodes_before,
                chosen=decision.action,
                chosen_key=keys[decision.action],
                scores_a=decision.scores_a,
                nn_cost_a=np.asarray(scan.nn_cost_a),
                trajectory=outcome.plan.trajectory,
                outcome=kind,
                knot=outcome.knot,
                stage=outcome.stage,
                gauss_code=outcome.gauss_code,
                failure=outcome.failure,
                timings={
                    "scan_s": t_scan,
                    "decide_s": t_decide,
                    "step_s": time.perf_counter() - t0,
                    **outcome.plan.timings,
                },
                info=decision.info,
            )
        )
        if outcome.knot:
            failure_kind = None
            break
        if kind in ("exploded", "registration"):
            failure_kind = kind
            break
    success = bool(steps) and steps[-1].knot
    if not success and failure_kind == "no_knot" and any(s.outcome == "misgrasp" for s in steps):
        failure_kind = "misgrasp"  # ran out of steps after at least one empty grasp
    return EpisodeRecord(
        task_id,
        policy.name,
        success,
        steps,
        None if success else failure_kind,
        error,
        time.perf_counter() - t_episode,
    )
