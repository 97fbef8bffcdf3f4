"""What an agent knows of the rope's state, and the model world it simulates that state in.

A policy that simulates (lookahead, the oracle) never touches the world that executes: it
simulates in a *model world* (a `RopeWorld` with the agent's own physics) placed in the state a
`StateEstimator` reports. A `RopeEstimate` carries:

- ``nodes_k3``: the rope's estimated node chain (K, 3), always;
- ``state``: the full dynamic state (every link's pose and velocity), only from the `perfect`
  estimator, i.e. an oracle state estimate; the model adopts it exactly where its rope has the
  same links (count, length, radius), and otherwise places its own rope at rest along the nodes;
- ``error_mm``: the mean distance of the estimated nodes to the true ones, ``shape_mm``: the
  mean distance from each centreline to the other (a chain slid along the rope has a node error
  but no shape error), and ``crossings_right``: whether the estimate's crossings, read as the
  knot test reads them (over/under, in order along the rope), are the true rope's (a knot
  simulated on a chain with other crossings is another knot, however small its shape error).
  A simulation knows the truth: all three are reported, never used to decide.

Estimators:

- ``perfect``: the world's own state (what every result before model error was measured with);
- ``tracker``: a rope tracker that is not told the truth. Its prior for a step is its own
  previous estimate carried through the trajectory the robot executed, simulated in the agent's
  model (the prediction step of a physics-based tracker). Where that prior fits the camera cloud
  badly (the rope moved off the prediction), it is first registered onto the cloud (the same
  TPS-RPM as trajectory transfer) and carried by the fitted warp; it is then pulled to the
  visible surface points (`tracked_centreline`: a 1 cm voxel cloud with sensor noise; a point
  hidden under a crossing keeps its place plus noise), and a seeded drift (a random walk of the
  whole estimate in xy, as a slowly drifting camera calibration) is added. The first estimate
  starts from the true chain: the start ropes lie uncrossed, which every tracker initialises on.
  It sees one frame after each executed step, not the motion in between.
- ``video``: the same tracker following the camera during the motion too, at ``VIDEO_FPS``
  frames a second (a rope tracker runs at the camera's rate): at each frame its chain moves by
  the agent's model's predicted motion since the last frame (the executed trajectory simulated
  from its previous estimate), then its nodes are pulled to that frame's visible rope
  (`follow_frame`: hidden nodes stay where the prediction put them). The decision's estimate is
  the ``tracker``'s update from the chain it followed to the end of the motion.
- ``tracker_ends``, ``video_ends``: the same two trackers that also read the rope's two visible
  ends at each decision's update and slide their chain along the rope to them where both ends
  read a slide the same way and the slide leaves the chain's crossings as they were
  (`rope_ends.slide_to_ends`): the pull moves a chain across the rope only, so without this a
  chain that slid along the rope in a prediction stays slid.
- ``tracker_marked``, ``video_marked``: the same two trackers on a *marked* rope (a mark every
  5 cm along it, each one told apart from the others, `rope_marks`): at each decision's update
  the camera also reads the marks not hidden under another strand, and the chain moves so that
  its point at each seen mark's place along the rope lies at the mark, short of the camera's
  noise, after the pull (straight between neighbouring marks in view, the tail beyond the last
  one slid along the chain: `rope_marks.move_to_marks`). A changed sensor, not a better
  algorithm: what knowing which part of the rope lies where is worth.

Same seed, same estimates: a tracker draws its noise and drift from one Generator per episode
(a marked rope's mark noise from a second one, seeded by the same seed, so that the cloud's
draws are those of the same tracker on an unmarked rope).
Shape suffixes: k = rope nodes, n = cloud points.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import StrEnum
from typing import TYPE_CHECKING, Protocol

import numpy as np

from knotlab.core.errors import InvalidInputError, parse_choice
from knotlab.core.world.frames import ExecutionFrames, FrameRecorder
from knotlab.core.world.knot import canonical_code, gauss_code
from knotlab.core.world.observation import (
    TRACKER_NOISE,
    TRACKER_RADIUS,
    centreline_points,
    surface_cloud_of_nodes,
    tracked_centreline,
)
from knotlab.core.world.protocol import World
from knotlab.core.world.rope import resample_by_arc_length, rope_length, scale_xy_to_length
from knotlab.core.world.rope_ends import slide_to_ends
from knotlab.core.world.rope_marks import MarkReading, move_to_marks, observe_marks
from knotlab.core.world.video_tracking import follow_frame

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.sim import SimSnapshot
    from knotlab.core.world.trajectory import GripperTrajectory

# The tracker's camera: a 1 cm voxel cloud of the visible surface (as the `tracked` observation).
_TRACKER_VOXEL = 0.01
_TRACKER_POINTS = 1000
# The prior is registered onto the cloud first only where it fits this badly (symmetric mean
# nearest distance in xy, m; the true chain measures about 0.013 against its own cloud, one
# shifted 2 cm sideways 0.029): a rope that moved off its prediction further than a pull reaches.
REGISTER_ABOVE = 0.02
TRACKER_DRIFT = 0.001  # m per step, standard deviation of the drift's xy random walk
_MAX_HEIGHT_RADII = 8.0  # an estimated node higher than this many rope radii is placed there
# The video tracker's camera rate: a gripper at its 0.5 m/s cap moves 1.7 cm a frame, inside
# one pull's 2 cm reach.
VIDEO_FPS = 30.0


class EstimatorKind(StrEnum):
    """How the agent learns the rope's state."""

    PERFECT = "perfect"
    TRACKER = "tracker"
    VIDEO = "video"
    TRACKER_ENDS = "tracker_ends"
    VIDEO_ENDS = "video_ends"
    TRACKER_MARKED = "tracker_marked"
    VIDEO_MARKED = "video_marked"

    @property
    def anchors_ends(self) -> bool:
        """Whether this tracker slides its chain along the rope to the cloud's visible ends."""
        return self in (EstimatorKind.TRACKER_ENDS, EstimatorKind.VIDEO_ENDS)

    @property
    def reads_marks(self) -> bool:
        """Whether this tracker follows a marked rope: it reads the marks in view at each
        decision and moves its chain to them."""
        return self in (EstimatorKind.TRACKER_MARKED, EstimatorKind.VIDEO_MARKED)

    @property
    def follows_video(self) -> bool:
        """Whether this tracker follows the camera during each motion (else once a step)."""
        return self in (EstimatorKind.VIDEO, EstimatorKind.VIDEO_ENDS, EstimatorKind.VIDEO_MARKED)

    @classmethod
    def parse(cls, value: str | EstimatorKind) -> EstimatorKind:
        """The estimator named ``value``; a one-line error naming the choices otherwise."""
        return parse_choice(cls, value, "state estimator")


@dataclass(frozen=True, eq=False)
class RopeEstimate:
    """The agent's estimate of the rope: nodes always, the full state only when perfect."""

    nodes_k3: np.ndarray
    state: SimSnapshot | None = None
    error_mm: float = 0.0  # mean distance of the estimated nodes to the true ones
    shape_mm: float = 0.0  # mean distance from each centreline to the other
    crossings_right: bool | None = None  # the true rope's crossing code (None: not measured)

    @property
    def is_exact(self) -> bool:
        """Whether this is the world's own full state."""
        return self.state is not None


def node_error_mm(estimate_k3: np.ndarray, truth_k3: np.ndarray) -> float:
    """Mean distance (mm) between two node chains, the estimate resampled to the truth's count."""
    truth = np.asarray(truth_k3, dtype=float)
    est = np.asarray(estimate_k3, dtype=float)
    if est.shape != truth.shape:
        est = resample_by_arc_length(est, truth.shape[0])
    return float(np.linalg.norm(est - truth, axis=1).mean() * 1000.0)


def shape_error_mm(estimate_k3: np.ndarray, truth_k3: np.ndarray) -> float:
    """Mean distance (mm) from each centreline's points to the other centreline, both ways."""
    from scipy.spatial import cKDTree

    est, truth = centreline_points(estimate_k3), centreline_points(truth_k3)
    there = cKDTree(truth).query(est)[0].mean()
    back = cKDTree(est).query(truth)[0].mean()
    return float(500.0 * (there + back))


def same_crossings(estimate_k3: np.ndarray, truth_k3: np.ndarray) -> bool:
    """Whether two chains cross themselves alike: the same over/under crossing code, read from
    either end (the code the knot test's stages are made of)."""
    return canonical_code(gauss_code(estimate_k3)[0]) == canonical_code(gauss_code(truth_k3)[0])


def place_estimate(model_world: World, estimate: RopeEstimate) -> None:
    """Put the model world's rope in the estimated state.

    The full state is adopted exactly when the model's rope has the same links (count, length,
    radius): the poses and velocities carry over, under the model's own mass, friction and
    damping. Otherwise the model's rope is placed at rest along the estimated nodes, evenly
    respaced, and scaled in xy to its own length where the estimate's differs (an estimate's
    noise adds length; a model whose rope is of another length altogether measures it at the
    start of the episode: `mismatch.measured_model`).
    """
    params = model_world.params
    state = estimate.state
    if state is not None and (state.params.n_links, state.params.length, state.params.radius) == (
        params.n_links,
        params.length,
        params.radius,
    ):
        model_world.restore(state if state.params == params else replace(state, params=params))
        return
    # Heights within what a rope on a table can have (a knot stacks a few diameters): a warped
    # estimate may put a node under the table or in the air, and only xy is scaled below.
    nodes = np.array(estimate.nodes_k3, dtype=float)
    nodes[:, 2] = np.clip(nodes[:, 2], params.radius, _MAX_HEIGHT_RADII * params.radius)
    # Evenly spaced first: an estimate's noise makes uneven segments that no rope of equal
    # links could lie along.
    nodes = resample_by_arc_length(nodes, params.n_links + 1)
    if abs(rope_length(nodes) - params.length) > 1e-9 * params.length:
        nodes = scale_xy_to_length(nodes, params.length)
        # Scaling xy shortens a steep segment less than a flat one: where that left a segment
        # longer than the simulator lets a link stretch, respace evenly and scale the whole
        # chain about its centroid instead (every segment then a link long; heights change by
        # the same factor). Any other estimate is placed as before.
        if np.linalg.norm(np.diff(nodes, axis=0), axis=1).max() > 1.25 * params.link_length:
            nodes = resample_by_arc_length(nodes, params.n_links + 1)
            centre = nodes.mean(axis=0)
            nodes = centre + (nodes - centre) * (params.length / rope_length(nodes))
    model_world.reset(nodes)


# Each pull's reach, as multiples of the `tracked` observation's 2 cm (see `track_update`).
TRACKER_REACHES = (1.0,)


def _registered(nodes_k3: np.ndarray, surface_n3: np.ndarray) -> np.ndarray:
    """The chain carried by the TPS-RPM registration of its centreline onto the camera cloud."""
    from knotlab.core.registration import EXACT
    from knotlab.core.registration.rpm import register

    # A prior that already fits is kept: the warp would only add the registration's own error
    # (it may slide the chain along the rope, which no cloud can tell).
    if _chamfer_xy(nodes_k3, surface_n3) < REGISTER_ABOVE:
        return nodes_k3
    # Every few points of the 1 cm cloud, evenly along its order: registration takes at most
    # EXACT.max_points (150) a side.
    keep = np.unique(np.linspace(0, len(surface_n3) - 1, EXACT.max_points).round().astype(int))
    reg = register(centreline_points(nodes_k3), surface_n3[keep], EXACT)
    return reg.f(nodes_k3) if reg.ok else nodes_k3


def _chamfer_xy(nodes_k3: np.ndarray, surface_n3: np.ndarray) -> float:
    """Symmetric mean nearest distance in xy between a chain's centreline and a cloud (m)."""
    from scipy.spatial import cKDTree

    chain = centreline_points(nodes_k3)[:, :2]
    cloud = surface_n3[:, :2]
    to_cloud = cKDTree(cloud).query(chain)[0].mean()
    to_chain = cKDTree(chain).query(cloud)[0].mean()
    return float(to_cloud + to_chain)


def track_update(
    prior_nodes_k3: np.ndarray,
    surface_n3: np.ndarray,
    *,
    radius: float,
    rng: np.random.Generator,
    reaches: tuple[float, ...] = TRACKER_REACHES,
    register_first: bool = True,
    anchor_ends: bool = False,
    marks: MarkReading | None = None,
) -> np.ndarray:
    """The tracker's update (K, 3): the prior chain pulled to the visible rope, once per reach.

    Each pass is `tracked_centreline` from the previous pass's chain: a point takes the mean of
    the visible surface points within ``reach`` x 2 cm of it at its height (the other strand at a
    crossing, a diameter away, never pulls; a hidden point keeps its place plus sensor noise),
    then the chain is smoothed; only the part of each move across the chain is kept. One 2 cm
    pass was the best of those tried on training starts (longer or more passes pull a chain
    across to the wrong strand more often than they correct it). ``anchor_ends``: before the
    pull, the chain slides along its own curve to where the cloud's two visible ends say the
    rope begins and ends (`rope_ends.slide_to_ends`; nothing where they disagree or where the
    slide would change the chain's crossings). ``marks``: after the pull, the chain moves to
    the marks in view (`rope_marks.move_to_marks`).
    """
    nodes = np.asarray(prior_nodes_k3, dtype=float)
    if register_first and len(surface_n3) >= 4:
        nodes = _registered(nodes, np.asarray(surface_n3, dtype=float))
    if anchor_ends:
        nodes = slide_to_ends(nodes, surface_n3, radius=radius, reach=TRACKER_RADIUS)[0]
    for reach in reaches:
        pulled = tracked_centreline(nodes, surface_n3, radius=radius, rng=rng, reach=reach)[0::2]
        tangent = np.gradient(nodes, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        move = pulled - nodes
        # Points say where the rope is, not which part of it: a pull along the chain is no
        # evidence (near an end it is only the missing points beyond the end pulling inwards),
        # so only the part across the chain moves it.
        move -= np.einsum("ij,ij->i", move, tangent)[:, None] * tangent
        nodes = nodes + move
    if marks is not None:
        # Last: the pull's mean of nearby surface points shrinks a loop and would move a
        # node off its mark again.
        nodes = move_to_marks(nodes, marks)
    return nodes


class StateEstimator(Protocol):
    """Estimates the rope's state in an episode, step by step."""

    kind: EstimatorKind

    def start(self, world: World, seed: int, model_world: World) -> None:
        """A new episode begins in the world's current (start) state; the agent simulates in
        ``model_world``."""
        ...

    def estimate(self, world: World) -> RopeEstimate:
        """The estimate of the world's current rope (the world is only sensed, never changed)."""
        ...

    @property
    def frame_dt(self) -> float | None:
        """Seconds between the camera frames it follows during a motion (None: it needs none)."""
        ...

    def executed(
        self,
        trajectory: GripperTrajectory | None,
        model_world: World,
        frames: ExecutionFrames | None = None,
    ) -> None:
        """The robot executed ``trajectory`` (None: nothing moved), recorded as ``frames`` when
        `frame_dt` asked for them; carry the estimate along."""
        ...


class PerfectEstimator:
    """The world's own full state: an oracle estimate (every result before model error)."""

    kind = EstimatorKind.PERFECT

    def start(self, world: World, seed: int, model_world: World) -> None:
        """Nothing to initialise."""

    def estimate(self, world: World) -> RopeEstimate:
        """The world's snapshot and nodes, error 0."""
        return RopeEstimate(world.rope_nodes(), world.snapshot(), 0.0)

    @property
    def frame_dt(self) -> float | None:
        """No frames: it reads the world's state."""
        return None

    def executed(
        self,
        trajectory: GripperTrajectory | None,
        model_world: World,
        frames: ExecutionFrames | None = None,
    ) -> None:
        """Nothing to carry: the next estimate reads the world again."""


@dataclass
class TrackingEstimator:
    """A rope tracker that carries its own estimate through each executed trajectory."""

    noise: float = TRACKER_NOISE  # m, per-coordinate camera noise
    drift: float = TRACKER_DRIFT  # m per step, xy random-walk of the whole estimate
    kind: EstimatorKind = EstimatorKind.TRACKER
    anchor_ends: bool = False  # slide the chain to the cloud's visible ends at each update
    read_marks: bool = False  # the rope is marked: move the chain to the marks seen

    def __post_init__(self) -> None:
        for name in ("noise", "drift"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise InvalidInputError(f"tracker {name} must be finite and >= 0, got {value}")
        self._rng = np.random.default_rng(0)
        self._mark_rng = np.random.default_rng(0)
        self._prior: np.ndarray | None = None
        self._radius = 0.0
        self._length = 1.0
        self._last: np.ndarray | None = None
        self._offset = np.zeros(3)

    def start(self, world: World, seed: int, model_world: World) -> None:
        """Initialise on the start rope (uncrossed, at rest): its true chain is the prior."""
        self._rng = np.random.default_rng(seed)
        # The marks' noise from a stream of its own: the cloud's draws stay those of the same
        # tracker on an unmarked rope, so the two pair episode by episode.
        self._mark_rng = np.random.default_rng([seed, 1])
        # The tracker knows the rope as the agent's model does: its radius and length.
        self._radius = model_world.params.radius
        self._length = model_world.params.length
        self._prior = world.rope_nodes()
        self._last = None
        self._offset = np.zeros(3)

    def estimate(self, world: World) -> RopeEstimate:
        """The prior pulled to this step's camera cloud, smoothed, plus the drift so far."""
        if self._prior is None:
            raise InvalidInputError("the tracker was not started on this episode's rope")
        rng = self._rng
        surface = world.observe(max_points=_TRACKER_POINTS, voxel=_TRACKER_VOXEL)
        surface = surface + rng.normal(0.0, self.noise, size=surface.shape)
        marks = None
        if self.read_marks:
            seen = observe_marks(
                world.rope_nodes(), world.params.radius, rng=self._mark_rng, noise=self.noise
            )
            # A mark's centre lies one radius under its top by the rope the agent knows.
            marks = replace(seen, radius=self._radius)
        nodes = track_update(
            self._prior,
            surface,
            radius=self._radius,
            rng=rng,
            anchor_ends=self.anchor_ends,
            marks=marks,
        )
        nodes[:, 2] = np.clip(nodes[:, 2], 0.0, _MAX_HEIGHT_RADII * self._radius)
        self._offset[:2] += rng.normal(0.0, self.drift, size=2)
        nodes = nodes + self._offset
        self._last = nodes
        truth = world.rope_nodes()
        return RopeEstimate(
            nodes,
            None,
            node_error_mm(nodes, truth),
            shape_error_mm(nodes, truth),
            same_crossings(nodes, truth),
        )

    @property
    def frame_dt(self) -> float | None:
        """No frames: it sees the rope once, after each step."""
        return None

    def executed(
        self,
        trajectory: GripperTrajectory | None,
        model_world: World,
        frames: ExecutionFrames | None = None,
    ) -> None:
        """Predict: the last estimate simulated through ``trajectory`` in the agent's model."""
        if self._last is not None and trajectory is not None:
            self._predict(trajectory, model_world, None)

    def _predict(
        self, trajectory: GripperTrajectory, model_world: World, frames: FrameRecorder | None
    ) -> None:
        """The prior: the last estimate placed in the model world and simulated through
        ``trajectory`` (a recorder with a correction follows the camera on the way)."""
        assert self._last is not None
        place_estimate(model_world, RopeEstimate(self._last))
        result = model_world.execute(trajectory, frames=frames)
        predicted = model_world.rope_nodes()
        if result.failure_kind is not None and not np.all(np.isfinite(predicted)):
            predicted = self._last  # the model blew up: keep the last estimate as the prior
        self._prior = predicted


@dataclass
class VideoTracker(TrackingEstimator):
    """The tracker following the camera at ``fps`` through each motion, not once a step."""

    fps: float = VIDEO_FPS
    kind: EstimatorKind = EstimatorKind.VIDEO

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise InvalidInputError(f"tracker fps must be finite and > 0, got {self.fps}")
        self._camera_radius = 0.0

    def start(self, world: World, seed: int, model_world: World) -> None:
        """Initialise on the start rope, as the once-a-step tracker does."""
        super().start(world, seed, model_world)
        # Only to render the frames' camera clouds: the camera sees the rope as thick as it is.
        self._camera_radius = world.params.radius

    @property
    def frame_dt(self) -> float | None:
        """One camera frame every 1 / fps seconds of the motion."""
        return 1.0 / self.fps

    def executed(
        self,
        trajectory: GripperTrajectory | None,
        model_world: World,
        frames: ExecutionFrames | None = None,
    ) -> None:
        """Follow the motion frame by frame: the model simulates the executed trajectory from
        the last estimate, and at each camera frame its rope is pulled to what the camera sees."""
        if self._last is None or trajectory is None:
            return
        if frames is None or len(frames) < 2:
            super().executed(trajectory, model_world)
            return
        rng = self._rng

        def correct(f: int, nodes_k3: np.ndarray) -> np.ndarray | None:
            if f == 0 or f >= len(frames):
                return None
            surface = surface_cloud_of_nodes(
                frames.nodes_fk3[f],
                self._camera_radius,
                max_points=_TRACKER_POINTS,
                voxel=_TRACKER_VOXEL,
            )
            surface = surface + rng.normal(0.0, self.noise, size=surface.shape)
            return follow_frame(nodes_k3, surface, radius=self._radius, reach=TRACKER_RADIUS)

        self._predict(trajectory, model_world, FrameRecorder(1.0 / self.fps, correct))


def make_estimator(kind: EstimatorKind | str) -> StateEstimator:
    """A fresh estimator of ``kind`` (one per episode worker; `start` resets it per episode)."""
    kind = EstimatorKind.parse(kind)
    if kind is EstimatorKind.PERFECT:
        return PerfectEstimator()
    tracker = VideoTracker if kind.follows_video else TrackingEstimator
    return tracker(kind=kind, anchor_ends=kind.anchors_ends, read_marks=kind.reads_marks)
