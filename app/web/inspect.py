"""Inspect one state for a researcher: what NN, greedy and lookahead choose and why. No viser.

The inspector has its own simulator, so a lookahead search (which simulates) never disturbs a
labelling episode; the search runs on a background thread and reports its expansions.
Shape suffixes: a = demos, n = cloud points, k = rope nodes.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from knotlab.app.web.resources import AppResources, RankingModel
from knotlab.app.web.sim_pool import PoolRunner, SimPool
from knotlab.core.execution.compare import ModelAndWorld
from knotlab.core.registration import ScanResult
from knotlab.core.registration.planner import DemoTransferer, TransferPlan
from knotlab.core.selection.decision import LevelDecision
from knotlab.core.selection.explain import Contribution, PolicyChoices, feature_contributions
from knotlab.core.selection.ranking import RankedDemo, rank_demos
from knotlab.core.world.sim import RopeWorld

SHOWN = 10  # candidates listed (by the model's ranking)


class _CountingTransferer(DemoTransferer):
    """A transferer that reports every plan (one per simulated expansion) for a progress bar."""

    def __init__(self, base: DemoTransferer, on_plan: Callable[[], None]) -> None:
        super().__init__(base.library, base.params)
        self._on_plan = on_plan

    def plan(self, cloud_n3: np.ndarray, demo_index: int) -> TransferPlan:
        """Plan as usual, then count it."""
        out = super().plan(cloud_n3, demo_index)
        self._on_plan()
        return out


@dataclass(frozen=True, eq=False)
class RegistrationView:
    """One candidate's registration onto the scene: clouds, correspondences and costs."""

    demo_key: str
    demo_cloud_n3: np.ndarray  # the demo's own rope, where it was recorded
    warped_n3: np.ndarray  # f(demo cloud): the demo rope mapped onto the scene
    pairs_n23: np.ndarray  # warped point -> its nearest scene point, for lines
    costs: dict[str, float]


@dataclass
class InspectView:
    """A state's decision, explained."""

    label: str
    nodes_k3: np.ndarray
    cloud_n3: np.ndarray
    ranking: list[RankedDemo]
    nn_rank_of: dict[int, int]  # demo index -> its rank by registration cost (1 = nearest)
    choices: PolicyChoices
    model: str
    contributions: dict[int, list[Contribution]] = field(default_factory=dict)
    search_progress: float = 0.0  # 0..1 while the lookahead searches
    search_error: str | None = None
    search_expansions: int = 0  # simulated so far
    search_cancelled: bool = False
    search_levels: int = 0  # levels the running search plans (its depth)


class SearchCancelledError(Exception):
    """Raised inside a lookahead search at its next expansion once it was cancelled."""


class Inspector:
    """Explains decisions on any rope state, with its own simulator."""

    def __init__(self, resources: AppResources, pool: SimPool | None = None) -> None:
        self.res = resources
        self.pool = pool  # lookahead levels simulated in parallel there, when given
        self._world: RopeWorld | None = None  # made on first use: most tabs never inspect
        self._lock = threading.Lock()  # the simulator (a search holds it while it runs)
        self._state_lock = threading.Lock()  # the loaded state: view, scan, ranking
        self.view: InspectView | None = None
        self._scan: ScanResult | None = None
        self._ranking: RankingModel | None = None
        self._search: threading.Thread | None = None
        self._cancel = threading.Event()  # the running search's; set: stop at its next expansion
        self._keep = False  # with a cancel: keep the choice of the levels finished so far
        self._generation = 0  # a newer load makes an older search's result stale
        self._other_worlds: dict = {}  # physics -> RopeWorld: worlds unlike the model, to compare

    @property
    def world(self) -> RopeWorld:
        """The inspector's simulator, made the first time it is needed (use under ``_lock``):
        building it (~10-25 ms) no longer delays a new tab."""
        if self._world is None:
            self._world = RopeWorld()
        return self._world

    def load(self, nodes_k3: np.ndarray, label: str) -> InspectView:
        """Observe, scan and rank this rope; NN and greedy choices and every Q's contributions."""
        ranking = self.res.current
        with self._lock:
            self._generation += 1
            self.world.reset(np.asarray(nodes_k3, dtype=float))
            nodes = self.world.rope_nodes()
            fz = ranking.featurizer
            cloud = fz.observe(self.world)
            phi, scan = fz.features(cloud) if ranking.model is not None else (None, fz.scan(cloud))
            keys = self.res.library.keys
            ranked = rank_demos(scan, phi, ranking.model, keys, SHOWN)
            by_cost = rank_demos(scan, None, None, keys)
            nn_rank = {r.demo_index: r.rank for r in by_cost}
            contributions = {}
            if ranking.model is not None and phi is not None:
                names = tuple(fz.feature_spec.names)
                contributions = {  # every demo's: an expert's pick may be far down the list
                    r.demo_index: feature_contributions(ranking.model, phi[r.demo_index], names)
                    for r in rank_demos(scan, phi, ranking.model, keys)
                }
            choices = PolicyChoices(
                nn=by_cost[0].demo_index if by_cost else 0,
                greedy=ranked[0].demo_index if ranking.model is not None and ranked else None,
            )
            view = InspectView(
                label, nodes, cloud, ranked, nn_rank, choices, ranking.label, contributions
            )
            with self._state_lock:
                self._scan, self._ranking, self._phi, self.view = scan, ranking, phi, view
            return view

    def load_path(
        self, start_nodes_k3: np.ndarray, path: tuple[str, ...] | list[str], label: str
    ) -> InspectView:
        """The state reached from a start by transferring the demos of ``path`` in turn."""
        with self._lock:
            self.world.reset(np.asarray(start_nodes_k3, dtype=float))
            agent = self.res.current.agent
            for key in path:
                agent.act(self.world, key)
            nodes = self.world.rope_nodes()
        return self.load(nodes, label)

    def start_lookahead(
        self, depth: int, width: int, on_update: Callable[[InspectView], None]
    ) -> bool:
        """Run lookahead(depth, width) on the loaded state in the background; False if busy."""
        with self._lock:
            view, ranking = self.view, self._ranking
            if view is None or ranking is None or ranking.model is None:
                return False
            if self._search is not None and self._search.is_alive():
                return False
            generation, phi = self._generation, self._phi
            snapshot = self.world.snapshot()
        budget = max(1, depth * width)
        cancel = self._cancel = threading.Event()
        self._keep = False
        view.search_progress, view.search_expansions = 0.0, 0
        view.search_cancelled, view.search_error = False, None
        view.search_levels = depth
        choices = view.choices
        choices.lookahead, choices.lookahead_info, choices.lookahead_levels = None, {}, (0, depth)

        def counted() -> None:
            """One expansion done: report it, or stop the search here if it was cancelled."""
            if cancel.is_set():
                raise SearchCancelledError
            view.search_expansions += 1
            view.search_progress = min(0.99, view.search_expansions / budget)
            on_update(view)

        def on_level(report: LevelDecision) -> None:
            """A level finished: its choice is shown at once (and may be kept)."""
            if generation != self._generation:
                return
            view.search_levels = report.levels
            choices.lookahead = report.decision.action
            info = report.decision.info
            choices.lookahead_info = {**info, "wall_s": info.get("search_s", 0.0)}
            choices.lookahead_levels = (report.level, report.levels)
            on_update(view)

        def search() -> None:
            name = f"la{depth}x{width}"
            runner = None
            if self.pool is not None:  # a level's expansions side by side in the workers
                runner = PoolRunner(self.pool, counted)
                agent = ranking.agent.with_policy(name, runner=runner)
                transferer = agent.transferer
            else:
                agent = ranking.agent.with_policy(name)
                transferer = _CountingTransferer(agent.transferer, counted)
            t0 = time.perf_counter()
            try:
                with self._lock:
                    self.world.restore(snapshot)
                    try:
                        ctx = agent.context(self.world, view.cloud_n3)
                        ctx.transferer = transferer
                        ctx._phi_ad = phi
                        ctx.on_level = on_level
                        decision = agent.policy.choose(ctx)
                    finally:
                        self.world.restore(snapshot)
                if generation != self._generation:
                    return
                choices.lookahead = decision.action
                choices.lookahead_name = agent.name
                choices.lookahead_info = {**decision.info, "wall_s": time.perf_counter() - t0}
                choices.lookahead_levels = None
            except SearchCancelledError:
                finished = choices.lookahead_levels
                if self._keep and finished is not None and finished[0] > 0:
                    choices.lookahead_name = agent.name  # the levels so far decide
                    choices.lookahead_info["wall_s"] = time.perf_counter() - t0
                else:  # nothing of it is kept
                    view.search_cancelled = True
                    choices.lookahead, choices.lookahead_info = None, {}
                    choices.lookahead_levels = None
            except Exception as exc:  # shown in the panel; the inspector stays usable
                view.search_error = f"{type(exc).__name__}: {exc}"
                choices.lookahead, choices.lookahead_levels = None, None
            finally:
                if runner is not None:  # expansions queued for later levels: nobody wants them
                    runner.drop_prefetched()
            view.search_progress = 1.0
            on_update(view)

        self._search = threading.Thread(target=search, name="inspect-lookahead", daemon=True)
        self._search.start()
        return True

    def model_and_world(self, demo_index: int, world_setting: str) -> ModelAndWorld:
        """Candidate ``demo_index`` on the loaded rope, simulated in the agent's model (this
        inspector's nominal world) and in the world of ``world_setting`` (a physics setting
        name; a combined one drawn for this state's label), from the same rope at rest."""
        from knotlab.core.execution.compare import outcome_in_model_and_world
        from knotlab.core.world.mismatch import parse_setting

        physics = parse_setting(world_setting).params_for(self.view.label if self.view else "")
        with self._lock:
            view = self.view
            if view is None:
                raise ValueError("inspect a state first")
            if physics not in self._other_worlds:
                self._other_worlds[physics] = RopeWorld(physics.rope, physics.gripper)
            agent = self.res.current.agent
            out = outcome_in_model_and_world(
                view.nodes_k3,
                view.cloud_n3,
                demo_index,
                agent.transferer,
                self.world,
                self._other_worlds[physics],
                task=agent.task,
            )
            self.world.reset(view.nodes_k3)  # the loaded state again, for a search
            return out

    def cancel_lookahead(self, *, keep: bool = False) -> bool:
        """Stop the running search at its next expansion; False when none runs. With ``keep``
        the choice of the levels finished so far stays (none finished: nothing stays)."""
        if self._search is None or not self._search.is_alive():
            return False
        self._keep = keep
        self._cancel.set()
        return True

    def registration(self, demo_index: int) -> RegistrationView:
        """Demo cloud, its warp onto the scene, nearest-point pairs and the cost parts."""
        with self._state_lock:  # not the simulator's lock: a running search holds that one
            assert self._scan is not None and self.view is not None
            scan, cloud = self._scan, self.view.cloud_n3
        demo = self.res.library[demo_index]
        warped = scan.f(demo_index).evaluate(demo.pre_cloud_n3)
        _, nearest = cKDTree(cloud).query(warped)
        pairs = np.stack([warped, cloud[nearest]], axis=1)
        costs = scan.costs(demo_index)
        return RegistrationView(
            demo.key,
            demo.pre_cloud_n3,
            warped,
            pairs,
            {k: float(v) for k, v in vars(costs).items()},
        )

    def close(self) -> None:
        """Stop a search and free the simulator."""
        self._cancel.set()
        with self._lock:
            if self._world is not None:
                self._world.close()
            for world in self._other_worlds.values():
                world.close()
