"""Episodes whose agent simulates in its own model of the world, apart from the world that acts."""

from __future__ import annotations

import inspect
import json
from dataclasses import replace

import numpy as np
import pytest

from knotlab.app import cli
from knotlab.core.agent import Agent
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.execution.memo import OutcomeMemo
from knotlab.core.experiments.episode import decode_nodes
from knotlab.core.world.estimate import (
    PerfectEstimator,
    TrackingEstimator,
    VideoTracker,
    node_error_mm,
)
from knotlab.core.world.observation import centreline_points
from knotlab.core.world.sim import RopeParams, RopeWorld
from tests.minilib import mini_library, mini_tasks, write_mini_files

pytestmark = pytest.mark.xdist_group("bench")


def _centreline_library() -> DemoLibrary:
    """The mini library with centreline clouds (what the tracker's estimates are compared to)."""
    lib = mini_library(2)
    segments = [replace(s, pre_cloud_n3=centreline_points(s.pre_nodes_k3)) for s in lib]
    return DemoLibrary(segments, {**lib.metadata, "observation_model": "centreline"})


def _summary(record) -> tuple:
    out = record.outcome()
    return out.success, out.chosen, out.stages, out.outcomes


def test_a_perfect_estimate_in_a_model_of_the_same_physics_is_the_world_itself():
    agent = Agent(mini_library(2), None, "oracle")
    tasks = list(mini_tasks(2))
    with RopeWorld() as world, RopeWorld() as model:
        for task in tasks:
            itself = agent.run_episode(world, task, max_steps=2)
            apart = agent.run_episode(
                world, task, max_steps=2, model_world=model, estimator=PerfectEstimator()
            )
            assert _summary(itself) == _summary(apart)
            for a, b in zip(itself.steps, apart.steps, strict=True):
                assert np.array_equal(a.nodes_before_k3, b.nodes_before_k3)
                assert np.array_equal(a.scores_a, b.scores_a)


class _SensedOnly:
    """A world whose own state no policy may read or set (the episode's bookkeeping may)."""

    def __init__(self, world: RopeWorld) -> None:
        self._world = world

    def __getattr__(self, name: str) -> object:
        if name in ("snapshot", "restore", "reset"):
            for frame in inspect.stack():
                if "/core/selection/" in frame.filename or "/core/world/estimate" in frame.filename:
                    raise AssertionError(f"{frame.filename} reached the world's state ({name})")
        return getattr(self._world, name)


@pytest.mark.parametrize("tracker", [TrackingEstimator, VideoTracker])
def test_with_a_tracker_the_search_never_touches_the_worlds_state(tracker):
    agent = Agent(_centreline_library(), None, "oracle")
    task = mini_tasks(1)[0]
    searched_in = []
    choose = agent.policy.choose
    agent.policy.choose = lambda ctx: searched_in.append(ctx.world) or choose(ctx)  # type: ignore[method-assign]
    with RopeWorld() as world, RopeWorld() as model:
        record = agent.run_episode(
            _SensedOnly(world),  # type: ignore[arg-type]
            task,
            max_steps=2,
            model_world=model,
            estimator=tracker(),
        )
    assert record.error is None, record.error
    assert searched_in and all(w is model for w in searched_in)
    errors = record.outcome().estimate_error_mm
    assert len(errors) == record.n_steps and all(0 < e < 50 for e in errors)
    assert "estimate_error_mm" in record.summary()
    crossings = record.outcome().estimate_crossings_right
    assert len(crossings) == record.n_steps and crossings[0]  # it starts on the true chain
    assert record.summary()["estimate_crossings_right"] == list(crossings)
    # The estimate each step decided from is recorded beside the true rope: read back, its
    # node error against the true rope is the recorded error (to the encoding's 0.1 mm).
    row = record.summary()
    assert len(row["estimate_nodes"]) == record.n_steps
    for est, true, err in zip(row["estimate_nodes"], row["nodes_before"], errors, strict=True):
        assert node_error_mm(decode_nodes(est), decode_nodes(true)) == pytest.approx(err, abs=0.2)


def test_the_video_tracker_gets_the_worlds_frames_through_a_shared_memo_and_ends_the_same():
    agent = Agent(_centreline_library(), None, "nn")
    task = mini_tasks(1)[0]
    seen: list[int] = []

    class Counting(VideoTracker):
        def executed(self, trajectory, model_world, frames=None):
            seen.append(0 if frames is None else len(frames))
            super().executed(trajectory, model_world, frames)

    memo = OutcomeMemo(size=64)
    with RopeWorld() as world, RopeWorld() as model:
        # A perfect-estimate episode fills the memo with outcomes recorded without frames.
        agent.run_episode(world, task, max_steps=2, memo=memo, model_world=model)
        runs = [
            agent.run_episode(
                world, task, max_steps=2, memo=memo, model_world=model, estimator=Counting()
            )
            for _ in range(2)
        ]
        fresh = agent.run_episode(
            world, task, max_steps=2, model_world=model, estimator=VideoTracker()
        )
    # Every executed step reached the tracker with its frames (30 a second, ~2 s or more).
    assert seen and all(n > 30 for n in seen)
    assert _summary(runs[0]) == _summary(runs[1]) == _summary(fresh)
    assert runs[0].outcome().estimate_error_mm == fresh.outcome().estimate_error_mm


def test_in_a_heavier_world_the_world_acts_not_the_models_prediction():
    agent = Agent(mini_library(2), None, "oracle")
    task = mini_tasks(1)[0]
    heavy = replace(RopeParams(), mass=0.6, friction=0.4)
    with RopeWorld(heavy) as world, RopeWorld() as model, RopeWorld(heavy) as replay:
        record = agent.run_episode(
            world, task, max_steps=2, model_world=model, estimator=PerfectEstimator()
        )
        assert record.n_steps == 2
        replay.reset(task.start_nodes_k3)
        first = record.steps[0].trajectory
        assert first is not None
        replay.execute(first)
        # The next state is what the heavy world did with the chosen demo...
        assert np.array_equal(replay.rope_nodes(), record.steps[1].nodes_before_k3)
        model.reset(task.start_nodes_k3)
        model.execute(first)
        # ... which is not what the nominal model predicted.
        assert not np.allclose(model.rope_nodes(), record.steps[1].nodes_before_k3, atol=1e-4)


def test_a_tracker_needs_a_centreline_library_and_a_model_world_apart():
    agent = Agent(mini_library(2), None, "nn")
    task = mini_tasks(1)[0]
    with RopeWorld() as world, RopeWorld() as model:
        with pytest.raises(InvalidInputError, match="centreline"):
            agent.run_episode(world, task, model_world=model, estimator=TrackingEstimator())
        with pytest.raises(InvalidInputError, match="model world apart"):
            agent.run_episode(world, task, estimator=TrackingEstimator())


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("model_world")
    lib, tasks = write_mini_files(d, n_tasks=2)
    return {"library": lib, "tasks": tasks}


def _bench(files, out, *extra):
    return cli.main(
        [
            *("bench", "--policies", "nn,oracle", "--tasks", "2", "--out-dir", str(out)),
            *("--library", str(files["library"]), "--task-set", str(files["tasks"])),
            *("--max-steps", "1", "--workers", "1", "--no-progress", *extra),
        ]
    )


def test_bench_records_each_tasks_world_and_refuses_to_mix_worlds(files, tmp_path, capsys):
    out = tmp_path / "c25"
    assert _bench(files, out, "--world-params", "combined25", "--seed", "3") == 0
    lines = [json.loads(x) for x in (out / "outcomes.jsonl").read_text().splitlines()]
    scales = {r["task_id"]: r["world_scales"] for r in lines}
    assert len(scales) == 2 and all(len(s) == 10 for s in scales.values())
    assert all(0.75 <= v <= 1.25 for s in scales.values() for v in s.values())
    assert lines[0]["run"]["world"] == "combined25"
    results = json.loads((out / "results.json").read_text())
    assert results["physics"]["world"]["combined_level"] == 0.25
    assert results["physics"]["agent_model"]["name"] == "nominal"
    assert results["physics"]["estimator"] == "perfect"
    before = (out / "outcomes.jsonl").read_bytes()
    capsys.readouterr()
    assert _bench(files, out, "--world-params", "mass+25", "--seed", "3") == 2
    err = capsys.readouterr().err
    assert "different arguments" in err and "world" in err
    assert (out / "outcomes.jsonl").read_bytes() == before


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (("--world-params", "massy+5"), "unknown physics setting"),
        (("--model-params", "radius+50"), "not a valid world"),
        (("--world-params", "measured"), "an agent model (--model-params), not a world"),
        (("--estimator", "psychic"), "invalid choice"),
    ],
)
def test_bad_physics_flags_get_one_line_and_write_nothing(files, tmp_path, capsys, flags, message):
    out = tmp_path / "bad"
    assert _bench(files, out, *flags) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1]
    assert not out.exists()


def test_one_candidate_in_the_model_and_in_another_world_side_by_side():
    from knotlab.core.execution.compare import outcome_in_model_and_world
    from knotlab.core.world.mismatch import parse_setting

    agent = Agent(mini_library(2), None, "nn")
    task = mini_tasks(1)[0]
    heavy = parse_setting("table_friction-50").params_for(task.task_id)
    with RopeWorld() as model, RopeWorld() as same, RopeWorld(heavy.rope, heavy.gripper) as other:
        model.reset(task.start_nodes_k3)
        cloud = agent.observe(model)
        action = agent.choose(model).action
        twin = outcome_in_model_and_world(
            task.start_nodes_k3, cloud, action, agent.transferer, model, same
        )
        assert twin.apart_mm == 0.0 and twin.agree  # the same physics: the same outcome
        apart = outcome_in_model_and_world(
            task.start_nodes_k3, cloud, action, agent.transferer, model, other
        )
        assert apart.apart_mm > 1.0  # a slipperier table: the dragged rope ends elsewhere
        assert np.array_equal(apart.model.nodes_after_k3, twin.model.nodes_after_k3)
