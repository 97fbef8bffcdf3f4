"""The figure-eight task: its goal test on hand-built knots, its stages, and its scripted expert."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.demos.generation import GenSettings
from knotlab.core.tasks import get_task, task_names
from knotlab.core.tasks.figure8.stages import STAGE_CODES, Stage, stage_of
from knotlab.core.world.knot import analyse_knot, canonical_code
from knotlab.core.world.rope import resample_by_arc_length, straight_rope
from knotlab.core.world.sim import RopeWorld
from tests.world.test_knot import figure_eight, kinked_rope, trefoil


def cinquefoil(n: int = 400) -> np.ndarray:
    """The (2, 5) torus knot, opened: determinant 5 like the figure-eight, another polynomial."""
    t = np.linspace(0.05, 2 * np.pi - 0.05, n)
    r = 2 + np.cos(5 * t)
    return np.stack([r * np.cos(2 * t), r * np.sin(2 * t), np.sin(5 * t)], axis=1)


def moved(rope: np.ndarray, angle: float, shift: tuple[float, float, float], reverse: bool):
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    out = rope @ rot.T + np.array(shift)
    return out[::-1].copy() if reverse else out


TASK = get_task("figure8")
POSES = [(0.0, (0, 0, 0), False), (2.1, (3, -1, 0.5), False), (-0.7, (-5, 2, 0), True)]


def test_the_task_is_registered_with_the_expert_count_plus_two_steps() -> None:
    assert "figure8" in task_names()
    assert TASK.name == "figure8" and TASK.expert_steps == 4
    assert TASK.step_limit == TASK.expert_steps + 2
    assert TASK.stage_names[int(Stage.KNOT)] == "knot"
    assert set(TASK.levels) == {"main", "hard"}


@pytest.mark.parametrize("pose", POSES)
def test_a_figure_eight_is_the_goal_in_any_pose_and_direction(pose) -> None:
    for rope in (figure_eight(), resample_by_arc_length(figure_eight(), 41)):
        nodes = moved(rope, *pose)
        assert TASK.is_success(nodes)
        assert TASK.stage(nodes).success and TASK.stage(nodes).stage == int(Stage.KNOT)
        assert not get_task("overhand").is_success(nodes)


@pytest.mark.parametrize("pose", POSES)
def test_trefoils_unknots_and_a_cinquefoil_are_not(pose) -> None:
    for rope in (trefoil(), trefoil(mirror=True), kinked_rope(2), straight_rope(), cinquefoil()):
        nodes = moved(rope, *pose)
        assert not TASK.is_success(nodes)
        assert not TASK.stage(nodes).success
    # The cinquefoil shares the figure-eight's determinant: only the polynomial tells them apart.
    assert analyse_knot(cinquefoil()).determinants == (5, 5)


def test_stage_codes_are_read_from_either_end() -> None:
    for i, code in enumerate(STAGE_CODES):
        reversed_code = " ".join(code.split()[::-1])
        assert stage_of(code, False) == Stage(i + 1)
        assert stage_of(canonical_code(reversed_code), False) == Stage(i + 1)
    assert stage_of("U0 O1 U2 O0 U1 O2", False) is Stage.OTHER  # the overhand's knot code
    assert stage_of("", False) is Stage.OTHER
    assert TASK.stage(np.full((41, 3), np.nan)).stage == int(Stage.OTHER)


def test_the_expert_ties_it_in_four_steps_and_each_step_replays_bit_for_bit() -> None:
    settings = GenSettings(task="figure8")
    with RopeWorld() as world:
        run = TASK.demonstrate(world, settings, seed=0)
        assert run.knotted and len(run.steps) == TASK.expert_steps
        for i, step in enumerate(run.steps):
            assert TASK.stage(step.post_nodes_k3).stage == i + 1
            world.reset(step.pre_nodes_k3)
            assert world.execute(step.trajectory).ok
            assert np.array_equal(world.rope_nodes(), step.post_nodes_k3)
        assert TASK.is_success(run.steps[-1].post_nodes_k3)
        again = TASK.demonstrate(world, settings, seed=0)
    assert np.array_equal(again.steps[-1].post_nodes_k3, run.steps[-1].post_nodes_k3)


def test_the_command_line_generates_a_figure8_library_and_start_set(tmp_path, capsys) -> None:
    from knotlab.app import cli
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.demos.tasks import TaskSet

    lib_path = tmp_path / "f8.npz"
    base = ["--task", "figure8", "--workers", "1", "--no-progress"]
    assert cli.main(["demos", "generate", "--starts", "1", "--out", str(lib_path), *base]) == 0
    library = DemoLibrary.load(lib_path)
    assert library.task == "figure8"
    assert sorted(s.step_index for s in library.segments) == [0, 1, 2, 3]
    assert TASK.is_success(library.segments[-1].post_nodes_k3)
    argv = ["tasks", "generate", "--train", "2", "--test", "0", "--seed", "3", "--level", "main"]
    assert cli.main([*argv, "--library", str(lib_path), "--out-dir", str(tmp_path), *base]) == 0
    tasks = TaskSet.load(tmp_path / "tasks_main_train.npz")
    assert tasks.task == "figure8" and len(tasks) == 2
    # The overhand knot's commands refuse the figure-eight's files (one line, exit 2).
    assert cli.main(["tasks", "generate", "--seed", "3", "--library", str(lib_path),
                     "--out-dir", str(tmp_path / "o"), "--workers", "1"]) == 2  # fmt: skip
    assert "task 'figure8'" in capsys.readouterr().err


def test_bench_runs_episodes_under_the_tasks_step_limit(tmp_path, capsys) -> None:
    """Without --max-steps an episode gets the task's limit (6 here), not the overhand knot's 5."""
    import json

    from knotlab.app import cli

    out = tmp_path / "bench"
    argv = ["bench", "--task", "figure8", "--policies", "nn", "--tasks", "1", "--workers", "1"]
    assert cli.main([*argv, "--out-dir", str(out), "--no-progress"]) == 0
    assert "success = knot within 6 steps" in capsys.readouterr().out
    results = json.loads((out / "results.json").read_text())
    assert results["identity"]["max_steps"] == TASK.step_limit == 6
    (line,) = (out / "outcomes.jsonl").read_text().splitlines()
    record = json.loads(line)
    assert record["success"] or record["n_steps"] == 6  # a failure used every allowed step
