"""Task generation: determinism, validity (no crossing, length kept), disjoint seeds, files."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.demos.tasks import TaskSet, generate_tasks, min_clearance, task_seed
from knotlab.core.errors import CorruptFileError
from knotlab.core.tasks.expert_moves import sample_start_rope
from knotlab.core.world.rope import has_xy_self_intersection, rope_length


@pytest.fixture(scope="module")
def starts():
    return {i: sample_start_rope(np.random.default_rng(i), max_rotation=0.5) for i in range(3)}


@pytest.fixture(scope="module")
def train(starts):
    return generate_tasks(starts, 4, split="train", rho=0.05, seed=11, workers=1, progress=False)


def test_tasks_are_valid_settled_ropes(train, starts):
    assert len(train) == 4
    for t in train:
        assert t.start_nodes_k3.shape == (41, 3)
        assert not has_xy_self_intersection(t.start_nodes_k3)
        assert rope_length(t.start_nodes_k3) == pytest.approx(1.0, rel=0.02)
        assert t.source_start in starts
        assert np.abs(t.start_nodes_k3[:, 2] - 0.01).max() < 0.005  # resting on the table
        dist = np.linalg.norm(t.start_nodes_k3 - starts[t.source_start], axis=1)
        assert 0.0 < dist.max() < 0.2  # perturbed, but close to its source


def test_generation_is_deterministic(train, starts):
    again = generate_tasks(starts, 4, split="train", rho=0.05, seed=11, workers=2, progress=False)
    assert again.content_hash() == train.content_hash()


def test_train_and_test_seeds_are_disjoint():
    train = {task_seed(3, "train", i) for i in range(500)}
    test = {task_seed(3, "test", i) for i in range(500)}
    assert len(train) == 500 and len(test) == 500
    assert not train & test


def test_larger_rho_moves_the_rope_further(starts):
    small = generate_tasks(starts, 3, split="test", rho=0.02, seed=4, workers=1, progress=False)
    big = generate_tasks(starts, 3, split="test", rho=0.10, seed=4, workers=1, progress=False)

    def spread(ts):
        return np.mean([np.abs(t.start_nodes_k3 - starts[t.source_start]).max() for t in ts])

    assert spread(big) > spread(small)
    for t in big:
        assert min_clearance(t.start_nodes_k3) > 0.015


def test_file_round_trip_and_corruption(train, tmp_path):
    path = train.save(tmp_path / "tasks.npz")
    loaded = TaskSet.load(path)
    assert loaded.content_hash() == train.content_hash()
    assert loaded.metadata["rho"] == 0.05 and loaded.split == "train"
    assert np.array_equal(loaded.seeds(), train.seeds())
    for a, b in zip(loaded, train, strict=True):
        assert np.array_equal(a.start_nodes_k3, b.start_nodes_k3)
    raw = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(CorruptFileError, match="cut.npz"):
        TaskSet.load(tmp_path / "cut.npz")


@pytest.mark.parametrize(("level", "rho"), [("main", 0.05), ("hard", 0.10)])
def test_shipped_task_sets_load_with_disjoint_seeds(level, rho):
    from knotlab.app.defaults import task_set_path

    train = TaskSet.load(task_set_path(level, "train"))
    test = TaskSet.load(task_set_path(level, "test"))
    assert (len(train), len(test)) == (300, 500)
    assert train.metadata["rho"] == test.metadata["rho"] == rho
    assert not set(train.seeds().tolist()) & set(test.seeds().tolist())
    for t in list(train)[:20]:
        assert not has_xy_self_intersection(t.start_nodes_k3)
