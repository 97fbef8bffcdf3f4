"""Task-independent features phi(s, a) of every demo a at once, from one library scan.

Shape suffixes: a = demos (actions), d = features, p = points, k = demo steps (phases).

For each demo a, from the bidirectional registration of its cloud onto the scene:
- c1 = map_fwd + map_bwd (mapping error), c2 = bend_f, c3 = bend_g (docs/reference/learning.md);
- q(c1, c2, c3): the six products c_i c_j, i <= j (the original's quadratic features);
- grasp_dist: metres from each warped grasp point of demo a to the nearest scene point (max over
  the segment's grasps). The original's version of this feature was 0 by a loader bug
  (docs/reference/original_system.md, "Known bugs", 7); a transferred grasp that lands off the
  rope is a misgrasp, so this predicts one;
- phase_k: soft "which demo step does this state look like" (k = 0, 1, 2): the softmax over demos
  of the relative NN cost, summed per demo step. The same for every action (the landmark idea of
  docs/reference/learning.md, with the library's own clouds as landmarks): it only enters the
  Bellman and dead-end rows, where it lets the value depend on progress;
- phase_match: phase_k at demo a's own step k(a): does this demo belong to the state's phase?;
- landmark[l]: with landmarks (core/selection/landmarks.py: labelled and dead-end training
  states, as the original's 50 + 20), the same softmax over the landmarks' registration costs
  to the state. The same for every action, so it only shapes the value: it lets V(s') tell a
  state the expert went on from apart from a dead end, which is what lookahead compares;
- e_a: a one-hot of the demo (a per-demo prior: some demos transfer far better than others).
- with ``rank_features``: where demo a stands among the state's demos by
  registration cost: nn_rel = cost(a) / min cost - 1 (scale-free), one-hots for ranks 0, 1 and 2,
  and min(rank, 10) / 10. The expert was shown candidates in cost order and took the first that
  worked (docs/reference/original_system.md, "Labelling protocol"), so the rank is what the
  labels are made of; a linear Q on the raw costs plus 148 per-demo offsets cannot express
  "the cheapest one" within a state.
Not repeated from the original (docs/reference/original_system.md, "Known bugs"): positive-exponent
gram features, indicators that are never cleared, c2-only "bend" features labelled c2 + c3.

Demos whose registration failed get the worst finite value of each cost column (their Q is
masked by the policies anyway, via ``scan.ok_a``), so training rows stay finite.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from knotlab.core.arrays import cloud_digest
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.registration import SCAN, LibraryRegistrar, RegistrationParams, ScanResult
from knotlab.core.registration.params import COST_NAMES
from knotlab.core.selection.compatibility import check_feature_names, check_observation
from knotlab.core.selection.feature_spec import FeatureSpec
from knotlab.core.selection.landmarks import Landmarks
from knotlab.core.selection.qmodel import QModel
from knotlab.core.world.observation import ObservationModel, observe
from knotlab.core.world.protocol import World

FEATURE_SET = "knotlab-features-v1"
_COSTS = ("c1_map", "c2_bend_f", "c3_bend_g")
_QUAD = tuple(f"{_COSTS[i]}*{_COSTS[j]}" for i in range(3) for j in range(i, 3))
_RANK = ("nn_rel", "nn_rank_0", "nn_rank_1", "nn_rank_2", "nn_rank_10")
_RANK_INDICATOR = (False, True, True, True, False)
_RANK_CAP = 10  # ranks beyond this all look alike (the oracle tries 10 candidates)
_MAX_MARGIN_POINTS = 40  # trajectory points per demo used for margins (subsampled evenly)
SUMMARY_COSTS = COST_NAMES[:4]  # map_fwd, map_bwd, bend_f, bend_g: the features' costs
_MEMO_STATES = 32  # scans (and their features) a featurizer keeps, by the cloud's exact bytes


@dataclass(frozen=True)
class ScanSummary:
    """What phi(s, .) needs of a state's library scan, without the warps: per demo a the four
    cost columns the features use (SUMMARY_COSTS, +inf where not ok), whether it registered, and
    the raw grasp distance (m; NaN where not ok). Small enough to keep for every start state,
    and model-independent."""

    costs_ac: np.ndarray
    ok_a: np.ndarray
    grasp_a: np.ndarray

    @property
    def nn_cost_a(self) -> np.ndarray:
        """map_fwd + map_bwd + bend_f + bend_g per demo (as ScanResult's)."""
        return self.costs_ac.sum(axis=1)

    def cost(self, name: str) -> np.ndarray:
        """One cost column by name (one of SUMMARY_COSTS)."""
        return self.costs_ac[:, SUMMARY_COSTS.index(name)]


class _ScanMemo:
    """The last few states' scans and features, by cloud digest (thread-safe LRU).

    A search scans every child it values, and the episode then scans the child it moved to
    again; the app re-ranks a state it has shown. The scan is a pure function of the cloud
    (for a fixed library and preset), so a hit returns the very same arrays.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[str, list] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def get(self, key: str) -> list | None:
        with self._lock:
            item = self._items.get(key)
            if item is None:
                self.misses += 1
                return None
            self.hits += 1
            self._items.move_to_end(key)
            return item

    def __contains__(self, key: str) -> bool:
        with self._lock:  # not counted: a look, not a use
            return key in self._items

    def put(self, key: str, scan: ScanResult) -> list:
        with self._lock:
            item = self._items.setdefault(key, [scan, None])
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)
            return item


def _grasp_points(library: DemoLibrary) -> list[np.ndarray]:
    """Positions where each demo closes a gripper (its grasps), world frame of the demo."""
    out = []
    for seg in library:
        closed = seg.trajectory.closed_gt
        prev = np.zeros_like(closed)
        prev[:, 1:] = closed[:, :-1]
        g_idx, t_idx = np.nonzero(closed & ~prev)
        pts = seg.trajectory.positions_gt3[g_idx, t_idx]
        out.append(pts if len(pts) else seg.trajectory.positions_gt3[:, 0])
    return out


def _margin_points(library: DemoLibrary) -> list[np.ndarray]:
    """Points traced by each demo's working grippers (those that ever close), subsampled."""
    out = []
    for seg in library:
        traj = seg.trajectory
        active = traj.active_grippers() or (0, 1)
        pts = np.concatenate([traj.positions_gt3[g] for g in active])
        if len(pts) > _MAX_MARGIN_POINTS:
            pts = pts[np.linspace(0, len(pts) - 1, _MAX_MARGIN_POINTS).round().astype(int)]
        out.append(pts)
    return out


class LibraryFeaturizer:
    """Computes phi(s, .) for a library; holds the registrar and everything per-library."""

    def __init__(
        self,
        library: DemoLibrary,
        *,
        registrar: LibraryRegistrar | None = None,
        params: RegistrationParams = SCAN,
        phase_temperature: float = 0.25,
        landmarks: Landmarks | None = None,
        rank_features: bool = False,
    ) -> None:
        if not phase_temperature > 0:
            raise InvalidInputError(f"phase_temperature must be > 0, got {phase_temperature}")
        self.library = library
        self.params = params
        self.registrar = registrar or LibraryRegistrar(params)
        self.phase_temperature = float(phase_temperature)
        self.library_hash = library.content_hash()
        self.observation = ObservationModel.of_library_metadata(library.metadata)
        self._clouds = library.clouds()
        self._memo = _ScanMemo(_MEMO_STATES)
        self._steps_a = library.step_indices()
        self._phase_steps = tuple(int(k) for k in np.unique(self._steps_a))
        self._phase_onehot_ak = (self._steps_a[:, None] == np.array(self._phase_steps)).astype(
            float
        )
        self._grasp_pts = _grasp_points(library)
        self._margin_pts = _margin_points(library)
        self.landmarks = landmarks if landmarks is not None and len(landmarks) else None
        self.landmark_hash = self.landmarks.content_hash() if self.landmarks is not None else None
        self.rank_features = bool(rank_features)
        self._landmark_key = f"landmarks-{self.landmark_hash}" if self.landmark_hash else None
        landmark_names = (
            [f"landmark[{i}:{kind}]" for i, kind in enumerate(self.landmarks.kinds)]
            if self.landmarks is not None
            else []
        )
        n = len(library)
        names = (
            list(_COSTS)
            + list(_QUAD)
            + ["grasp_dist_m"]
            + [f"phase_{k}" for k in self._phase_steps]
            + ["phase_match"]
            + list(_RANK if self.rank_features else ())
            + landmark_names
            + [f"demo[{key}]" for key in library.keys]
        )
        # Columns left unstandardised by the learner: the one-hots (demo, rank), and the landmark
        # softmax weights (in [0, 1]; most are ~0 for most states, so standardising them would
        # blow a rarely-near landmark up to hundreds and leave the QP badly conditioned).
        indicator = [False] * (len(names) - n - len(landmark_names)) + [True] * (
            len(landmark_names) + n
        )
        if self.rank_features:
            first = names.index(_RANK[0])
            for offset, is_onehot in enumerate(_RANK_INDICATOR):
                indicator[first + offset] = is_onehot
        self._spec = FeatureSpec(
            FEATURE_SET,
            self.library_hash,
            library.keys,
            tuple(names),
            tuple(indicator),
            self._phase_steps,
            self.phase_temperature,
            self.landmark_hash,
            self.observation.value,
            self.rank_features,
            task=library.task,  # written only when not the overhand knot: old hashes hold
        )

    @classmethod
    def for_model(
        cls,
        library: DemoLibrary,
        model: QModel,
        *,
        registrar: LibraryRegistrar | None = None,
        params: RegistrationParams = SCAN,
    ) -> LibraryFeaturizer:
        """The featurizer a QModel was trained with (its landmarks), checked against its spec."""
        featurizer = cls(
            library,
            registrar=registrar,
            params=params,
            phase_temperature=model.feature_spec.phase_temperature,
            landmarks=getattr(model, "landmarks", None),
            rank_features=model.feature_spec.rank_features,
        )
        check_observation(model, featurizer.observation)
        check_feature_names(model, featurizer.feature_spec.names)
        return featurizer

    @property
    def n_actions(self) -> int:
        """Number of demos (actions)."""
        return len(self.library)

    @property
    def feature_spec(self) -> FeatureSpec:
        """The spec of the columns :meth:`features` returns."""
        return self._spec

    def spec(self) -> dict:
        """JSON-able spec (StateFeaturizer protocol)."""
        return self._spec.to_dict()

    def action_index(self, demo_key: str) -> int:
        """Row of ``demo_key`` in phi_ad."""
        return self.library.index_of(demo_key)

    def observe(self, world: World, *, noise: float = 0.0, seed: int | None = None) -> np.ndarray:
        """The scene cloud of ``world``'s rope under this library's observation model."""
        return observe(world, self.observation, noise=noise, seed=seed)

    def scan(self, cloud_n3: np.ndarray, timings: dict | None = None) -> ScanResult:
        """Register the cloud against every demo (cached demo side; a state seen lately is
        not scanned again, unless ``timings`` asks for a measured scan)."""
        if timings is not None:
            return self._scan_now(cloud_n3, timings)
        key = cloud_digest(cloud_n3)
        item = self._memo.get(key)
        if item is None:
            item = self._memo.put(key, self._scan_now(cloud_n3, None))
        return item[0]

    def _scan_now(self, cloud_n3: np.ndarray, timings: dict | None) -> ScanResult:
        return self.registrar.scan(
            cloud_n3, self._clouds, key=self.library_hash, params=self.params, timings=timings
        )

    def scanned_lately(self, cloud_n3: np.ndarray) -> bool:
        """Whether this exact cloud's scan is among the recent states kept (a scan of it is then
        free)."""
        return cloud_digest(cloud_n3) in self._memo

    def scan_demos(self, cloud_n3: np.ndarray, demos: Sequence[int]) -> ScanResult:
        """Register the cloud against these demos only (rows in the order given): each row is
        the full scan's registration of that demo, bit for bit (a demo's registration does not
        depend on the others). Their demo side is cut from the library's prepared one (no
        demo factorised again); a registrar of its own scans it, so the library's side stays
        in the shared one's cache."""
        library = self.registrar.prepare(self._clouds, key=self.library_hash, params=self.params)
        side = library.rows([int(a) for a in demos])
        return LibraryRegistrar(self.params).scan_side(cloud_n3, side, params=self.params)

    @property
    def memo_stats(self) -> tuple[int, int]:
        """(hits, misses) of the recent-states memo."""
        return self._memo.hits, self._memo.misses

    def warped_points(self, scan: ScanResult, points: list[np.ndarray]) -> list[np.ndarray]:
        """Each demo's points pushed through its own f_a (NaN rows where registration failed)."""
        out = []
        for a, pts in enumerate(points):
            if scan.ok_a[a]:
                out.append(scan.f_points(a, pts))
            else:
                out.append(np.full_like(pts, np.nan))
        return out

    def features(self, cloud_n3: np.ndarray) -> tuple[np.ndarray, ScanResult]:
        """phi_ad for every demo, and the scan it came from."""
        scan = self.scan(cloud_n3)
        return self.features_from_scan(scan, cloud_n3), scan

    def features_from_scan(self, scan: ScanResult, cloud_n3: np.ndarray) -> np.ndarray:
        """phi_ad from an existing scan of ``cloud_n3`` (kept with the scan when it is the
        memo's own; treat it as read-only)."""
        item = self._memo.get(cloud_digest(cloud_n3))
        if item is not None and item[0] is scan:
            if item[1] is None:
                phi = self._features_now(scan, cloud_n3)
                phi.flags.writeable = False
                item[1] = phi
            return item[1]
        return self._features_now(scan, cloud_n3)

    def _features_now(self, scan: ScanResult, cloud_n3: np.ndarray) -> np.ndarray:
        return self.features_from_summary(self.summarise(scan, cloud_n3), cloud_n3)

    def summarise(self, scan: ScanResult, cloud_n3: np.ndarray) -> ScanSummary:
        """What the features need of a scan (costs, which registered, grasp distances): small,
        model-independent, and enough to rebuild phi_ad bit for bit."""
        ok = np.asarray(scan.ok_a, dtype=bool)
        tree = cKDTree(np.asarray(cloud_n3, dtype=float))
        grasp = np.full(self.n_actions, np.nan)
        usable = np.flatnonzero(ok)
        if usable.size:
            # one query for every demo's warped points: each point's distance is its own
            warped = self.warped_points(scan, self._grasp_pts)
            dist = tree.query(np.concatenate([warped[a] for a in usable]))[0]
            ends = np.cumsum([len(warped[a]) for a in usable])
            for a, part in zip(usable, np.split(dist, ends[:-1]), strict=True):
                grasp[a] = part.max()
        costs = np.column_stack([scan.cost(name) for name in SUMMARY_COSTS])
        return ScanSummary(costs.astype(float), ok, grasp)

    def features_from_summary(
        self,
        summary: ScanSummary,
        cloud_n3: np.ndarray,
        landmark_weights: np.ndarray | None = None,
    ) -> np.ndarray:
        """phi_ad from a state's scan summary (and its landmark weights, if this featurizer has
        landmarks: computed here unless given)."""
        ok = summary.ok_a
        if not ok.any():
            raise InvalidInputError("registration failed for every demo: no features")
        if len(ok) != self.n_actions:
            raise InvalidInputError(
                f"a scan summary of {len(ok)} demos does not fit this library of {self.n_actions}"
            )
        c = np.column_stack(
            [
                summary.cost("map_fwd") + summary.cost("map_bwd"),
                summary.cost("bend_f"),
                summary.cost("bend_g"),
            ]
        )
        c = _fill_failed(c, ok)
        quad = np.column_stack([c[:, i] * c[:, j] for i in range(3) for j in range(i, 3)])
        grasp = _fill_failed(summary.grasp_a[:, None], ok)
        phase_k = self.phase(summary)
        phase_ak = np.broadcast_to(phase_k, (self.n_actions, phase_k.size))
        match = self._phase_onehot_ak @ phase_k
        columns = [c, quad, grasp, phase_ak, match]
        if self.rank_features:
            columns.append(rank_columns(summary.nn_cost_a))
        if self.landmarks is not None:
            near_l = (
                self.landmark_weights(cloud_n3) if landmark_weights is None else landmark_weights
            )
            columns.append(np.broadcast_to(near_l, (self.n_actions, near_l.size)))
        return np.column_stack([*columns, np.eye(self.n_actions)])

    def landmark_weights(self, cloud_n3: np.ndarray) -> np.ndarray:
        """Softmax over landmarks of the relative registration cost (all zero if none register)."""
        assert self.landmarks is not None
        scan = self.registrar.scan(
            cloud_n3,
            list(self.landmarks.clouds),
            key=self._landmark_key,
            params=self.params,
        )
        cost = np.asarray(scan.nn_cost_a, dtype=float)
        if not np.any(np.isfinite(cost)):
            return np.zeros(len(cost))
        return _soft_nearest(cost, self.phase_temperature)

    def phase(self, scan: ScanResult | ScanSummary) -> np.ndarray:
        """Soft phase: softmax over demos of -(cost/min cost - 1)/T, summed per demo step."""
        return _soft_nearest(scan.nn_cost_a, self.phase_temperature) @ self._phase_onehot_ak

    def margins(self, scan: ScanResult, expert_action: int) -> np.ndarray:
        """m(a*, a): mean closest-point distance (m) from a's warped trajectory to a*'s."""
        warped = self.warped_points(scan, self._margin_pts)
        ref = warped[expert_action]
        if not np.all(np.isfinite(ref)):
            raise InvalidInputError(
                f"registration of the expert's demo {self.library.keys[expert_action]} failed"
            )
        tree = cKDTree(ref)
        m = np.empty(self.n_actions)
        finite_max = 0.0
        for a, pts in enumerate(warped):
            if np.all(np.isfinite(pts)):
                m[a] = tree.query(pts)[0].mean()
                finite_max = max(finite_max, m[a])
            else:
                m[a] = np.nan
        m[~np.isfinite(m)] = finite_max  # a failed demo is as wrong as the most different one
        m[expert_action] = 0.0
        return m


def rank_columns(cost_a: np.ndarray) -> np.ndarray:
    """(A, 5): cost / min cost - 1, one-hots of cost ranks 0, 1, 2, and min(rank, 10) / 10.

    Failed demos (non-finite cost) rank last and get the worst finite relative cost; ties keep
    the lower demo index first (stable), as `rank_order` does.
    """
    cost = np.asarray(cost_a, dtype=float)
    finite = np.isfinite(cost)
    if not finite.any():
        raise InvalidInputError("registration failed for every demo: no rank features")
    rank = np.empty(cost.size)
    rank[np.argsort(np.where(finite, cost, np.inf), kind="stable")] = np.arange(cost.size)
    c_min = max(cost[finite].min(), 1e-12)
    rel = np.where(finite, cost / c_min - 1.0, np.nan)
    rel[~finite] = rel[finite].max()
    return np.column_stack(
        [rel, rank == 0, rank == 1, rank == 2, np.minimum(rank, _RANK_CAP) / _RANK_CAP]
    ).astype(float)


def _soft_nearest(cost_a: np.ndarray, temperature: float) -> np.ndarray:
    """Softmax of -(cost / min cost - 1) / T over finite costs (scale-free; failed -> 0)."""
    cost = np.asarray(cost_a, dtype=float)
    finite = np.isfinite(cost)
    rel = np.full_like(cost, np.inf)
    c_min = max(cost[finite].min(), 1e-12)
    rel[finite] = cost[finite] / c_min - 1.0
    logits = -rel / temperature
    w = np.exp(logits - logits[finite].max())
    w[~finite] = 0.0
    return w / w.sum()


def _fill_failed(values_ac: np.ndarray, ok_a: np.ndarray) -> np.ndarray:
    """Replace rows of failed demos (and any non-finite value) by the column's worst value."""
    out = np.array(values_ac, dtype=float)
    good = ok_a[:, None] & np.isfinite(out)
    worst = np.where(good, out, -np.inf).max(axis=0)
    worst[~np.isfinite(worst)] = 0.0
    return np.where(good, out, worst)
