"""Library generation: every step represented, replay identity, bit-identical regeneration."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.demos.generation import GenSettings, candidate_seed, generate_library
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.world.knot import is_overhand_knot
from knotlab.core.world.sim import RopeWorld


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    report = generate_library(2, GenSettings(seed=5), workers=1, progress=False)
    path = report.library.save(tmp_path_factory.mktemp("lib") / "a.npz")
    return report, path


@pytest.mark.slow
def test_small_library_has_all_three_steps_of_successful_demos(small):
    report, path = small
    lib = DemoLibrary.load(path)
    assert lib.summary()["segments_per_step"] == {0: 2, 1: 2, 2: 2}
    assert lib.summary()["start_states"] == 2
    assert all(s.metadata["demo_knotted"] for s in lib)
    assert 0 < lib.metadata["expert_success_rate"] <= 1
    for s in lib:
        if s.step_index == 2:
            assert is_overhand_knot(s.post_nodes_k3)
        assert s.pre_cloud_n3.shape[0] >= 20
        assert s.trajectory.active_grippers() == (1,)  # the left gripper stays open
    assert report.knotted >= 2


@pytest.mark.slow
def test_segments_replay_to_their_post_nodes_exactly(small):
    lib = DemoLibrary.load(small[1])
    with RopeWorld() as world:
        for seg in lib:
            world.reset(seg.pre_nodes_k3)
            result = world.execute(seg.trajectory)
            assert result.ok
            assert np.array_equal(world.rope_nodes(), seg.post_nodes_k3), seg.key


@pytest.mark.slow
def test_regenerating_with_the_same_seed_is_bit_identical(small, tmp_path):
    again = generate_library(2, GenSettings(seed=5), workers=2, progress=False)
    path = again.library.save(tmp_path / "b.npz")
    assert path.read_bytes() == small[1].read_bytes()


def test_candidate_seeds_differ_across_candidates_and_generation_seeds():
    seeds = {candidate_seed(s, j) for s in range(3) for j in range(50)}
    assert len(seeds) == 150


def test_shipped_default_library_meets_the_spec():
    from knotlab.app.defaults import library_path

    path = library_path()
    lib = DemoLibrary.load(path)
    s = lib.summary()
    assert s["segments"] >= 148 and s["start_states"] >= 50
    assert set(s["segments_per_step"]) == {0, 1, 2}
    assert path.stat().st_size <= 10 * 2**20
    assert all(seg.metadata["demo_knotted"] for seg in lib)
