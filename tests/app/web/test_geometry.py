"""The app's pure geometry: the rope tube is a closed surface; ray picking finds the polyline."""

from __future__ import annotations

import numpy as np
import trimesh

from knotlab.app.web.geometry import (
    camera_rotation,
    frame_points,
    hull_points,
    pick_candidate,
    pick_marker,
    pick_polyline,
    project,
    ray_polyline_distance,
    tube_faces,
    tube_vertices,
)


def test_the_tube_is_watertight_with_the_rope_volume():
    nodes = np.c_[np.linspace(0, 1, 41), 0.1 * np.sin(np.linspace(0, 6, 41)), np.full(41, 0.01)]
    mesh = trimesh.Trimesh(tube_vertices(nodes, 0.01), tube_faces(41, 12), process=False)
    assert mesh.is_watertight and mesh.volume > 0
    length = np.linalg.norm(np.diff(nodes, axis=0), axis=1).sum()
    # A 12-gon's area is 0.955 of the circle's.
    assert abs(mesh.volume / (np.pi * 0.01**2 * length) - 0.955) < 0.03


def test_ray_distance_to_a_segment():
    line = np.array([[0.0, 0, 0], [1, 0, 0]])
    down = np.array([0.0, 0, -1])
    assert ray_polyline_distance([0.5, 0, 1], down, line) < 1e-12
    assert abs(ray_polyline_distance([0.5, 0.2, 1], down, line) - 0.2) < 1e-12
    assert abs(ray_polyline_distance([2, 0, 1], down, line) - 1.0) < 1e-12  # beyond the end
    assert abs(ray_polyline_distance([0.5, 0, -1], down, line) - 1.0) < 1e-12  # behind the ray


def test_pick_returns_the_closest_polyline_within_reach():
    lines = {
        1: [np.array([[0.0, 0, 0], [1, 0, 0]])],
        2: [np.array([[0.0, 0.1, 0], [1, 0.1, 0]])],
    }
    down = np.array([0.0, 0, -1])
    assert pick_polyline(np.array([0.5, 0.08, 1]), down, lines) == 2
    assert pick_polyline(np.array([0.5, 0.01, 1]), down, lines) == 1
    assert pick_polyline(np.array([0.5, 0.5, 1]), down, lines) is None


def test_a_click_on_a_marker_beats_a_path_passing_in_front_of_it():
    down = np.array([0.0, 0, -1])
    # Candidate 3's path runs 2 cm above candidate 2's grasp marker: the marker is what the
    # labeller clicked, whatever the path's distance to the ray.
    markers = {2: [(np.array([0.5, 0.0, 0.0]), 0.011)], 3: [(np.array([0.9, 0.0, 0.0]), 0.016)]}
    lines = {
        2: [np.array([[0.5, 0.0, 0.0], [0.5, 0.3, 0.0]])],
        3: [np.array([[0.0, 0.0, 0.02], [1.0, 0.0, 0.02]])],
    }
    assert pick_polyline(np.array([0.5, 0.0, 1]), down, lines) in (2, 3)
    assert pick_candidate(np.array([0.5, 0.0, 1]), down, markers, lines) == 2
    # Two markers on one ray: the one in front (nearer the camera) wins.
    stacked = {1: [(np.array([0.2, 0.0, 0.0]), 0.011)], 4: [(np.array([0.2, 0.0, 0.05]), 0.011)]}
    assert pick_marker(np.array([0.2, 0.0, 1]), down, stacked) == 4
    assert pick_marker(np.array([0.2, 0.0, -1]), -down, stacked) == 1
    # A small marker inside a larger (selected) one: a click on the small one's centre takes it.
    nested = {3: [(np.array([0.54, 0.0, 0.0]), 0.016)], 2: [(np.array([0.532, 0.0, 0.0]), 0.011)]}
    assert pick_marker(np.array([0.532, 0.0, 1]), down, nested) == 2
    assert pick_marker(np.array([0.545, 0.0, 1]), down, nested) == 3
    # Beside every marker: the nearest path within reach, else nothing.
    assert pick_candidate(np.array([0.7, 0.01, 1]), down, markers, lines) == 3
    assert pick_candidate(np.array([0.7, 0.5, 1]), down, markers, lines) is None


def test_framing_puts_every_point_inside_the_box_and_touches_its_edge():
    rng = np.random.default_rng(0)
    points = rng.uniform([-0.3, -0.2, 0.0], [0.4, 0.3, 0.3], (500, 3))
    forward, up, fov, size = np.array([0.0, 0.75, -0.65]), np.array([0.0, 0, 1]), 1.3, (1280, 760)
    box = (24.0, 24.0, 857.0, 736.0)  # left of an 400 px side panel
    position, look_at = frame_points(points, forward, up, fov, size, box)
    rotation = camera_rotation(look_at - position, up)
    assert np.allclose(rotation[:, 2], forward / np.linalg.norm(forward))  # the view kept
    uv = project(points, rotation, position, fov, size)
    assert (uv[:, 0] >= box[0] - 1e-6).all() and (uv[:, 0] <= box[2] + 1e-6).all()
    assert (uv[:, 1] >= box[1] - 1e-6).all() and (uv[:, 1] <= box[3] + 1e-6).all()
    # As close as they fit: some point is on the box's edge.
    gap = np.min(np.abs(np.concatenate([uv - box[:2], uv - box[2:]])))
    assert gap < 1e-3


def test_framing_a_clouds_hull_corners_frames_the_whole_cloud():
    # An episode's every frame of rope: framing the hull's corners alone keeps every point in
    # the box (the constraints are linear), with the same camera as framing them all.
    rng = np.random.default_rng(1)
    cloud = rng.uniform([-0.3, -0.2, 0.0], [0.4, 0.3, 0.2], (4000, 3))
    corners = hull_points(cloud)
    assert 4 <= len(corners) < 200
    forward, up, fov, size = np.array([0.0, 0.75, -0.65]), np.array([0.0, 0, 1]), 1.3, (1280, 760)
    box = (24.0, 24.0, 857.0, 736.0)
    position, look_at = frame_points(corners, forward, up, fov, size, box)
    uv = project(cloud, camera_rotation(look_at - position, up), position, fov, size)
    assert (uv >= np.array(box[:2]) - 1e-6).all() and (uv <= np.array(box[2:]) + 1e-6).all()
    full, _ = frame_points(cloud, forward, up, fov, size, box)
    assert np.allclose(position, full, atol=1e-9)
    # A flat cloud (a rope lying on the table) has no hull: all its points are kept.
    flat = np.c_[cloud[:, :2], np.zeros(len(cloud))]
    assert len(hull_points(flat)) == len(flat)
