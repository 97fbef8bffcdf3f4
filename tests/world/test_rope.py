"""Rope geometry: resampling, length, self-intersection and the tent perturbation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from knotlab.core.errors import InvalidInputError
from knotlab.core.world.rope import (
    has_xy_self_intersection,
    perturb_rope,
    perturb_rope_with_info,
    points_at_arc,
    resample_by_arc_length,
    rope_length,
    slide_along,
    straight_rope,
)


def smooth_curve(coeffs: list[float], n: int = 400) -> np.ndarray:
    u = np.linspace(0, 1, n)
    y = sum(c / (k + 1) * np.sin((k + 1) * np.pi * u) for k, c in enumerate(coeffs))
    return np.stack([u - 0.5, y, 0.01 + 0.02 * u], axis=1)


@settings(max_examples=40, deadline=None)
@given(
    coeffs=st.lists(st.floats(-0.15, 0.15), min_size=1, max_size=3),
    n=st.integers(41, 120),
)
def test_resampling_keeps_length_ends_and_even_spacing(coeffs, n) -> None:
    curve = smooth_curve(coeffs)
    out = resample_by_arc_length(curve, n)
    assert out.shape == (n, 3)
    assert np.array_equal(out[[0, -1]], curve[[0, -1]])
    assert rope_length(out) <= rope_length(curve) + 1e-12  # chords never lengthen
    assert rope_length(out) == pytest.approx(rope_length(curve), rel=2e-3)
    seg = np.linalg.norm(np.diff(out, axis=0), axis=1)
    assert seg.max() - seg.min() < 0.05 * seg.mean()


def test_resampling_a_straight_rope_is_exact_for_any_count() -> None:
    out = resample_by_arc_length(np.array([[-0.5, 0, 0.01], [0.5, 0, 0.01]]), 41)
    np.testing.assert_allclose(out, straight_rope(41), atol=1e-15)


@pytest.mark.parametrize(
    "bad", [np.zeros((1, 3)), np.zeros((4, 2)), np.array([[0, 0, 0], [np.nan, 0, 0.0]])]
)
def test_bad_nodes_are_rejected(bad) -> None:
    with pytest.raises(InvalidInputError):
        resample_by_arc_length(bad, 10)


def test_self_intersection_in_xy() -> None:
    assert not has_xy_self_intersection(straight_rope())
    loop = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0.5, 1, 0], [0.5, -1, 0.5]], dtype=float)
    assert has_xy_self_intersection(loop)  # crossing above the first strand still counts
    assert not has_xy_self_intersection(loop[:4])


def serpentine() -> np.ndarray:
    """Strands 4 cm apart: most tent draws with rho = 5 cm make it cross itself."""
    pts = []
    for row in range(6):
        xs = np.linspace(-0.1, 0.1, 8)
        pts += [(x, 0.04 * row, 0.01) for x in (xs if row % 2 == 0 else xs[::-1])]
    return resample_by_arc_length(np.array(pts), 41)


@pytest.mark.parametrize("rope", [straight_rope(), serpentine()], ids=["straight", "serpentine"])
def test_perturbation_keeps_length_and_count_and_never_crosses(rope) -> None:
    for seed in range(5):
        out = perturb_rope(rope, 0.05, seed=seed, max_tries=200)
        assert out.shape == rope.shape
        assert rope_length(out) == pytest.approx(rope_length(rope), rel=1e-9)
        assert not has_xy_self_intersection(out)
        np.testing.assert_allclose(out[:, 2], rope[0, 2])  # xy-only: the rope stays flat


def test_perturbation_is_seeded() -> None:
    a = perturb_rope(straight_rope(), 0.1, seed=3)
    b = perturb_rope(straight_rope(), 0.1, seed=3)
    c = perturb_rope(straight_rope(), 0.1, seed=4)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    assert np.abs(a - straight_rope()).max() > 0.01  # it really moved


def test_peak_displacement_does_not_grow_with_retries() -> None:
    rho = 0.05
    infos = [perturb_rope_with_info(serpentine(), rho, seed=s, max_tries=500) for s in range(12)]
    retried = [i for i in infos if i.n_tries >= 3]
    assert retried, "the serpentine should need retries"
    # Stacked retries (the original bug) would reach n_tries * rho; fresh draws stay <= rho.
    assert max(i.peak_tent for i in infos) <= rho * (1 + 1e-12)


def test_impossible_perturbation_raises_clear_error() -> None:
    crossing = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0.5, 1, 0], [0.5, -1, 0]], float)
    with pytest.raises(InvalidInputError, match="no self-intersection-free perturbation"):
        perturb_rope(resample_by_arc_length(crossing, 41), 0.0, max_tries=3)


def test_segment_feet_finds_each_points_nearest_place_on_every_segment():
    from knotlab.core.world.rope import segment_feet

    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    points = np.array([[0.25, 0.5, 0.0], [2.0, 0.5, 3.0], [-1.0, 0.0, 0.0]])
    t, foot, dist = segment_feet(points, path)
    assert t.shape == dist.shape == (3, 2) and foot.shape == (3, 2, 3)
    assert np.allclose(t[0], [0.25, 0.5]) and np.allclose(foot[0, 0], [0.25, 0.0, 0.0])
    assert np.allclose(dist[0], [0.5, 0.75])
    # In 3-D the height counts; in the table's plane it does not.
    assert dist[1, 1] == pytest.approx(np.hypot(1.0, 3.0))
    assert segment_feet(points, path, xy_only=True)[2][1, 1] == pytest.approx(1.0)
    # Clipped per segment: the first segment continued before its start reaches (-1, 0, 0).
    t_open, _, dist_open = segment_feet(points, path, low_m=np.array([-np.inf, 0.0]))
    assert t_open[2, 0] == pytest.approx(-1.0) and dist_open[2, 0] == pytest.approx(0.0)
    assert dist[2, 0] == pytest.approx(1.0)


def test_a_chain_slides_along_its_own_curve_and_straight_on_past_its_ends():
    # An L: 2 links along x, then 2 along y (each 0.1 m).
    ell = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.2, 0.1, 0], [0.2, 0.2, 0]])
    assert np.allclose(slide_along(ell, 0.0), ell, rtol=0.0, atol=1e-15)
    forward = slide_along(ell, 0.15)  # every node 15 cm further along, round the corner
    assert np.allclose(forward[0], [0.15, 0.0, 0.0]) and np.allclose(forward[1], [0.2, 0.05, 0])
    assert np.allclose(forward[-1], [0.2, 0.35, 0.0])  # past the end: on along the last link
    back = slide_along(ell, -0.05)
    assert np.allclose(back[0], [-0.05, 0.0, 0.0]) and np.allclose(back[3], [0.2, 0.05, 0.0])
    # Points at arc lengths from the first node: round the corner and straight on past it.
    at = points_at_arc(ell, np.array([0.0, 0.25, 0.4, -0.1]))
    assert np.allclose(at, [[0.0, 0, 0], [0.2, 0.05, 0], [0.2, 0.2, 0], [-0.1, 0, 0]])
