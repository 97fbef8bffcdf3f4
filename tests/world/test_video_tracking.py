"""The video tracker: one frame's correction, the camera cloud of a chain, a real execution."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.world.estimate import (
    EstimatorKind,
    VideoTracker,
    make_estimator,
    shape_error_mm,
)
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.observation import surface_cloud, surface_cloud_of_nodes
from knotlab.core.world.rope import perturb_rope, straight_rope
from knotlab.core.world.sim import RopeWorld
from knotlab.core.world.trajectory import GripperTrajectory, down_rotation
from knotlab.core.world.video_tracking import DEAD_BAND, follow_frame

LINK = 0.025
RADIUS = 0.01


def _line(n: int = 41) -> np.ndarray:
    """A straight chain of ``n`` nodes along x, lying on the table."""
    nodes = np.zeros((n, 3))
    nodes[:, 0] = np.arange(n) * LINK
    nodes[:, 2] = RADIUS
    return nodes


def test_a_frame_pulls_the_chain_across_to_the_visible_rope_and_leaves_hidden_nodes_alone():
    truth = _line()
    cloud = surface_cloud_of_nodes(truth, RADIUS, max_points=1000, voxel=0.01)
    shifted = truth + np.array([0.0, 0.01, 0.0])
    pulled = follow_frame(shifted, cloud, radius=RADIUS, reach=0.02)
    # Back onto the rope, short of the camera's noise (a move shrinks by the dead band) ...
    assert np.abs(pulled[5:-5, 1] - truth[5:-5, 1]).max() < DEAD_BAND + 0.002
    # ... and a node already within the dead band of what the camera sees is left alone.
    close = truth + np.array([0.0, 0.003, 0.0])
    assert np.array_equal(follow_frame(close, cloud, radius=RADIUS, reach=0.02), close)
    # Only across the chain: a cloud does not say which part of the rope a node is.
    assert np.allclose(pulled[:, 0], shifted[:, 0])
    # Half the rope out of view (hidden): those nodes keep their place exactly.
    seen = cloud[cloud[:, 0] < 0.45]
    half = follow_frame(shifted, seen, radius=RADIUS, reach=0.02)
    assert np.array_equal(half[25:], shifted[25:])
    # Heights are the model's: a frame moves nodes in the table's plane only.
    assert np.array_equal(pulled[:, 2], shifted[:, 2])


def test_the_cloud_of_a_node_chain_is_the_cloud_of_the_rope_it_came_from():
    with RopeWorld() as world:
        world.reset(perturb_rope(straight_rope(41, 1.0, 0.01), 0.05, n_centres=5, seed=3))
        world.settle(0.5)
        nodes = world.rope_nodes()
        from_state = surface_cloud(world.snapshot(), max_points=1000, voxel=0.01)
        from_nodes = surface_cloud_of_nodes(nodes, world.params.radius, max_points=1000, voxel=0.01)
    from scipy.spatial import cKDTree

    # On the rope's surface: one radius from its centreline (sampled every 0.5 mm)...
    t = np.linspace(0.0, 1.0, 50)[:, None, None]
    axis = (nodes[:-1] + t * (nodes[1:] - nodes[:-1])).reshape(-1, 3)
    # (a point sampled on one link's cylinder lies a little closer to the next link's axis
    # inside a bend).
    off = cKDTree(axis).query(from_nodes)[0]
    assert np.all((off > 0.009) & (off < 0.0101)) and np.median(off) == pytest.approx(
        0.01, abs=1e-4
    )
    # ... and covering the same surface, to the 1 cm voxel (a capsule's roll about its axis
    # moves its samples around the rope, and so which voxels keep one).
    assert cKDTree(from_nodes).query(from_state)[0].max() < 0.011
    assert cKDTree(from_state).query(from_nodes)[0].max() < 0.011


def _lift_and_lay(at: np.ndarray) -> GripperTrajectory:
    """The left gripper grasps the rope at ``at``, lifts it 20 cm, carries it 25 cm in y, lays it
    down and lets go."""
    x, y = float(at[0]), float(at[1])
    left = np.array(
        [
            (x, y, 0.06),
            (x, y, 0.01),
            (x, y, 0.2),
            (x, y + 0.25, 0.2),
            (x, y + 0.25, 0.02),
            (x, y + 0.25, 0.06),
        ]
    )
    right = np.array([(0.6, 0.0, 0.2)] * 6)
    closed = np.array([[False, True, True, True, True, False], [False] * 6])
    rot = np.broadcast_to(down_rotation(), (2, 6, 3, 3))
    return GripperTrajectory(np.arange(6) * 0.5, np.stack([left, right]), rot, closed)


@pytest.fixture(scope="module")
def lifted() -> tuple[np.ndarray, GripperTrajectory, object, np.ndarray]:
    """A start rope, a lift-and-lay of its end, the execution's frames and the rope after."""
    with RopeWorld() as world:
        world.reset(perturb_rope(straight_rope(41, 1.0, 0.01), 0.05, n_centres=5, seed=3))
        world.settle(0.5)
        start = world.rope_nodes()
        world.reset(start)  # as the test below starts it
        traj = _lift_and_lay(start[3])
        result = world.execute(traj, frames=FrameRecorder(1 / 30))
        assert result.ok
        return start, traj, result.frames, world.rope_nodes()


def test_the_video_tracker_follows_a_lifted_rope_closer_in_shape_than_once_a_step(lifted):
    start, traj, frames, after = lifted
    shape = {}
    with RopeWorld() as world, RopeWorld() as model:
        for kind in (EstimatorKind.TRACKER, EstimatorKind.VIDEO):
            runs = []
            for _ in range(2):
                world.reset(start)
                tracker = make_estimator(kind)
                tracker.start(world, 11, model)
                tracker.estimate(world)
                world.execute(traj)
                tracker.executed(traj, model, frames if kind is EstimatorKind.VIDEO else None)
                runs.append(tracker.estimate(world))
            assert np.array_equal(runs[0].nodes_k3, runs[1].nodes_k3)  # same seed, same estimate
            assert np.array_equal(world.rope_nodes(), after)  # the world was only sensed
            assert runs[0].shape_mm == pytest.approx(shape_error_mm(runs[0].nodes_k3, after))
            shape[kind] = runs[0].shape_mm
    # The end was carried 25 cm through the air: the start chain is far off in shape. Followed
    # frame by frame, the estimate lies closer to the rope than one predicted through the whole
    # motion and corrected once (measured 5.6 against 7.9 mm; 3 seeds all ways round).
    assert shape_error_mm(start, after) > 30.0
    assert shape[EstimatorKind.VIDEO] < shape[EstimatorKind.TRACKER] - 1.0
    assert shape[EstimatorKind.VIDEO] < 7.0


def test_the_video_tracker_falls_back_to_one_frame_without_frames_and_refuses_bad_fps(lifted):
    start, traj, _, _ = lifted
    with RopeWorld() as world, RopeWorld() as model:
        world.reset(start)
        tracker = VideoTracker()
        assert tracker.frame_dt == pytest.approx(1 / 30)
        tracker.start(world, 3, model)
        tracker.estimate(world)
        world.execute(traj)
        tracker.executed(traj, model, None)  # e.g. a stored outcome made without frames
        assert np.isfinite(tracker.estimate(world).error_mm)
    with pytest.raises(InvalidInputError, match="fps"):
        VideoTracker(fps=0.0)
