"""Tasks: what is specific to one rope task (goal test, stages, expert, limits, shipped files).

`get_task(name)` returns a `Task`; each task is a folder here (``overhand/``) that registers
itself with `register_task`. Nothing outside a task's folder knows which task it runs.
"""

from knotlab.core.tasks.base import (
    DEFAULT_TASK,
    PerturbationLevel,
    StageReading,
    Task,
    TaskFiles,
    check_task_of,
    level_of,
)
from knotlab.core.tasks.registry import get_task, register_task, task_names

__all__ = [
    "DEFAULT_TASK",
    "PerturbationLevel",
    "StageReading",
    "Task",
    "TaskFiles",
    "check_task_of",
    "get_task",
    "level_of",
    "register_task",
    "task_names",
]
