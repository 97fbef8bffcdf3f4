"""The scripted expert: start-rope sampler, style records, and knots on seeded ropes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.tasks.expert_moves import sample_start_rope
from knotlab.core.tasks.overhand.expert import (
    STAGE_CODES,
    ExpertStyle,
    run_expert,
    sample_style,
)
from knotlab.core.world.knot import analyse_knot
from knotlab.core.world.rope import has_xy_self_intersection, rope_length
from knotlab.core.world.sim import RopeWorld


@pytest.fixture(scope="module")
def world():
    with RopeWorld() as w:
        yield w


def test_start_rope_has_the_rope_length_and_no_crossing():
    for seed in range(20):
        nodes = sample_start_rope(np.random.default_rng(seed), bend_amplitude=0.06)
        assert nodes.shape == (41, 3)
        assert rope_length(nodes) == pytest.approx(1.0, abs=1e-3)
        assert not has_xy_self_intersection(nodes)
        assert np.allclose(nodes[:, 2], 0.01)


def test_start_rope_sampler_is_seeded():
    a = sample_start_rope(np.random.default_rng(3))
    b = sample_start_rope(np.random.default_rng(3))
    assert np.array_equal(a, b)


def test_style_round_trips_through_a_dict_and_rejects_bad_chirality():
    style = sample_style(np.random.default_rng(0))
    assert ExpertStyle.from_dict(style.to_dict()) == style
    with pytest.raises(InvalidInputError):
        ExpertStyle(chirality=0)


def test_style_sampler_draws_both_chiralities_and_some_brittle_grasps():
    styles = [sample_style(np.random.default_rng(s)) for s in range(60)]
    assert {s.chirality for s in styles} == {1, -1}
    assert any(s.end_grasp < 0.02 for s in styles)
    assert any(s.end_grasp >= 0.02 for s in styles)


@pytest.mark.parametrize(
    ("seed", "chirality"), [(1, 1), pytest.param(2, -1, marks=pytest.mark.slow)]
)
def test_expert_ties_an_overhand_knot_with_stage_checks(world, seed, chirality):
    start = sample_start_rope(np.random.default_rng(seed), bend_amplitude=0.03)
    run = run_expert(world, start, replace(ExpertStyle(), chirality=chirality), seed=seed)
    assert run.knotted, f"failed at step {run.failed_step}"
    assert [s.code for s in run.steps[:2]] == list(STAGE_CODES[:2])
    assert analyse_knot(run.steps[-1].post_nodes_k3).is_overhand
    # Steps chain: each step starts where the previous one ended.
    for a, b in zip(run.steps, run.steps[1:], strict=False):
        assert np.array_equal(a.post_nodes_k3, b.pre_nodes_k3)


@pytest.mark.slow
def test_expert_steps_replay_exactly(world):
    start = sample_start_rope(np.random.default_rng(1), bend_amplitude=0.03)
    run = run_expert(world, start, ExpertStyle(), seed=1)
    assert run.steps
    for step in run.steps:
        world.reset(step.pre_nodes_k3)
        world.execute(step.trajectory)
        assert np.array_equal(world.rope_nodes(), step.post_nodes_k3)
