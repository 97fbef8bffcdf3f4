"""Run one episode (up to the task's step limit) with an agent, recording every step.

A failed registration, a misgrasp, a simulation blow-up or a numerical error inside a step is a
recorded step outcome, never an exception that would end a long benchmark: the episode ends as a
failure with a ``failure_kind`` and the error message kept in the record.
Shape suffixes: n = cloud points, k = rope nodes, a = demos.
"""

from __future__ import annotations

import base64
import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.errors import InvalidInputError, KnotlabError
from knotlab.core.execution.apply import ActionOutcome
from knotlab.core.execution.memo import OutcomeMemo, execute_with_memo
from knotlab.core.failures import FailureKind
from knotlab.core.outcomes import StepOutcome
from knotlab.core.seeds import derive_seed
from knotlab.core.selection.decision import StepContext
from knotlab.core.world.estimate import PerfectEstimator, StateEstimator, place_estimate
from knotlab.core.world.observation import ObservationModel, centreline_points
from knotlab.core.world.protocol import World
from knotlab.core.world.trajectory import GripperTrajectory

if TYPE_CHECKING:  # the agent builds episodes
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import SimSnapshot

log = logging.getLogger(__name__)

FAILURE_KINDS: tuple[str, ...] = tuple(k.value for k in FailureKind)
_NUMERIC_ERRORS = (KnotlabError, FloatingPointError, np.linalg.LinAlgError, ValueError)
NODES_UNIT_M = 1e-4  # rope nodes in results files: int16 tenths of a millimetre (+-3.2 m)


def encode_nodes(nodes_k3: np.ndarray) -> str | None:
    """Rope nodes as base64 of little-endian int16 in 0.1 mm (None if not finite or too far)."""
    q = np.asarray(nodes_k3, dtype=float) / NODES_UNIT_M
    if q.ndim != 2 or q.shape[1] != 3 or not np.all(np.isfinite(q)) or np.abs(q).max() > 32767:
        return None  # a blown-up rope: nothing worth replaying from
    return base64.b64encode(np.round(q).astype("<i2").tobytes()).decode("ascii")


def decode_nodes(text: str) -> np.ndarray:
    """Inverse of :func:`encode_nodes`: (k, 3) float metres."""
    raw = np.frombuffer(base64.b64decode(text, validate=True), dtype="<i2")
    if raw.size % 3:
        raise KnotlabError(f"encoded rope nodes hold {raw.size} numbers, not a multiple of 3")
    return raw.reshape(-1, 3).astype(float) * NODES_UNIT_M


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
    outcome: StepOutcome | FailureKind  # KNOT, PROGRESSED, or the failure kind of the step
    knot: bool
    stage: int
    gauss_code: str
    failure: str | None
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


@dataclass(frozen=True)
class EpisodeOutcome:
    """One episode's row in a results file (``outcomes.jsonl``): what Table I is counted from."""

    task_id: str
    policy: str
    success: bool
    n_steps: int
    failure_kind: FailureKind | None
    error: str | None
    wall_s: float
    decision_s: tuple[float, ...] = ()
    chosen: tuple[str, ...] = ()
    outcomes: tuple[str, ...] = ()
    stages: tuple[int, ...] = ()
    # For playback (absent from files written before them): the chosen demo's score per step
    # (Q, or -registration cost for NN; None if not finite) and the rope before each step
    # (`encode_nodes`).
    scores: tuple[float | None, ...] = ()
    nodes_before: tuple[str | None, ...] = ()
    # With a state estimator that is not the world's own state: the mean node error (mm) of the
    # estimate each step decided from (absent otherwise).
    estimate_error_mm: tuple[float, ...] = ()
    # With a policy that plans in one of several models (the adaptive lookahead): the member it
    # planned in at each step, 0 being the agent's own model (absent otherwise).
    planned_in: tuple[int, ...] = ()
    # With a state estimator: the estimate's shape error (mm) at each step, the mean distance
    # from each centreline to the other (what a cloud-only policy sees; a chain slid along the
    # rope has a node error but no shape error).
    estimate_shape_mm: tuple[float, ...] = ()
    # With a state estimator: whether the estimate crossed itself as the rope did at each step
    # (the same over/under crossing code; `RopeEstimate.crossings_right`).
    estimate_crossings_right: tuple[bool, ...] = ()
    # With a state estimator: the estimated rope each step decided from (`encode_nodes`), beside
    # the true rope in ``nodes_before``, so where an estimate went wrong can be read back.
    estimate_nodes: tuple[str | None, ...] = ()

    @classmethod
    def errored(
        cls, task_id: str, policy: str, message: str, wall_s: float = 0.0
    ) -> EpisodeOutcome:
        """The row of an episode that crashed before it could record a step."""
        return cls(task_id, policy, False, 0, FailureKind.ERROR, message, wall_s)

    def to_dict(self) -> dict:
        """JSON-able row (failure kind as its value string, lists for sequences)."""
        return {
            "task_id": self.task_id,
            "policy": self.policy,
            "success": self.success,
            "n_steps": self.n_steps,
            "failure_kind": None if self.failure_kind is None else self.failure_kind.value,
            "error": self.error,
            "wall_s": round(self.wall_s, 4),
            "decision_s": [round(t, 4) for t in self.decision_s],
            "chosen": list(self.chosen),
            "outcomes": list(self.outcomes),
            "stages": [int(s) for s in self.stages],
            "scores": [None if v is None else round(v, 6) for v in self.scores],
            "nodes_before": list(self.nodes_before),
            **(
                {"estimate_error_mm": [round(e, 3) for e in self.estimate_error_mm]}
                if self.estimate_error_mm
                else {}
            ),
            **({"planned_in": list(self.planned_in)} if self.planned_in else {}),
            **(
                {"estimate_shape_mm": [round(e, 3) for e in self.estimate_shape_mm]}
                if self.estimate_shape_mm
                else {}
            ),
            **(
                {"estimate_crossings_right": list(self.estimate_crossings_right)}
                if self.estimate_crossings_right
                else {}
            ),
            **({"estimate_nodes": list(self.estimate_nodes)} if self.estimate_nodes else {}),
        }


@dataclass
class EpisodeRecord:
    """A whole episode: success, steps, failure kind and time."""

    task_id: str
    policy: str
    success: bool
    steps: list[StepRecord]
    failure_kind: FailureKind | None
    error: str | None = None
    wall_s: float = 0.0

    @property
    def n_steps(self) -> int:
        """Steps executed."""
        return len(self.steps)

    def decision_times(self) -> list[float]:
        """Seconds spent choosing (scan + features + policy) at each step."""
        return [s.timings.get("decide_s", float("nan")) for s in self.steps]

    def outcome(self) -> EpisodeOutcome:
        """The episode's results-file row."""
        return EpisodeOutcome(
            self.task_id,
            self.policy,
            self.success,
            self.n_steps,
            self.failure_kind,
            self.error,
            self.wall_s,
            tuple(self.decision_times()),
            tuple(s.chosen_key for s in self.steps),
            tuple(s.outcome.value for s in self.steps),
            tuple(int(s.stage) for s in self.steps),
            tuple(_finite(s.scores_a[s.chosen]) for s in self.steps),
            tuple(encode_nodes(s.nodes_before_k3) for s in self.steps),
            tuple(
                float(s.info["estimate_error_mm"])
                for s in self.steps
                if "estimate_error_mm" in s.info
            ),
            tuple(int(s.info["planned_in"]) for s in self.steps if "planned_in" in s.info),
            tuple(
                float(s.info["estimate_shape_mm"])
                for s in self.steps
                if "estimate_shape_mm" in s.info
            ),
            tuple(
                bool(s.info["estimate_crossings_right"])
                for s in self.steps
                if "estimate_crossings_right" in s.info
            ),
            tuple(s.info["estimate_nodes"] for s in self.steps if "estimate_nodes" in s.info),
        )

    def summary(self) -> dict:
        """JSON-able per-task outcome for results files (`EpisodeOutcome.to_dict`)."""
        return self.outcome().to_dict()


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def step_seed(seed: int, step: int) -> int:
    """Observation-noise seed of step ``step`` of an episode seeded ``seed`` (replays use it)."""
    return derive_seed(seed, step)


def _classify(outcome: ActionOutcome) -> StepOutcome | FailureKind:
    """The step's outcome word: knot, progressed, or the failure kind set by planner or sim."""
    if outcome.knot:
        return StepOutcome.KNOT
    kind = outcome.failure_kind
    return StepOutcome.PROGRESSED if kind is None else kind


def run_episode(
    agent: Agent,
    world: World,
    start_nodes_k3: np.ndarray,
    *,
    task_id: str = "task",
    seed: int = 0,
    max_steps: int | None = None,
    observe_noise: float = 0.0,
    memo: OutcomeMemo | None = None,
    model_world: World | None = None,
    estimator: StateEstimator | None = None,
    start_snapshot: SimSnapshot | None = None,
) -> EpisodeRecord:
    """Reset the world to the start rope and act with ``agent`` until its task's goal or
    ``max_steps`` (default: the task's step limit).

    ``start_snapshot``: begin in this full simulator state (a state another episode reached,
    velocities and contacts included) instead of the rope at rest along ``start_nodes_k3``.

    ``memo``: simulated outcomes shared with the other policies run on this task (same start,
    same seed), so an execution another policy already simulated is restored, not simulated
    again; the episode is the same either way.

    ``model_world`` and ``estimator``: the agent's model of the world (core/world/estimate.py).
    Its policies simulate in ``model_world`` placed in the ``estimator``'s state, and only the
    chosen demo runs in ``world``. Neither given (or a perfect estimator and no model world): the
    agent's model is the world itself, which is what a perfect estimate with the world's own
    physics amounts to, bit for bit.
    """
    t_episode = time.perf_counter()
    steps: list[StepRecord] = []
    failure_kind: FailureKind | None = FailureKind.NO_KNOT
    error: str | None = None
    limit = agent.task.step_limit if max_steps is None else max_steps
    try:
        if start_snapshot is None:
            world.reset(start_nodes_k3)
        else:
            world.restore(start_snapshot)
    except _NUMERIC_ERRORS as exc:  # a bad start state is this episode's failure, not the run's
        log.warning("task %s: cannot reset to its start state: %s", task_id, exc)
        return EpisodeRecord(
            task_id,
            agent.name,
            False,
            [],
            FailureKind.ERROR,
            f"{type(exc).__name__}: {exc}",
            time.perf_counter() - t_episode,
        )
    keys = agent.library.keys
    estimator = estimator if estimator is not None else PerfectEstimator()
    itself = model_world is None or model_world is world
    if itself and not isinstance(estimator, PerfectEstimator):
        raise InvalidInputError("an estimated state needs a model world apart from the world")
    observation = agent.featurizer.observation
    if (
        not isinstance(estimator, PerfectEstimator)
        and observation is not ObservationModel.CENTRELINE
    ):
        raise InvalidInputError(
            f"the {estimator.kind.value} estimator reports a centreline; the library's "
            f"observation model is {observation.value}"
        )
    sim_world = world if model_world is None else model_world
    estimator.start(world, seed, sim_world)
    for step in range(limit):
        nodes_before = world.rope_nodes()
        estimate_info: dict = {}
        try:
            t0 = time.perf_counter()
            if isinstance(estimator, PerfectEstimator):
                cloud = agent.observe(world, noise=observe_noise, seed=step_seed(seed, step))
                if not itself:
                    place_estimate(sim_world, estimator.estimate(world))
            else:
                estimate = estimator.estimate(world)
                place_estimate(sim_world, estimate)
                cloud = centreline_points(estimate.nodes_k3)
                if observe_noise > 0:
                    rng = np.random.default_rng(step_seed(seed, step))
                    cloud = cloud + rng.normal(0.0, observe_noise, size=cloud.shape)
                estimate_info = {
                    "estimate_nodes": encode_nodes(estimate.nodes_k3),
                    "estimate_error_mm": estimate.error_mm,
                    "estimate_shape_mm": estimate.shape_mm,
                    **(
                        {"estimate_crossings_right": estimate.crossings_right}
                        if estimate.crossings_right is not None
                        else {}
                    ),
                }
            scan = agent.scan(cloud)
            t_scan = time.perf_counter() - t0
            ctx = StepContext(
                sim_world,
                cloud,
                scan,
                agent.featurizer,
                agent.transferer,
                step,
                limit - step,
                memo,
            )
            decision = agent.policy.choose(ctx)
            t_decide = time.perf_counter() - t0
            if itself and decision.outcome is not None:
                world.restore(decision.outcome.snapshot_after)
                outcome = decision.outcome
            else:  # the model's simulated outcome is only its prediction: the world acts
                outcome = execute_with_memo(
                    memo,
                    world,
                    agent.transferer,
                    cloud,
                    decision.action,
                    task=agent.task,
                    frame_dt=estimator.frame_dt,
                )
            if not itself:
                frames = outcome.execution.frames if outcome.execution is not None else None
                estimator.executed(outcome.plan.trajectory, sim_world, frames)
        except _NUMERIC_ERRORS as exc:
            log.warning("task %s step %d: %s: %s", task_id, step, type(exc).__name__, exc)
            failure_kind, error = FailureKind.ERROR, f"{type(exc).__name__}: {exc}"
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
                info={**decision.info, **estimate_info},
            )
        )
        if outcome.knot:
            failure_kind = None
            break
        step_kind = outcome.failure_kind
        if step_kind is not None and step_kind.ends_episode:
            failure_kind = step_kind
            break
    success = bool(steps) and steps[-1].knot
    if (
        not success
        and failure_kind is FailureKind.NO_KNOT
        and any(s.outcome == FailureKind.MISGRASP for s in steps)
    ):
        failure_kind = FailureKind.MISGRASP  # ran out of steps after at least one empty grasp
    return EpisodeRecord(
        task_id,
        agent.name,
        success,
        steps,
        None if success else failure_kind,
        error,
        time.perf_counter() - t_episode,
    )
