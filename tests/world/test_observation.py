"""Observation models: what registration sees of the rope (centreline, camera cloud, tracked)."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.world.observation import (
    DEFAULT_OBSERVATION,
    ObservationModel,
    centreline_points,
    observe,
)
from knotlab.core.world.rope import straight_rope
from knotlab.core.world.sim import RopeWorld


@pytest.fixture(scope="module")
def bent_world():
    nodes = straight_rope()
    nodes[:, 1] += 0.05 * np.sin(np.linspace(0, 2 * np.pi, len(nodes)))
    with RopeWorld() as world:
        world.reset(nodes)
        yield world


def test_centreline_interleaves_nodes_and_midpoints() -> None:
    nodes = np.arange(12, dtype=float).reshape(4, 3)
    pts = centreline_points(nodes)
    assert pts.shape == (7, 3)
    np.testing.assert_array_equal(pts[0::2], nodes)
    np.testing.assert_allclose(pts[1], 0.5 * (nodes[0] + nodes[1]))


@pytest.mark.parametrize("bad", [np.zeros((1, 3)), np.zeros((5, 2)), np.zeros(3)])
def test_centreline_rejects_bad_shapes(bad: np.ndarray) -> None:
    with pytest.raises(InvalidInputError, match="rope nodes(: need at least| must have shape)"):
        centreline_points(bad)


def test_default_model_is_the_centreline(bent_world) -> None:
    assert DEFAULT_OBSERVATION is ObservationModel.CENTRELINE
    cloud = observe(bent_world)
    np.testing.assert_array_equal(cloud, centreline_points(bent_world.rope_nodes()))
    assert cloud.shape == (2 * len(bent_world.rope_nodes()) - 1, 3)


def test_cloud_model_is_the_camera_surface_cloud(bent_world) -> None:
    np.testing.assert_array_equal(observe(bent_world, ObservationModel.CLOUD), bent_world.observe())


@pytest.mark.parametrize("model", list(ObservationModel))
def test_noise_is_seeded(bent_world, model: ObservationModel) -> None:
    a = observe(bent_world, model, noise=0.004, seed=3)
    b = observe(bent_world, model, noise=0.004, seed=3)
    c = observe(bent_world, model, noise=0.004, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_tracked_centreline_is_close_to_the_truth_but_not_equal(bent_world) -> None:
    truth = centreline_points(bent_world.rope_nodes())
    tracked = observe(bent_world, ObservationModel.TRACKED)
    err = np.linalg.norm(tracked - truth, axis=1)
    assert tracked.shape == truth.shape
    assert 0.0 < np.median(err) < 0.01  # camera-like errors, millimetres, not centimetres
    # Without a seed the estimate is still a function of the rope state (lookahead relies on it).
    np.testing.assert_array_equal(tracked, observe(bent_world, ObservationModel.TRACKED))


def test_unknown_model_names_the_choices() -> None:
    with pytest.raises(InvalidInputError, match="centreline, cloud, tracked"):
        ObservationModel.parse("kinect")


def test_libraries_from_before_the_models_were_named_read_as_cloud() -> None:
    assert ObservationModel.of_library_metadata({}) is ObservationModel.CLOUD
    meta = {"observation_model": "centreline"}
    assert ObservationModel.of_library_metadata(meta) is ObservationModel.CENTRELINE
