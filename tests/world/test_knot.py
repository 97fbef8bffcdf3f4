"""Knot test: trefoils in, other knots and clutter out, invariance, and a simulated knot."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from knotlab.core.tasks.overhand.knot_sequence import overhand_sequence
from knotlab.core.world.knot import (
    alexander_polynomial,
    analyse_knot,
    canonical_code,
    gauss_code,
    is_overhand_knot,
)
from knotlab.core.world.rope import resample_by_arc_length, straight_rope
from knotlab.core.world.sim import RopeWorld


def trefoil(mirror: bool = False, n: int = 200) -> np.ndarray:
    """Parametric trefoil opened by cutting a small arc."""
    t = np.linspace(0.1, 2 * np.pi - 0.1, n)
    z = -np.sin(3 * t) * (-1 if mirror else 1)
    return np.stack([np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), z], axis=1)


def figure_eight(n: int = 300) -> np.ndarray:
    t = np.linspace(0.1, 2 * np.pi - 0.1, n)
    r = 2 + np.cos(2 * t)
    return np.stack([r * np.cos(3 * t), r * np.sin(3 * t), np.sin(4 * t)], axis=1)


def kinked_rope(n_kinks: int, n: int = 400) -> np.ndarray:
    """A rope with n_kinks curls (Reidemeister I loops): a prolate cycloid, one crossing each."""
    t = np.linspace(np.pi, 2 * np.pi * n_kinks + np.pi, n)
    return np.stack([t - 1.8 * np.sin(t), -1.8 * np.cos(t), 0.3 * np.sin(t)], axis=1)


def r2_clutter() -> np.ndarray:
    """The rope's end passes over its own standing part twice (a Reidemeister II pair)."""
    return np.array(
        [
            [-1, 0, 0],
            [1, 0, 0],
            [1, 1, 0.1],
            [0.2, 1, 0.1],
            [0.2, -0.5, 0.1],
            [-0.2, -0.5, 0.1],
            [-0.2, 1, 0.1],
            [-1.5, 1, 0.1],
        ],
        dtype=float,
    )


def trefoil_with_kink() -> np.ndarray:
    """A trefoil with an extra curl (R1 loop) spliced into a lobe tip: still an overhand knot."""
    tre = trefoil()
    a, b = tre[99], tre[101]
    t_2 = (b - a)[:2] / np.linalg.norm((b - a)[:2])
    n_2 = np.array([-t_2[1], t_2[0]])
    r = np.linalg.norm((b - a)[:2]) / 2
    u = np.linspace(-np.pi, np.pi, 40)
    x, y = r * (u - 1.8 * np.sin(u)) / np.pi, -1.8 * r * (np.cos(u) + 1) / np.pi
    curl = np.zeros((u.size, 3))
    curl[:, :2] = 0.5 * (a + b)[:2] + x[:, None] * t_2 + y[:, None] * n_2
    curl[:, 2] = np.linspace(a[2], b[2], u.size) + 0.3 * r * np.sin(u)
    return np.vstack([tre[:99], curl, tre[102:]])


@pytest.mark.parametrize("mirror", [False, True])
def test_both_trefoil_chiralities_are_overhand_knots(mirror: bool) -> None:
    rope = trefoil(mirror)
    res = analyse_knot(rope)
    assert res.is_overhand and is_overhand_knot(rope)
    assert res.determinants == (3, 3) and res.alexander_values == (3, 3)
    assert res.n_crossings == 3
    expected = "O0 U1 O2 U0 O1 U2" if mirror else "U0 O1 U2 O0 U1 O2"
    assert res.gauss_code == expected
    # Coarse (41-node) ropes too.
    assert is_overhand_knot(resample_by_arc_length(rope, 41))


def test_figure_eight_is_rejected_with_determinant_five() -> None:
    res = analyse_knot(figure_eight())
    assert not res.is_overhand
    assert res.determinants == (5, 5)


@pytest.mark.parametrize(
    "rope",
    [
        straight_rope(),
        trefoil()[:120],
        r2_clutter(),
        kinked_rope(1),
        kinked_rope(2),
        kinked_rope(3),
    ],
    ids=["straight", "half-trefoil", "r2-clutter", "1-kink", "2-kinks", "3-kinks"],
)
def test_unknots_with_clutter_are_rejected(rope: np.ndarray) -> None:
    res = analyse_knot(rope)
    assert not res.is_overhand
    assert res.determinants == (1, 1)


def test_kinks_really_cross_and_do_not_fool_the_test() -> None:
    assert analyse_knot(kinked_rope(3)).n_crossings == 3
    assert gauss_code(r2_clutter()) == ("U0 U1 O1 O0", 2)
    kinked = analyse_knot(trefoil_with_kink())
    assert kinked.n_crossings == 4 and kinked.is_overhand


def test_both_closures_must_agree() -> None:
    # The rope's end lifted above a strand closes to a knot one way only: not a tied knot.
    rope = trefoil()[:170]
    res = analyse_knot(rope)
    assert not res.is_overhand


def test_degenerate_input_does_not_crash() -> None:
    doubled = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0.0], [0.5, 0, 0], [0.5, 0, 0]], dtype=float)
    analyse_knot(doubled)
    grid = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, -1, 1], [1, -2, 1]], float)
    analyse_knot(grid)  # a vertex exactly above a segment
    assert not is_overhand_knot(np.zeros((2, 3)))


ROPES = {
    "trefoil": trefoil(),
    "mirror": trefoil(True),
    "eight": figure_eight(),
    "kinks": kinked_rope(2),
}


@settings(max_examples=25, deadline=None)
@given(
    name=st.sampled_from(sorted(ROPES)),
    angle=st.floats(0, 2 * np.pi),
    shift=st.tuples(*[st.floats(-100, 100)] * 3),
    scale=st.floats(1e-3, 1e3),
)
def test_invariant_under_z_rotation_translation_and_scale(name, angle, shift, scale) -> None:
    rope = ROPES[name]
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    moved = scale * rope @ rot.T + np.array(shift)
    ref, got = analyse_knot(rope), analyse_knot(moved)
    assert got.is_overhand == ref.is_overhand
    assert got.determinants == ref.determinants
    assert got.n_crossings == ref.n_crossings


def test_a_trefoil_resampled_to_the_simulated_41_nodes_is_still_an_overhand_knot() -> None:
    # (its speed, < 5 ms a call, is measured by bench/knot_speed.py, not asserted in tests)
    for mirror in (False, True):
        result = analyse_knot(resample_by_arc_length(trefoil(mirror), 41))
        assert result.is_overhand and result.n_crossings == 3
        assert result.determinants == (3, 3)


@pytest.fixture(scope="module")
def simulated_steps() -> list[np.ndarray]:
    with RopeWorld() as world:
        world.reset(straight_rope())
        nodes = []
        for traj in overhand_sequence():
            result = world.execute(traj)
            assert result.ok, result.failure
            nodes.append(world.rope_nodes())
    return nodes


def test_fixed_sequence_ties_an_overhand_knot_in_the_simulator(simulated_steps) -> None:
    after1, after2, final = simulated_steps
    assert not is_overhand_knot(after1)
    assert analyse_knot(after1).n_crossings == 1
    assert not is_overhand_knot(after2)
    res = analyse_knot(final)
    assert res.is_overhand, res
    assert res.gauss_code == "U0 O1 U2 O0 U1 O2"


def test_alexander_polynomials_of_known_knots_under_both_closures() -> None:
    for above in (True, False):
        assert alexander_polynomial(kinked_rope(2), above) == (1,)
        assert alexander_polynomial(straight_rope(), above) == (1,)
        assert alexander_polynomial(trefoil(), above) == (1, -1, 1)
        assert alexander_polynomial(trefoil(mirror=True), above) == (1, -1, 1)
        assert alexander_polynomial(figure_eight(), above) == (1, -3, 1)
        assert alexander_polynomial(figure_eight()[::-1].copy(), above) == (1, -3, 1)


def test_a_canonical_code_is_the_same_from_either_end() -> None:
    code, _ = gauss_code(trefoil())
    backwards, _ = gauss_code(trefoil()[::-1].copy())
    assert canonical_code(code) == canonical_code(backwards)
    assert canonical_code("") == ""
