"""Default file locations the command line falls back on: the files each task ships.

A task's library, model and task sets are package data of its folder (``core/tasks/<name>/data``)
read through importlib.resources, so an installed knotlab finds them as a checkout does.
"""

from __future__ import annotations

from pathlib import Path

from knotlab.core.tasks import DEFAULT_TASK, get_task

REPO_DIR = Path(__file__).resolve().parent.parent  # a checkout's root (results/ lives there)
RESULTS_DIR = REPO_DIR / "results"
MODELS_DIR = Path("models")  # relative to the working directory: where `train` writes by default
DB_URL = "sqlite:///knotlab.db"
LEVELS: tuple[str, ...] = tuple(get_task(DEFAULT_TASK).levels)


def library_path(task: str = DEFAULT_TASK) -> Path:
    """The demonstration library shipped with ``task``."""
    return get_task(task).files.library_path


def model_path(task: str = DEFAULT_TASK) -> Path:
    """The default Q-model shipped with ``task``."""
    return get_task(task).files.model_path


def task_set_path(level: str, split: str, task: str = DEFAULT_TASK) -> Path:
    """The shipped task set of one perturbation level and split, e.g. tasks_main_test.npz."""
    return get_task(task).files.task_set_path(level, split)


def scans_path(level: str, split: str, task: str = DEFAULT_TASK, kind: str | None = None) -> Path:
    """The shipped scan summaries of a task set's start clouds made on CPUs of ``kind``
    (default: this machine's; used if present)."""
    return get_task(task).files.scans_path(level, split, kind)


def shipped_dirs() -> tuple[Path, ...]:
    """Folders whose files no command replaces without --force (shipped data and results)."""
    from knotlab.core.tasks import task_names

    return (*(get_task(t).files.library_path.parent for t in task_names()), RESULTS_DIR)


LIBRARY_PATH = library_path()
MODEL_PATH = model_path()
STATIC_DIR = REPO_DIR / "static"
