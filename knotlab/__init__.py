"""knotlab: learning to select expert demonstrations for rope manipulation.

The public API for notebooks, cluster jobs and robots: an `Agent` makes one decision (observe,
rank, choose, act) or runs an episode; a `Task` says what is being tied. Everything else lives in
``knotlab.core`` (the science), ``knotlab.labeling_db`` (storage) and ``knotlab.app`` (the web
app and command line).

The names below are imported on first use, so ``import knotlab.app.cli`` (the command line)
stays fast and never loads the registration kernels or the simulator it does not need.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

# The one place the version is written: pyproject reads it ([tool.setuptools.dynamic]) and
# `knotlab --version` prints it.
__version__ = "0.1.0"

_EXPORTS: dict[str, str] = {
    "ActionOutcome": "knotlab.core.execution.apply",
    "Agent": "knotlab.core.agent",
    "Candidate": "knotlab.core.agent",
    "Decision": "knotlab.core.selection.decision",
    "DemoLibrary": "knotlab.core.demos.library",
    "QModel": "knotlab.core.selection.qmodel",
    "RopeTask": "knotlab.core.demos.tasks",
    "RopeWorld": "knotlab.core.world.sim",
    "Task": "knotlab.core.tasks",
    "TaskSet": "knotlab.core.demos.tasks",
    "get_task": "knotlab.core.tasks",
    "task_names": "knotlab.core.tasks",
}

__all__ = [
    "ActionOutcome",
    "Agent",
    "Candidate",
    "Decision",
    "DemoLibrary",
    "QModel",
    "RopeTask",
    "RopeWorld",
    "Task",
    "TaskSet",
    "__version__",
    "get_task",
    "task_names",
]

if TYPE_CHECKING:
    from knotlab.core.agent import Agent, Candidate
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.demos.tasks import RopeTask, TaskSet
    from knotlab.core.execution.apply import ActionOutcome
    from knotlab.core.selection.decision import Decision
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.tasks import Task, get_task, task_names
    from knotlab.core.world.sim import RopeWorld


def __getattr__(name: str) -> object:
    """A public name, imported from its module on first use."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'knotlab' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})
