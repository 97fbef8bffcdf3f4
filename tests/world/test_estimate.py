"""State estimates and the model world: exact adoption, placement at rest, the honest tracker."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.world.estimate import (
    EstimatorKind,
    PerfectEstimator,
    RopeEstimate,
    TrackingEstimator,
    make_estimator,
    node_error_mm,
    place_estimate,
    same_crossings,
)
from knotlab.core.world.rope import perturb_rope, rope_length, straight_rope
from knotlab.core.world.sim import RopeParams, RopeWorld
from knotlab.core.world.trajectory import GripperTrajectory, down_rotation


@pytest.fixture(scope="module")
def start() -> np.ndarray:
    """An uncrossed rope at rest."""
    with RopeWorld() as world:
        world.reset(perturb_rope(straight_rope(41, 1.0, 0.01), 0.05, n_centres=5, seed=3))
        world.settle(0.5)
        return world.rope_nodes()


def _drag(at: np.ndarray) -> GripperTrajectory:
    """The left gripper lowers onto the rope at ``at``, drags it 15 cm in y and lets go."""
    x, y = float(at[0]), float(at[1])
    left = np.array([(x, y, 0.06), (x, y, 0.01), (x, y + 0.15, 0.05), (x, y + 0.15, 0.05)])
    right = np.array([(0.6, 0.0, 0.2)] * 4)
    closed = np.array([[False, True, True, False], [False] * 4])
    rot = np.broadcast_to(down_rotation(), (2, 4, 3, 3))
    return GripperTrajectory(np.arange(4) * 0.5, np.stack([left, right]), rot, closed)


def test_a_perfect_estimate_is_adopted_exactly_by_a_model_of_the_same_physics(start):
    with RopeWorld() as world, RopeWorld() as model:
        world.reset(start)
        world.execute(_drag(start[2]), settle_time=0.2)  # a moving rope: velocities matter
        estimate = PerfectEstimator().estimate(world)
        assert estimate.is_exact and estimate.error_mm == 0.0
        place_estimate(model, estimate)
        assert model.snapshot().equals(world.snapshot())
        a, b = world.execute(_drag(start[2])), model.execute(_drag(start[2]))
        assert a == b and np.array_equal(world.rope_nodes(), model.rope_nodes())


def test_a_heavier_model_takes_the_poses_and_velocities_under_its_own_physics(start):
    heavy = replace(RopeParams(), mass=0.4)
    with RopeWorld() as world, RopeWorld(heavy) as model:
        world.reset(start)
        place_estimate(model, PerfectEstimator().estimate(world))
        state = model.snapshot()
        assert state.params == heavy
        assert np.array_equal(state.positions_l3, world.snapshot().positions_l3)


def test_a_model_of_another_rope_is_placed_at_rest_along_the_nodes(start):
    thin = replace(RopeParams(), radius=0.008)
    with RopeWorld() as world, RopeWorld(thin) as model:
        world.reset(start)
        place_estimate(model, PerfectEstimator().estimate(world))
        assert node_error_mm(model.rope_nodes()[:, :2], world.rope_nodes()[:, :2]) < 1.0
        # A noisy chain (uneven, too long) still becomes a rope of the model's links.
        rng = np.random.default_rng(0)
        noisy = world.rope_nodes() + rng.normal(0.0, 0.004, size=(41, 3))
        place_estimate(model, RopeEstimate(noisy))
        assert rope_length(model.rope_nodes()) == pytest.approx(1.0, rel=0.01)


def test_the_tracker_starts_close_is_seeded_and_carries_its_estimate_through_a_step(start):
    with RopeWorld() as world, RopeWorld() as model:
        runs = []
        for _ in range(2):
            world.reset(start)
            tracker = TrackingEstimator()
            tracker.start(world, 7, model)
            first = tracker.estimate(world)
            assert first.state is None and 0.0 < first.error_mm < 10.0
            world.execute(_drag(start[2]))
            tracker.executed(_drag(start[2]), model)
            runs.append((first.nodes_k3, tracker.estimate(world)))
        assert np.array_equal(runs[0][0], runs[1][0])  # same seed, same estimates
        assert np.array_equal(runs[0][1].nodes_k3, runs[1][1].nodes_k3)
        moved = runs[0][1]
        assert first.crossings_right and moved.crossings_right  # a drag crosses nothing
        assert moved.error_mm < 15.0  # it followed the drag (the left end moved 15 cm)
        assert node_error_mm(runs[0][0], world.rope_nodes()) > 30.0


def test_the_tracker_refuses_to_estimate_before_it_starts_and_bad_settings():
    with RopeWorld() as world, pytest.raises(InvalidInputError, match="not started"):
        TrackingEstimator().estimate(world)
    with pytest.raises(InvalidInputError, match="drift"):
        TrackingEstimator(drift=-1.0)
    with pytest.raises(InvalidInputError, match="perfect, tracker"):
        make_estimator("psychic")
    assert make_estimator(EstimatorKind.TRACKER).kind is EstimatorKind.TRACKER


def test_a_long_estimate_with_a_steep_peak_still_becomes_a_rope_of_the_models_links():
    # An estimate a quarter too long (noise adds length) with one node 8 cm up: scaling xy
    # alone to the rope's length leaves the peak's steep segments longer than a link may
    # stretch (32 mm against 25), which the simulator refuses.
    # A zigzag as well: respacing it evenly cuts its corners (a tenth of its length or more).
    peaked = straight_rope(41, 1.0, 0.01)
    peaked[:, 0] *= 1.25
    peaked[20, 2] = 0.08
    zigzag = peaked.copy()
    zigzag[::2, 1] += 0.012
    with RopeWorld() as model:
        for nodes in (peaked, zigzag):
            place_estimate(model, RopeEstimate(nodes))
            placed = model.rope_nodes()
            assert rope_length(placed) == pytest.approx(1.0, rel=0.01)
            assert np.linalg.norm(np.diff(placed, axis=0), axis=1).max() < 1.25 * 0.025


def _loops(k: int = 81, second_over: bool = True) -> np.ndarray:
    """A rope along x with two loops (a prolate cycloid's two arches): each crossing's later pass
    goes over, or at the second loop under with ``second_over=False``."""
    t = np.linspace(-0.5, 1.5, k)  # the arches cross at t = -+0.29 and 1 -+ 0.29
    x = t - 0.3 * np.sin(2 * np.pi * t)
    y = -0.3 * np.cos(2 * np.pi * t)
    z = np.full(k, 0.01)
    z[np.abs(t - 0.29) < 0.06] = 0.02
    z[np.abs(t - 1.29) < 0.06] = 0.02 if second_over else 0.0
    return np.stack([x, y, z], axis=1)


def test_same_crossings_reads_over_and_under_from_either_end_and_counts_crossings():
    loops = _loops()
    from knotlab.core.world.knot import gauss_code

    assert gauss_code(loops)[1] == 2  # the helper's rope crosses itself twice
    assert same_crossings(loops, loops[::-1].copy())  # read from the other end
    assert same_crossings(loops + np.array([0.3, -0.2, 0.0]), loops)  # moved
    assert not same_crossings(loops, _loops(second_over=False))  # one crossing the other way
    one_loop = loops[:41]
    assert gauss_code(one_loop)[1] == 1 and not same_crossings(loops, one_loop)
    straight = straight_rope(41, 1.0, 0.01)
    assert not same_crossings(one_loop, straight)
    assert same_crossings(straight, straight[::-1].copy())
