"""The knot tasks' shared methods: what a task gets from naming its parts."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from knotlab.core.tasks import get_task
from knotlab.core.tasks.knot_task import KnotTaskMethods, KnotTaskParts


class _Stage(IntEnum):
    OTHER = 0
    HALF = 1
    KNOT = 2


@dataclass(frozen=True)
class _Style:
    chirality: int


def _rope_stage(nodes_k3: np.ndarray) -> tuple[_Stage, str]:
    # a toy stage: how many nodes sit above the table
    stage = _Stage(min(int(np.sum(nodes_k3[:, 2] > 0)), 2))
    return stage, f"C{int(stage)}"


def _run_expert(world, start, style, **kwargs):
    return (world, start, style, kwargs)


@dataclass(frozen=True)
class _ToyTask(KnotTaskMethods):
    def parts(self) -> KnotTaskParts:
        return KnotTaskParts(
            _Stage,
            _rope_stage,
            lambda nodes: bool(np.all(nodes[:, 2] > 0)),
            _Style,
            lambda rng, mirror_prob: _Style(1),
            _run_expert,
        )


def test_a_task_that_names_its_parts_reads_stages_tests_success_and_runs_its_expert() -> None:
    task = _ToyTask()
    up = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]])
    flat = np.zeros((2, 3))
    assert (task.stage(up).stage, task.stage(up).code, task.stage(up).success) == (2, "C2", True)
    assert task.stage(flat).success is False and task.stage(flat).stage == 0
    broken = up.copy()
    broken[0, 0] = np.nan
    # non-finite nodes: no stage, no code, no success, whatever the task's own functions say
    assert (task.stage(broken).stage, task.stage(broken).code) == (0, "")
    assert task.is_success(up) and not task.is_success(flat) and not task.is_success(broken)
    world, start, style, kwargs = task.run_expert(
        "w", up, mirrored=True, seed=7, max_attempts=3, max_restarts=1
    )
    assert world == "w" and start is up
    assert style == _Style(-1) and kwargs == {"seed": 7, "max_attempts": 3, "max_restarts": 1}
    assert task.run_expert("w", up, mirrored=False, seed=7, max_attempts=3, max_restarts=1)[
        2
    ] == _Style(1)


def test_both_shipped_tasks_name_their_own_stages_and_expert() -> None:
    for name in ("overhand", "figure8"):
        parts = get_task(name).parts()
        assert parts.stage_enum["KNOT"] == len(get_task(name).stage_names) - 1
        assert parts.run_expert.__module__ == f"knotlab.core.tasks.{name}.expert"
