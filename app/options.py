"""Command-line options shared by every `knotlab` command, defined once (one rule for defaults).

One meaning per flag name: a flag that more than one command takes is declared here once (`FLAGS`:
its dest, the kind of value it takes and the help sentence that says what it means) and added with
`add_flag`; tests/app/test_cli_flags.py walks the whole parser tree and holds every command to it.
An output file is ``--out FILE`` and an output folder ``--out-dir DIR`` everywhere.
Every path a command writes goes through `check_output`, one rule: an output that exists is
written only with ``--force`` or when it is the command's own output to resume (bench's results
folder, labels tries' file, with a matching identity); a shipped or committed one (static/,
results/, a task's data folder) only with ``--force``.

`--db URL` names the labelling database everywhere; its default is ``$KNOTLAB_DB_URL`` when set,
else the SQLite file ``knotlab.db`` in the working directory. ``--url`` is kept as a hidden alias
for scripts written before the flags were unified.

`--task NAME` (default overhand) chooses whose shipped files (library, model, task sets, levels)
the defaults are: `library_file`, `model_file`, `task_set_file` and `resolve_level` resolve them.
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from knotlab.app import defaults
from knotlab.core.tasks import DEFAULT_TASK, get_task, task_names

if TYPE_CHECKING:
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.demos.tasks import TaskSet

DB_ENV = "KNOTLAB_DB_URL"


def default_db_url() -> str:
    """The database URL used when --db is not given: $KNOTLAB_DB_URL, else the SQLite file."""
    return os.environ.get(DB_ENV) or defaults.DB_URL


def db_url(args: argparse.Namespace) -> str:
    """The database URL a command should open: its --db, else the default."""
    return getattr(args, "db", None) or default_db_url()


def integer(minimum: int, maximum: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum`` (and <= ``maximum``); one-line message else."""
    bound = f">= {minimum}" if maximum is None else f"from {minimum} to {maximum}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"expected an integer {bound}, got {text!r}")
        return value

    parse.__name__ = f"integer {bound}"
    return parse


def number(
    minimum: float = -math.inf, *, above: bool = False, maximum: float = math.inf
) -> Callable[[str], float]:
    """An argparse type: a finite float >= ``minimum`` (> with ``above``), < ``maximum``."""
    bound = f"> {minimum:g}" if above else f">= {minimum:g}"
    if maximum < math.inf:
        bound += f" and < {maximum:g}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        low_ok = value > minimum if above else value >= minimum
        if not (math.isfinite(value) and low_ok and value < maximum):
            raise argparse.ArgumentTypeError(f"expected a finite number {bound}, got {text!r}")
        return value

    parse.__name__ = f"number {bound}"
    return parse


# Shared argument types: a seed feeds NumPy's SeedSequence (>= 0), a worker count is >= 1.
SEED = integer(0)
WORKERS = integer(1)
LEVEL_NAME = re.compile(r"[a-z0-9_-]+")  # it becomes part of a file name: no folders, no dots
LABEL_FORMATS: tuple[str, ...] = ("jsonl", "csv")


def level_name(text: str) -> str:
    """An argparse type: a plain level name like main or hard (it goes into file names)."""
    if not LEVEL_NAME.fullmatch(text):
        raise argparse.ArgumentTypeError(
            f"expected a plain name of a-z, 0-9, _ and - (like main or hard), got {text!r}"
        )
    return text


def task_name(text: str) -> str:
    """An argparse type: the name of a task (a folder of core/tasks); one line naming the known."""
    known = task_names()
    if text not in known:
        raise argparse.ArgumentTypeError(f"unknown task {text!r}; known tasks: {', '.join(known)}")
    return text


# --- Flags with one meaning: each shared flag is declared here, once -------------------------

SHARED_ATTR = "shared_flag"  # the attribute add_flag stamps on the argparse actions it adds


@dataclass(frozen=True)
class Flag:
    """A command-line flag with one meaning in every command that takes it.

    ``help`` says what it means; a command may add a detail after it (its default, what the
    value is used for there) but not another meaning. ``aliases`` are older spellings of the same
    flag, still accepted and not shown in --help.
    """

    name: str
    dest: str
    help: str
    type: Callable[[str], Any] | None = None  # None: the text as given (a path, a URL)
    switch: bool = False  # takes no value (store_true)
    choices: tuple[str, ...] | None = None
    metavar: str | None = None
    aliases: tuple[str, ...] = ()

    @property
    def spellings(self) -> tuple[str, ...]:
        """Every spelling a command line may use: the name, then the hidden aliases."""
        return (self.name, *self.aliases)


FLAGS: dict[str, Flag] = {}  # name -> declaration: every flag more than one command takes


def _declare(name: str, help: str, **kwargs: Any) -> Flag:
    flag = Flag(name, kwargs.pop("dest", name.lstrip("-").replace("-", "_")), help, **kwargs)
    FLAGS[name] = flag
    return flag


_declare(
    "--db",
    f"labelling database URL (default: ${DB_ENV} or {defaults.DB_URL}); "
    "e.g. postgresql+psycopg://user@host/db",
    metavar="URL",
    aliases=("--url",),  # the spelling of the db commands before the flags were unified
)
_declare("--no-progress", "no progress bar", switch=True)
_declare("--json", "print the result as JSON, on the last line of stdout", switch=True)
_declare(
    "--force",
    "allow writing into an output path that exists or is shipped or committed "
    "(replace it, or resume into it)",
    switch=True,
)
_declare("--seed", "random seed, an integer >= 0", type=SEED)
_declare("--workers", "worker processes (default: all cores)", type=WORKERS, metavar="N")
_declare(
    "--task",
    "the task whose shipped files are the defaults: "
    f"{', '.join(task_names())} (default {DEFAULT_TASK})",
    type=task_name,
    metavar="NAME",
)
_declare(
    "--level",
    "perturbation level of the task's start sets "
    f"(default: the task's first; {DEFAULT_TASK}: {', '.join(defaults.LEVELS)})",
    type=level_name,
)
_declare(
    "--task-set",
    "task-set file (.npz)",
    metavar="PATH",
    # `knotlab label` and `knotlab suggest` spellings before the flags were unified
    aliases=("--task-file", "--tasks-file"),
)
_declare("--tasks", "use the first N tasks of the task set only", type=integer(1), metavar="N")
_declare("--library", "demo library file (.npz)", metavar="PATH")
_declare("--model", "trained Q-model that ranks the candidates", metavar="PATH")
_declare(
    "--labels", "labels file (.jsonl or .csv, as `knotlab labels export` writes)", metavar="FILE"
)
_declare(
    "--top",
    "how many of a state's best-ranked candidate demos to use",
    type=integer(1),
    metavar="N",
    aliases=("--top-k",),  # `knotlab app`'s spelling before the flags were unified
)
_declare("--format", "labels file format", choices=LABEL_FORMATS)
_declare("--out", "file to write", metavar="FILE")
_declare("--out-dir", "folder to write into", metavar="DIR")


def add_flag(
    parser: argparse.ArgumentParser | argparse._ActionsContainer,
    name: str,
    *,
    detail: str | None = None,
    **kwargs: Any,
) -> argparse.Action:
    """Add the shared flag ``name`` (declared above) to ``parser``, with its hidden aliases.

    ``detail`` is appended to the flag's help; ``kwargs`` are the command's own settings
    (default, required, a tighter bound of the same type, a metavar).
    """
    flag = FLAGS[name]
    help = flag.help if detail is None else f"{flag.help}; {detail}"
    settings: dict[str, Any] = {"action": "store_true"} if flag.switch else {}
    if flag.type is not None:
        settings["type"] = flag.type
    if flag.choices is not None:
        settings["choices"] = flag.choices
    if flag.metavar is not None:
        settings["metavar"] = flag.metavar
    settings.update(kwargs)
    action = parser.add_argument(flag.name, dest=flag.dest, help=help, **settings)
    setattr(action, SHARED_ATTR, flag)
    value = {k: v for k, v in settings.items() if k in ("action", "type", "choices", "metavar")}
    for alias in flag.aliases:
        hidden = parser.add_argument(
            alias, dest=flag.dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **value
        )
        setattr(hidden, SHARED_ATTR, flag)
    return action


def add_db_argument(parser: argparse.ArgumentParser | argparse._ActionsContainer) -> None:
    """Add ``--db URL`` (default: $KNOTLAB_DB_URL or the SQLite file) and its ``--url`` alias."""
    add_flag(parser, "--db")


def add_no_progress_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--no-progress`` (every command that can draw a progress bar takes it)."""
    add_flag(parser, "--no-progress")


def add_task_set_argument(parser: argparse.ArgumentParser, detail: str) -> None:
    """Add ``--task-set PATH``, the one name of a task-set file flag (older spellings hidden)."""
    add_flag(parser, "--task-set", detail=detail)


def add_task_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--task NAME`` (default overhand): whose shipped files the defaults are."""
    add_flag(parser, "--task", default=DEFAULT_TASK)


# --- Defaults resolved by the task ---------------------------------------------------------


def task_of(args: argparse.Namespace) -> str:
    """The parsed --task (the default task for a namespace built without one)."""
    return getattr(args, "task", None) or DEFAULT_TASK


def task_levels(task: str) -> tuple[str, ...]:
    """The perturbation levels ``task`` ships start sets for, its default first."""
    return tuple(get_task(task).levels)


def resolve_level(args: argparse.Namespace, *, shipped: bool = True) -> str:
    """--level, else the task's first level (stored back in ``args.level``); with ``shipped``
    it must be one of the task's levels (a one-line error names them)."""
    levels = task_levels(task_of(args))
    level = getattr(args, "level", None) or levels[0]
    if shipped and level not in levels:
        from knotlab.core.errors import InvalidInputError

        raise InvalidInputError(
            f"--level {level}: task {task_of(args)!r} has no such level; known: {', '.join(levels)}"
        )
    args.level = level
    return level


def library_file(args: argparse.Namespace) -> Path:
    """--library, else the task's shipped demo library."""
    library = getattr(args, "library", None)
    return Path(library) if library else defaults.library_path(task_of(args))


def model_file(args: argparse.Namespace) -> Path:
    """--model as a file, else the task's shipped default model."""
    model = getattr(args, "model", None)
    return Path(model) if model else defaults.model_path(task_of(args))


def task_set_file(args: argparse.Namespace, split: str) -> Path:
    """--task-set, else the task's shipped ``split`` set of the level (--level checked either
    way)."""
    level = resolve_level(args)
    task_set = getattr(args, "task_set", None)
    return Path(task_set) if task_set else defaults.task_set_path(level, split, task_of(args))


def load_library(path: str | Path, args: argparse.Namespace) -> DemoLibrary:
    """The demo library at ``path``, refused (one line) when it belongs to another --task."""
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.tasks import check_task_of

    library = DemoLibrary.load(path)
    check_task_of("demo library", library.metadata.get("task"), get_task(task_of(args)))
    return library


def load_task_set(path: str | Path, args: argparse.Namespace) -> TaskSet:
    """The task set at ``path``, refused (one line) when it belongs to another --task."""
    from knotlab.core.demos.tasks import TaskSet
    from knotlab.core.tasks import check_task_of

    task_set = TaskSet.load(path)
    check_task_of("task set", task_set.metadata.get("task"), get_task(task_of(args)))
    return task_set


def is_committed(path: str | Path) -> bool:
    """True for an existing path in a shipped or committed place: static/, results/ or a task's
    data folder (decided cheaply, without asking git: such a path that exists is treated as
    committed)."""
    path = Path(path)
    if not path.exists():
        return False
    protected = (defaults.STATIC_DIR, *defaults.shipped_dirs())
    resolved = path.resolve()
    return any(resolved.is_relative_to(d.resolve()) for d in protected)


def check_output(
    path: str | Path,
    *,
    flag: str = "--out",
    force: bool,
    kind: str = "file",
    folder: bool = False,
    suffixes: Sequence[str] = (".npz",),
    writes: Sequence[str] = (),
    resume: Callable[[Path], bool] | None = None,
) -> Path:
    """The one rule for every path a command writes, checked before any work starts.

    - ``path`` must be writable (core.atomic's checks: a file name with one of ``suffixes``, or
      with ``folder`` a folder).
    - A shipped or committed path (`is_committed`) is written only with ``force``, resuming
      included.
    - A path that exists (a folder: one of the files it ``writes`` exists in it) is written only
      with ``force``, or when ``resume`` says it is this command's own output to resume:
      ``resume(path)`` returns True for its own (matching) output, False for something else, and
      raises a one-line error for its own kind of output made by another run (never mixed, not
      even with ``force``).
    """
    from knotlab.core.atomic import check_output_dir, check_output_file
    from knotlab.core.errors import OutputPathError

    if folder:
        out = check_output_dir(path, flag=flag)
        exists = out.exists() and (not writes or any((out / n).exists() for n in writes))
    else:
        out = check_output_file(path, flag=flag, suffixes=suffixes)
        exists = out.exists()
    if is_committed(out) and not force:
        verb = "write into" if folder else "resume or replace" if resume is not None else "replace"
        raise OutputPathError(
            f"{flag} {out} would {verb} a shipped or committed {kind}; "
            "write elsewhere or pass --force"
        )
    if not exists:
        return out
    own = resume(out) if resume is not None else False
    if not own and not force:
        made = "is not this command's own output to resume" if resume is not None else "exists"
        raise OutputPathError(f"{flag} {out} {made}; write elsewhere or pass --force to replace it")
    return out
