"""`Agent`: the one object that decides which demonstration to transfer to a rope, and acts.

Built once from a demo library, an optional Q-model (none: nearest neighbour ranks by
registration cost) and a policy name (nn, greedy, la<D>x<W>, oracle); the constructor runs every
compatibility check (task, observation model, library hash, feature columns) once and warms the
registrar, so the first decision costs what every later one does. Then:

    cloud = agent.observe(world)             # the library's observation model
    ranked = agent.rank(cloud)               # the app's candidate list (Q, cost, warped path)
    decision = agent.choose(world)           # the policy's choice and why (scores, search tree)
    outcome = agent.act(world, decision.action)   # transfer + execute + the task's stage
    record = agent.run_episode(world, start)      # until the task's goal or its step limit

Agents made by `with_policy` share the library's featurizer (registration caches) and
transferer, so one process can run several policies on one warm state (the bench does).
Shape suffixes: n = cloud points, k = rope nodes, a = demos.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.demos.tasks import RopeTask
from knotlab.core.errors import InvalidInputError
from knotlab.core.execution.apply import ActionOutcome, apply_demo
from knotlab.core.execution.expansion import ExpansionRunner
from knotlab.core.execution.memo import OutcomeMemo
from knotlab.core.registration import EXACT, SCAN, RegistrationParams, ScanResult
from knotlab.core.registration.library_scan import LibraryRegistrar
from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.selection.compatibility import check_compatible
from knotlab.core.selection.decision import Decision, Policy, StepContext
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.policies import PolicyConfig, policy_config
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.ranking import demo_scores, rank_order
from knotlab.core.tasks import Task, get_task
from knotlab.core.world.estimate import StateEstimator
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.protocol import NO_WORLD, World
from knotlab.core.world.trajectory import GripperTrajectory

if TYPE_CHECKING:  # the episode record: only for the checker
    from knotlab.core.experiments.episode import EpisodeRecord

RegistrationPreset = Literal["scan", "exact"]
_PRESETS: dict[str, RegistrationParams] = {"scan": SCAN, "exact": EXACT}


@dataclass(frozen=True)
class Candidate:
    """One ranked demo for a state: what the app lists and a robot would execute."""

    rank: int  # 1 = best
    demo_index: int
    demo_key: str
    score: float  # Q with a model, else -registration cost (higher is better either way)
    q: float | None  # Q(s, a); None when ranked without a model
    nn_cost: float  # bidirectional registration cost (the nearest-neighbour score)
    trajectory: GripperTrajectory | None  # the demo's gripper path warped onto the scene
    failure: str | None = None  # why there is no trajectory (the exact registration failed)


def _policy_name(policy: str, depth: int | None, width: int | None) -> str:
    """The registry name of ``policy``, with depth/width folded into a lookahead's name."""
    if policy == "lookahead":
        if depth is None or width is None:
            raise InvalidInputError("policy 'lookahead' needs depth= and width=")
        return f"la{depth}x{width}"
    if depth is not None or width is not None:
        config = policy_config(policy)
        if config.kind != "lookahead" or (depth, width) != (config.depth, config.width):
            raise InvalidInputError(
                f"depth/width apply to policy 'lookahead' only (got {policy!r} with depth "
                f"{depth}, width {width})"
            )
    return policy


class Agent:
    """Chooses and executes library demos for a rope, with one policy, for one task."""

    def __init__(
        self,
        library: DemoLibrary,
        model: QModel | None = None,
        policy: str = "nn",
        *,
        task: str | Task | None = None,
        top_k: int = 5,
        depth: int | None = None,
        width: int | None = None,
        registration: RegistrationPreset = "scan",
        scan_threads: int = 1,
        runner: ExpansionRunner | None = None,
        _shared: tuple[LibraryFeaturizer, DemoTransferer] | None = None,
    ) -> None:
        if top_k < 1:
            raise InvalidInputError(f"top_k must be >= 1, got {top_k}")
        if registration not in _PRESETS:
            raise InvalidInputError(
                f"unknown registration preset {registration!r}; expected one of {list(_PRESETS)}"
            )
        self.config: PolicyConfig = policy_config(_policy_name(policy, depth, width))
        if self.config.needs_model and model is None:
            raise InvalidInputError(f"policy {self.config.name!r} needs a trained Q-model")
        self.task: Task = task if isinstance(task, Task) else get_task(task or library.task)
        self.library = library
        self.model = model
        self.top_k = int(top_k)
        self.registration: RegistrationPreset = registration
        if _shared is None:
            check_compatible(library, model, self.task)
            registrar = LibraryRegistrar(_PRESETS[registration], n_workers=scan_threads)
            _shared = (self._featurizer(model, registrar), DemoTransferer(library))
        self.featurizer, self.transferer = _shared
        self.policy: Policy = self.config.build(model)
        if runner is not None and hasattr(self.policy, "runner"):
            self.policy.runner = runner

    def _featurizer(self, model: QModel | None, registrar: LibraryRegistrar) -> LibraryFeaturizer:
        """The featurizer of ``model`` (its landmarks; plain without one), registrar warm."""
        params = registrar.params
        featurizer = (
            LibraryFeaturizer.for_model(self.library, model, registrar=registrar, params=params)
            if model is not None
            else LibraryFeaturizer(self.library, registrar=registrar, params=params)
        )
        # The demo side of the scan (normalised, factorised clouds) now, not in the first
        # decision: from the registrar's disk cache when it has it.
        registrar.prepare(self.library.clouds(), featurizer.library_hash, params)
        return featurizer

    @classmethod
    def default(
        cls,
        policy: str = "greedy",
        *,
        task: str = "overhand",
        top_k: int = 5,
        depth: int | None = None,
        width: int | None = None,
        registration: RegistrationPreset = "scan",
        scan_threads: int = 1,
    ) -> Agent:
        """An agent on the task's shipped library and model (the model only where the policy
        uses one, so nn and oracle rank exactly as nearest neighbour)."""
        spec = get_task(task)
        library = DemoLibrary.load(spec.files.library_path)
        needs = policy_config(_policy_name(policy, depth, width)).needs_model
        model = QModel.load(spec.files.model_path) if needs else None
        return cls(
            library,
            model,
            policy,
            task=spec,
            top_k=top_k,
            depth=depth,
            width=width,
            registration=registration,
            scan_threads=scan_threads,
        )

    def with_policy(self, policy: str, *, runner: ExpansionRunner | None = None) -> Agent:
        """Another policy on this agent's library, model, task and warm caches."""
        return Agent(
            self.library,
            self.model,
            policy,
            task=self.task,
            top_k=self.top_k,
            registration=self.registration,
            runner=runner,
            _shared=(self.featurizer, self.transferer),
        )

    def with_model(
        self, model: QModel, policy: str = "greedy", *, runner: ExpansionRunner | None = None
    ) -> Agent:
        """An agent ranking with ``model`` (checked against library and task) that shares this
        one's registrar and transferer, so no cache is built twice."""
        check_compatible(self.library, model, self.task)
        featurizer = self._featurizer(model, self.featurizer.registrar)
        return Agent(
            self.library,
            model,
            policy,
            task=self.task,
            top_k=self.top_k,
            registration=self.registration,
            runner=runner,
            _shared=(featurizer, self.transferer),
        )

    @property
    def name(self) -> str:
        """The policy's name (nn, greedy, la2x5, oracle)."""
        return self.policy.name

    # ------------------------------------------------------------------ one decision
    def observe(self, world: World, *, noise: float = 0.0, seed: int | None = None) -> np.ndarray:
        """The world's rope as a cloud (n, 3) under the library's observation model."""
        return self.featurizer.observe(world, noise=noise, seed=seed)

    def scan(self, cloud_n3: np.ndarray) -> ScanResult:
        """Register the cloud against every demo of the library (cached for recent states)."""
        return self.featurizer.scan(cloud_n3)

    def scores(self, cloud_n3: np.ndarray) -> np.ndarray:
        """Every demo's score (Q, else -registration cost); -inf where registration failed."""
        scan = self.scan(cloud_n3)
        if self.model is None:
            return demo_scores(scan, None, None)
        return demo_scores(scan, self.featurizer.features_from_scan(scan, cloud_n3), self.model)

    def rank(
        self, cloud_n3: np.ndarray, top_k: int | None = None, *, transfer: bool = True
    ) -> list[Candidate]:
        """The ``top_k`` best demos for the cloud, best first, failed registrations never
        offered; with ``transfer``, each with its gripper path warped onto the scene."""
        k = self.top_k if top_k is None else top_k
        if k < 1:
            raise InvalidInputError(f"top_k must be >= 1, got {k}")
        scan = self.scan(cloud_n3)
        scores_a = self.scores(cloud_n3)
        cost_a = np.asarray(scan.nn_cost_a, dtype=float)
        out = []
        for r, a in enumerate(rank_order(scores_a)[:k]):
            plan = self.transferer.plan(cloud_n3, int(a)) if transfer else None
            out.append(
                Candidate(
                    rank=r + 1,
                    demo_index=int(a),
                    demo_key=self.library.keys[a],
                    score=float(scores_a[a]),
                    q=None if self.model is None else float(scores_a[a]),
                    nn_cost=float(cost_a[a]),
                    trajectory=None if plan is None else plan.trajectory,
                    failure=None if plan is None else plan.failure,
                )
            )
        return out

    def context(
        self,
        world: World,
        cloud_n3: np.ndarray,
        *,
        step_index: int = 0,
        memo: OutcomeMemo | None = None,
    ) -> StepContext:
        """What the policy sees at step ``step_index`` of an episode of this task."""
        return StepContext(
            world,
            cloud_n3,
            self.scan(cloud_n3),
            self.featurizer,
            self.transferer,
            step_index,
            self.task.step_limit - step_index,
            memo,
        )

    def choose(
        self,
        world: World | None,
        *,
        cloud_n3: np.ndarray | None = None,
        step_index: int = 0,
        memo: OutcomeMemo | None = None,
    ) -> Decision:
        """The policy's choice in the world's current state, with its scores and reasons
        (``info``: the lookahead's search tree and backed-up values, the oracle's stages).
        The world is left as it was found. Without a world (a robot's cloud alone) only the
        policies that do not simulate can choose, from ``cloud_n3``."""
        if world is None:
            if self.config.simulates:
                raise InvalidInputError(
                    f"policy {self.name!r} simulates candidate executions: it needs a world "
                    "(a rope-state estimate), not a cloud alone"
                )
            if cloud_n3 is None:
                raise InvalidInputError("a decision without a world needs the cloud (cloud_n3)")
            world = NO_WORLD
        cloud = self.observe(world) if cloud_n3 is None else cloud_n3
        return self.policy.choose(self.context(world, cloud, step_index=step_index, memo=memo))

    def act(
        self,
        world: World,
        action: int | str,
        *,
        cloud_n3: np.ndarray | None = None,
        frames: FrameRecorder | None = None,
    ) -> ActionOutcome:
        """Transfer demo ``action`` (index or key) onto the world's rope and execute it; the
        outcome says the stage reached and whether the task's goal (the knot) is reached."""
        index = self.library.index_of(action) if isinstance(action, str) else int(action)
        if not 0 <= index < len(self.library):
            raise InvalidInputError(f"action {action} is not a demo of this library")
        cloud = self.observe(world) if cloud_n3 is None else cloud_n3
        return apply_demo(world, self.transferer, cloud, index, frames, task=self.task)

    def run_episode(
        self,
        world: World,
        start: RopeTask | np.ndarray,
        *,
        seed: int | None = None,
        noise: float = 0.0,
        max_steps: int | None = None,
        memo: OutcomeMemo | None = None,
        model_world: World | None = None,
        estimator: StateEstimator | None = None,
    ) -> EpisodeRecord:
        """Reset the world to ``start`` and act until the goal or the task's step limit.

        ``model_world``/``estimator``: the agent's own model of the world, apart from the world
        that executes (`core.experiments.episode.run_episode`); default: the world itself."""
        from knotlab.core.experiments.episode import run_episode

        if isinstance(start, RopeTask):
            task_id, nodes = start.task_id, start.start_nodes_k3
            seed = start.seed if seed is None else seed
        else:
            task_id, nodes = "rope", np.asarray(start, dtype=float)
        return run_episode(
            self,
            world,
            nodes,
            task_id=task_id,
            seed=0 if seed is None else seed,
            max_steps=self.task.step_limit if max_steps is None else max_steps,
            observe_noise=noise,
            memo=memo,
            model_world=model_world,
            estimator=estimator,
        )

    def warm_up(self, world: World, start_nodes_k3: Sequence[Sequence[float]]) -> None:
        """Compile the numba kernels of both registration presets before anything is timed."""
        world.reset(np.asarray(start_nodes_k3, dtype=float))
        cloud = self.observe(world)
        self.featurizer.features(cloud)
        self.transferer.plan(cloud, 0)
