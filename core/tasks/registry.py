"""Tasks by name: a task class registers itself with `register_task`; `get_task` finds it.

A task lives in its own folder ``core/tasks/<name>/``; asking for a name that is not registered
yet imports that folder (which registers it), so adding a task touches nothing outside it.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable

from knotlab.core.errors import InvalidInputError
from knotlab.core.tasks.base import DEFAULT_TASK, Task

_FACTORIES: dict[str, Callable[[], Task]] = {}
_INSTANCES: dict[str, Task] = {}  # tasks are immutable: one instance per name serves everyone
_PACKAGE = "knotlab.core.tasks"
_NOT_TASKS = frozenset({"base", "registry"})


def register_task(name: str) -> Callable[[type], type]:
    """Class decorator: make ``name`` build an instance of the decorated task class."""

    def wrap(cls: type) -> type:
        if name in _FACTORIES and _FACTORIES[name] is not cls:
            raise InvalidInputError(f"task {name!r} is registered twice")
        _FACTORIES[name] = cls
        return cls

    return wrap


def task_names() -> tuple[str, ...]:
    """Every task folder's name (sorted; the default task first)."""
    import knotlab.core.tasks as pkg

    found = {
        m.name for m in pkgutil.iter_modules(pkg.__path__) if m.ispkg and m.name not in _NOT_TASKS
    } | set(_FACTORIES)
    return tuple(sorted(found, key=lambda n: (n != DEFAULT_TASK, n)))


def get_task(name: str = DEFAULT_TASK) -> Task:
    """The task called ``name`` (its folder imported on first use); one-line error if unknown."""
    if name not in _FACTORIES:
        if name not in task_names():
            raise InvalidInputError(
                f"unknown task {name!r}; known tasks: {', '.join(task_names())}"
            )
        importlib.import_module(f"{_PACKAGE}.{name}")
        if name not in _FACTORIES:
            raise InvalidInputError(f"the folder of task {name!r} registers no task")
    if name not in _INSTANCES:
        _INSTANCES[name] = _FACTORIES[name]()
    return _INSTANCES[name]
