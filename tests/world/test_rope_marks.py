"""A marked rope: the camera's reading of its marks, and a tracker's chain slid to them."""

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
from knotlab.core.world.observation import TRACKER_NOISE
from knotlab.core.world.rope_marks import (
    MARK_DEAD_BAND,
    MARK_SPACING,
    MarkReading,
    mark_fractions,
    move_to_marks,
    observe_marks,
)
from knotlab.core.world.sim import RopeWorld
from tests.world.test_rope_ends import RADIUS, _cloud, _curve, _slid


def _marks(truth: np.ndarray, seed: int) -> MarkReading:
    return observe_marks(truth, RADIUS, rng=np.random.default_rng(seed), noise=TRACKER_NOISE)


def test_the_marks_lie_every_spacing_along_the_rope_and_each_is_read_on_its_top():
    truth = _curve(0)
    exact = observe_marks(truth, RADIUS, rng=np.random.default_rng(0), noise=0.0)
    length = float(np.linalg.norm(np.diff(truth, axis=0), axis=1).sum())
    assert np.allclose(np.diff(exact.fraction_j) * length, MARK_SPACING, rtol=1e-3)
    assert np.array_equal(exact.fraction_j, mark_fractions(1.0))  # stretch does not move them
    assert len(exact) == round(1.0 / MARK_SPACING)  # a rope lying flat hides none
    # Each reading is the rope's top (one radius above its centre) at its place along it.
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth, axis=0), axis=1))])
    centre = np.stack([np.interp(exact.fraction_j * length, arc, truth[:, d]) for d in range(3)], 1)
    assert np.allclose(exact.top_j3, centre + np.array([0.0, 0.0, RADIUS]))
    # With noise: the same marks, seeded.
    noisy, again = _marks(truth, 3), _marks(truth, 3)
    assert np.array_equal(noisy.top_j3, again.top_j3)
    assert 0.001 < np.abs(noisy.top_j3 - exact.top_j3).mean() < 0.005


def _crossing_rope(cross_x: float) -> np.ndarray:
    """A rope along x at y = 0 to x = 0.6, a U-turn, back along y = 0.1 to ``cross_x``, then
    across the first strand at ``cross_x`` one diameter up (a crossing), down to y = -0.25."""
    first = np.stack([np.linspace(0.0, 0.6, 25), np.zeros(25), np.full(25, RADIUS)], axis=1)
    u = np.linspace(0.0, np.pi, 9)[1:]
    turn = np.stack([0.6 + 0.05 * np.sin(u), 0.05 - 0.05 * np.cos(u), np.full(8, RADIUS)], 1)
    back = np.stack(
        [np.linspace(0.6, cross_x, 12)[1:], np.full(11, 0.1), np.full(11, RADIUS)], axis=1
    )
    over = np.stack(
        [np.full(14, cross_x), np.linspace(0.1, -0.25, 15)[1:], np.full(14, 3 * RADIUS)], axis=1
    )
    return np.vstack([first, turn, back, over])


def _mark_centres(nodes: np.ndarray) -> np.ndarray:
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    place = mark_fractions(float(arc[-1])) * arc[-1]
    return np.stack([np.interp(place, arc, nodes[:, d]) for d in range(3)], axis=1)


def test_a_mark_under_another_strand_is_hidden_and_one_on_top_is_seen():
    # The crossing put over one of the first strand's marks (its place moves with the rope's
    # length, so found by iterating).
    cross_x = 0.35
    for _ in range(20):
        centres = _mark_centres(_crossing_rope(cross_x))
        lower = centres[centres[:, 1] == 0.0]
        cross_x = float(lower[np.argmin(np.abs(lower[:, 0] - cross_x)), 0])
    nodes = _crossing_rope(cross_x)
    centres = _mark_centres(nodes)
    reading = observe_marks(nodes, RADIUS, rng=np.random.default_rng(0), noise=0.0)
    seen = {tuple(np.round(top - [0.0, 0.0, RADIUS], 9)) for top in reading.top_j3}
    hidden = [c for c in centres if tuple(np.round(c, 9)) not in seen]
    # Exactly the first strand's mark under the crossing; the crossing strand's own marks,
    # and the first strand's either side (5 cm away), are all seen.
    assert len(hidden) == 1
    assert hidden[0][0] == pytest.approx(cross_x) and hidden[0][1] == 0.0
    assert len(reading) == len(centres) - 1
    assert (reading.top_j3[:, 2] > 3.5 * RADIUS).sum() == (centres[:, 2] > 2 * RADIUS).sum() > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("by", [-0.03, 0.015, 0.04])
def test_a_chain_slid_along_a_marked_rope_is_moved_back_to_its_marks(seed, by):
    truth = _curve(seed)
    slid = _slid(truth, by)
    back = move_to_marks(slid, _marks(truth, seed))
    assert node_error_mm(slid, truth) > 14.0
    # To within the dead band and the marks' noise (3 mm a coordinate).
    assert node_error_mm(back, truth) < 1000 * MARK_DEAD_BAND + 3.0
    # Without noise: at every mark's place along the rope, the dead band from the mark, on
    # the line from where the chain was.
    exact = observe_marks(truth, RADIUS, rng=np.random.default_rng(0), noise=0.0)
    moved = move_to_marks(slid, exact)
    fraction_k = np.linspace(0.0, 1.0, len(moved))
    at_marks = np.stack([np.interp(exact.fraction_j, fraction_k, moved[:, d]) for d in range(3)], 1)
    assert np.allclose(np.linalg.norm(at_marks - exact.centre_j3, axis=1), MARK_DEAD_BAND)
    # A chain already within the dead band of every mark keeps its points at the marks, and
    # between neighbouring marks runs straight, within a bend's sagitta of where it was (up to
    # 9.6 mm at these curves' tightest bends, about 4 cm in radius).
    near = truth + 0.002
    kept = move_to_marks(near, exact)
    assert np.allclose(kept[1::2], near[1::2], rtol=0.0, atol=1e-12)
    assert 0.0 < np.linalg.norm(kept - near, axis=1).max() < 0.012


def test_between_neighbouring_marks_in_view_the_chain_runs_straight_from_mark_to_mark():
    truth = _curve(2)
    slid = _slid(truth, 0.04)
    marks = _marks(truth, 2)
    moved = move_to_marks(slid, marks)
    fraction_k = np.linspace(0.0, 1.0, len(moved))
    checked = 0
    for j in range(len(marks) - 1):
        if not marks.neighbours(j):
            continue
        a_3, b_3 = (
            np.array([np.interp(f, fraction_k, moved[:, d]) for d in range(3)])
            for f in marks.fraction_j[j : j + 2]
        )
        between = (fraction_k > marks.fraction_j[j]) & (fraction_k < marks.fraction_j[j + 1])
        w_n = (fraction_k[between] - marks.fraction_j[j]) / (
            marks.fraction_j[j + 1] - marks.fraction_j[j]
        )
        on_chord = a_3 + w_n[:, None] * (b_3 - a_3)
        assert np.allclose(moved[between], on_chord, rtol=0.0, atol=1e-12)
        checked += int(between.sum())
    assert checked >= 10  # most of the rope's nodes lie between two marks in view
    # A hidden mark breaks the chord: there the moves are interpolated along the rope.
    keep = np.arange(len(marks)) != 10
    gap = MarkReading(marks.fraction_j[keep], marks.top_j3[keep], RADIUS, marks.count)
    assert not gap.neighbours(9) and gap.neighbours(8)


@pytest.mark.parametrize("seed", [1, 2, 4])
@pytest.mark.parametrize("by", [-0.03, 0.03])
def test_a_tail_past_the_last_mark_in_view_slides_along_the_chain_not_off_the_rope(seed, by):
    truth = _curve(seed)
    slid = _slid(truth, by)
    exact = observe_marks(truth, RADIUS, rng=np.random.default_rng(0), noise=0.0)
    # The tail's marks hidden (under another strand, as at the knot step).
    keep = exact.fraction_j < 0.8
    hidden = MarkReading(exact.fraction_j[keep], exact.top_j3[keep], RADIUS, exact.count)
    moved = move_to_marks(slid, hidden)
    tail = np.linalg.norm(moved[33:] - truth[33:], axis=1)
    # Within the dead band of the rope (5 mm) to a millimetre or two; the tail carried by the
    # last mark's move as it stood measured 19-24 mm here on these curves.
    assert np.linalg.norm(slid[33:] - truth[33:], axis=1).min() > 0.02
    assert tail.mean() < 0.007


def test_a_loop_holding_the_wrong_part_of_the_rope_is_corrected_where_the_marks_say():
    truth = _curve(4)
    # The middle third of the chain slid 4 cm along the rope, the rest in place (a loop whose
    # material the prediction got wrong), and the whole chain 7 % short, as a pulled
    # estimate is.
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth, axis=0), axis=1))])
    shift = 0.04 * np.clip(1.0 - np.abs(arc - 0.5) / 0.2, 0.0, 1.0)
    warped = np.stack([np.interp(arc + shift, arc, truth[:, d]) for d in range(3)], axis=1)
    warped = warped.mean(axis=0) + 0.93 * (warped - warped.mean(axis=0))
    back = move_to_marks(warped, _marks(truth, 4))
    before = np.linalg.norm(warped - truth, axis=1)
    after = np.linalg.norm(back - truth, axis=1)
    assert before[18:23].mean() > 0.03
    assert after.mean() < 0.008 and after.max() < 0.015
    # Its length is the rope's again, its links about even (marks lie evenly along the rope).
    links = np.linalg.norm(np.diff(back, axis=0), axis=1)
    assert links.sum() == pytest.approx(arc[-1], rel=0.05)
    assert links.std() / links.mean() < 0.2


def test_no_marks_in_view_move_nothing_and_hidden_ones_are_bridged():
    truth = _curve(5)
    slid = _slid(truth, 0.03)
    none = MarkReading(np.zeros(0), np.zeros((0, 3)), RADIUS, 20)
    assert np.array_equal(move_to_marks(slid, none), slid)
    # The middle marks hidden (under a strand): the chain there follows its neighbours' moves.
    marks = _marks(truth, 5)
    keep = np.abs(marks.fraction_j - 0.5) > 0.12
    partial = MarkReading(marks.fraction_j[keep], marks.top_j3[keep], RADIUS, marks.count)
    moved = move_to_marks(slid, partial)
    assert node_error_mm(moved, truth) < 8.0 < node_error_mm(slid, truth)


def test_the_update_reads_marks_only_when_given_them():
    truth = _curve(6)
    cloud = _cloud(truth, 6)
    slid = _slid(truth, 0.05)
    plain = track_update(slid, cloud, radius=RADIUS, rng=np.random.default_rng(0))
    assert np.array_equal(
        plain, track_update(slid, cloud, radius=RADIUS, rng=np.random.default_rng(0), marks=None)
    )
    marked = track_update(
        slid, cloud, radius=RADIUS, rng=np.random.default_rng(0), marks=_marks(truth, 6)
    )
    assert node_error_mm(plain, truth) > 30.0
    assert node_error_mm(marked, truth) < 8.0


def test_the_marked_trackers_are_named_estimators_that_pair_with_the_unmarked_ones():
    tracker, video = make_estimator("tracker_marked"), make_estimator("video_marked")
    assert isinstance(tracker, TrackingEstimator) and not isinstance(tracker, VideoTracker)
    assert isinstance(video, VideoTracker)
    assert tracker.read_marks and video.read_marks
    assert (tracker.kind, video.kind) == (EstimatorKind.TRACKER_MARKED, EstimatorKind.VIDEO_MARKED)
    assert not make_estimator("video").read_marks and not make_estimator("video_ends").read_marks
    settings = parse_study_settings("video_marked,tracker_marked")
    assert [(s.name, s.world, s.estimator) for s in settings] == [
        ("video_marked", "nominal", EstimatorKind.VIDEO_MARKED),
        ("tracker_marked", "nominal", EstimatorKind.TRACKER_MARKED),
    ]
    # On the start rope (its true chain is the prior) the marks confirm it: the estimates of a
    # marked and an unmarked tracker differ by no more than the marks' noise, and the marked
    # tracker is seeded like any other.
    start = _curve(7)
    with RopeWorld() as world, RopeWorld() as model:
        world.reset(start)
        world.settle(0.3)
        estimates = {}
        for name in ("tracker", "tracker_marked", "tracker_marked"):
            est = make_estimator(name)
            est.start(world, 5, model)
            estimates.setdefault(name, []).append(est.estimate(world))
    marked_a, marked_b = estimates["tracker_marked"]
    assert np.array_equal(marked_a.nodes_k3, marked_b.nodes_k3)
    plain = estimates["tracker"][0]
    assert abs(marked_a.error_mm - plain.error_mm) < 3.0
