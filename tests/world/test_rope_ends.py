"""Reading a rope's two visible ends and sliding a tracker's chain along the rope to them."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.experiments.robustness import parse_study_settings
from knotlab.core.world.estimate import (
    EstimatorKind,
    TrackingEstimator,
    VideoTracker,
    make_estimator,
    node_error_mm,
    track_update,
)
from knotlab.core.world.observation import TRACKER_NOISE, TRACKER_RADIUS, surface_cloud_of_nodes
from knotlab.core.world.rope import perturb_rope, resample_by_arc_length, straight_rope
from knotlab.core.world.rope_ends import END_DEAD_BAND, END_OFFSET, read_ends, slide_to_ends

RADIUS = 0.01


def _curve(seed: int) -> np.ndarray:
    """A 1 m rope of 40 links lying on the table in a seeded wavy curve."""
    nodes = perturb_rope(straight_rope(41, 1.0, RADIUS), 0.08, n_centres=5, seed=seed)
    nodes = resample_by_arc_length(nodes, 41)
    nodes[:, 2] = RADIUS
    return nodes


def _cloud(nodes: np.ndarray, seed: int) -> np.ndarray:
    """The tracker camera's 1 cm voxel cloud of the rope, with its sensor noise."""
    cloud = surface_cloud_of_nodes(nodes, RADIUS, max_points=1000, voxel=0.01)
    return cloud + np.random.default_rng(seed).normal(0.0, TRACKER_NOISE, size=cloud.shape)


def _slid(nodes: np.ndarray, by: float) -> np.ndarray:
    """The chain moved along its own curve by ``by`` m (positive: each node takes the place of
    rope further along), the end that runs off continuing straight."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    ext = np.vstack(
        [nodes[0] - (nodes[1] - nodes[0]) * 8, nodes, nodes[-1] + (nodes[-1] - nodes[-2]) * 8]
    )
    step = arc[1] - arc[0]
    ext_arc = np.concatenate([[arc[0] - 8 * step], arc, [arc[-1] + 8 * (arc[-1] - arc[-2])]])
    return np.stack([np.interp(arc + by, ext_arc, ext[:, d]) for d in range(3)], axis=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_chain_on_its_own_rope_reads_no_slide_at_either_end(seed):
    truth = _curve(seed)
    reading = read_ends(truth, _cloud(truth, seed), radius=RADIUS, reach=TRACKER_RADIUS)
    # The offset that places the visible ends: within the voxel's and the noise's spread.
    assert reading.first is not None and abs(reading.first) < 0.006
    assert reading.last is not None and abs(reading.last) < 0.006
    assert reading.applied == 0.0
    assert 0 < END_OFFSET < END_DEAD_BAND


@pytest.mark.parametrize("by", [0.03, -0.03, 0.06])
def test_a_slid_chain_is_slid_back_onto_the_rope_its_ends_say(by):
    truth = _curve(4)
    slid = _slid(truth, by)
    assert node_error_mm(slid, truth) > 25.0
    moved, reading = slide_to_ends(slid, _cloud(truth, 4), radius=RADIUS, reach=TRACKER_RADIUS)
    # The overshooting end reads the slide; the other confirms its direction.
    assert np.sign(reading.first) == np.sign(reading.last) == np.sign(-by)
    assert reading.applied == pytest.approx(-by, abs=0.006)
    assert node_error_mm(moved, truth) < 6.0
    assert moved.shape == truth.shape


def test_ends_that_disagree_or_are_not_seen_move_nothing():
    truth = _curve(5)
    cloud = _cloud(truth, 5)
    # Only the middle of the rope in view (both ends hidden, or a chain too long): the ends
    # read opposite overshoots, which no slide explains.
    arc_x = np.linalg.norm(cloud[:, :2] - truth[20, :2], axis=1)
    middle = cloud[arc_x < 0.25]
    moved, reading = slide_to_ends(truth, middle, radius=RADIUS, reach=TRACKER_RADIUS)
    assert reading.applied == 0.0
    assert np.array_equal(moved, truth)
    # No cloud at all: nothing read.
    empty = read_ends(truth, np.zeros((0, 3)), radius=RADIUS, reach=TRACKER_RADIUS)
    assert (empty.first, empty.last, empty.applied) == (None, None, 0.0)


def test_the_update_anchors_ends_only_when_asked_and_is_otherwise_unchanged():
    truth = _curve(6)
    cloud = _cloud(truth, 6)
    slid = _slid(truth, 0.05)
    plain = track_update(slid, cloud, radius=RADIUS, rng=np.random.default_rng(0))
    default = track_update(
        slid, cloud, radius=RADIUS, rng=np.random.default_rng(0), anchor_ends=False
    )
    assert np.array_equal(plain, default)
    anchored = track_update(
        slid, cloud, radius=RADIUS, rng=np.random.default_rng(0), anchor_ends=True
    )
    # The pull alone cannot see a slide; the ends can.
    assert node_error_mm(plain, truth) > 30.0
    assert node_error_mm(anchored, truth) < 10.0


def test_the_ends_trackers_are_named_estimators_and_study_settings():
    tracker, video = make_estimator("tracker_ends"), make_estimator("video_ends")
    assert isinstance(tracker, TrackingEstimator) and tracker.anchor_ends
    assert isinstance(video, VideoTracker) and video.anchor_ends
    assert (tracker.kind, video.kind) == (EstimatorKind.TRACKER_ENDS, EstimatorKind.VIDEO_ENDS)
    assert not make_estimator("video").anchor_ends and not make_estimator("tracker").anchor_ends
    settings = parse_study_settings("video_ends,tracker_ends,video")
    assert [(s.name, s.world, s.estimator) for s in settings] == [
        ("video_ends", "nominal", EstimatorKind.VIDEO_ENDS),
        ("tracker_ends", "nominal", EstimatorKind.TRACKER_ENDS),
        ("video", "nominal", EstimatorKind.VIDEO),
    ]


def test_a_slide_that_would_change_the_chains_crossings_is_refused(monkeypatch):
    from knotlab.core.world import rope_ends
    from knotlab.core.world.knot import gauss_code

    # A rope whose tail comes back down towards its own first strand and stops 3 cm short.
    t = np.linspace(0.0, 1.0, 400)
    first = np.stack([0.5 * t, 0 * t], axis=1)
    arc = np.stack(
        [0.5 + 0.1 * np.cos(np.pi * (t - 0.5)), 0.1 + 0.1 * np.sin(np.pi * (t - 0.5))], 1
    )
    back = np.stack([0.5 - 0.2 * t, 0.2 + 0 * t], axis=1)
    down = np.stack([0.3 + 0 * t, 0.2 - 0.17 * t], axis=1)
    xy = np.vstack([first, arc[1:], back[1:], down[1:]])
    chain = resample_by_arc_length(np.column_stack([xy, np.full(len(xy), RADIUS)]), 41)
    assert gauss_code(chain)[1] == 0

    def reads(slide):
        # Both ends read ``slide``; the extension is traced as `slide_to_ends` traces it.
        def read(nodes, surface, radius, reach):
            extended = rope_ends._extended(nodes, surface, radius)
            return rope_ends.EndReading(slide, slide, slide), extended

        return read

    nothing_seen = np.zeros((0, 3))  # the extension past the tail then runs straight on
    monkeypatch.setattr(rope_ends, "_read", reads(0.05))
    moved, reading = slide_to_ends(chain, nothing_seen, radius=RADIUS, reach=TRACKER_RADIUS)
    # Five centimetres on would carry the tail across the first strand: refused.
    assert reading.applied == 0.0 and np.array_equal(moved, chain)
    monkeypatch.setattr(rope_ends, "_read", reads(0.01))
    moved, reading = slide_to_ends(chain, nothing_seen, radius=RADIUS, reach=TRACKER_RADIUS)
    assert reading.applied == 0.01 and gauss_code(moved)[1] == 0
    assert np.linalg.norm(moved - chain, axis=1).mean() == pytest.approx(0.01, abs=0.002)
