"""Command-line options shared by every `knotlab` command, defined once (one rule for defaults).

One meaning per flag name: a flag that more than one command takes is declared here once (`FLAGS`:
its dest, the kind of value it takes and the help sentence that says what it means) and added with
`add_flag`; tests/app/test_cli_flags.py walks the whole parser tree and holds every command to it.
An output file is ``--out FILE`` and an output folder ``--out-dir DIR`` everywhere.
Every path a command writes goes through `check_output`, one rule: an output that exists is
written only with ``--force`` or when it is the command's own output to resume (bench's results
folder, labels tries' file, with a matching identity); a shipped or committed one (static/,
results/, a task's data folder) only with ``--force``.

A flag whose value is a number takes a bounded type (`integer`, `number`, `number_list`,
`integer_tuple`, `PORT`, or a parser stamped with `bounded`): a NaN, an infinity or an
out-of-range value ends in one line when the command line is read. An argument that names a file
the command reads is marked (`Flag.reads`, `reads`, or a positional named ``path``), so that
tests/test_promises.py runs every command with one that does not exist.

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
import sys
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from knotlab.app import defaults
from knotlab.core.tasks import DEFAULT_TASK, get_task, task_names

if TYPE_CHECKING:
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.demos.tasks import TaskSet

DB_ENV = "KNOTLAB_DB_URL"
OBSERVATIONS: tuple[str, ...] = ("centreline", "cloud", "tracked")  # core's ObservationModel


def default_db_url() -> str:
    """The database URL used when --db is not given: $KNOTLAB_DB_URL, else the SQLite file."""
    return os.environ.get(DB_ENV) or defaults.DB_URL


def db_url(args: argparse.Namespace) -> str:
    """The database URL a command should open: its --db, else the default."""
    return getattr(args, "db", None) or default_db_url()


# --- Bounded number types: every flag whose value is a number takes one of these ------------
#
# tests/app/test_cli_flags.py walks the parser tree and refuses a numeric flag whose type is not
# stamped with BOUNDS_ATTR (bare int or float, or no type at all for a numeric default): a NaN,
# an infinity or a count below its minimum must end in one line at parse time, not in a run.

BOUNDS_ATTR = "bounds"  # the attribute a bounded argparse type carries: its bounds, in words


def bounded(bounds: str) -> Callable[[Callable[[str], Any]], Callable[[str], Any]]:
    """Stamp an argparse type that reads numbers (a list of them, a policy name with a depth)
    as bounded: it refuses, with an ArgumentTypeError, every value outside ``bounds``."""

    def stamp(parse: Callable[[str], Any]) -> Callable[[str], Any]:
        setattr(parse, BOUNDS_ATTR, bounds)
        return parse

    return stamp


def is_bounded(parse: object) -> bool:
    """True for an argparse type made by `integer`, `number` or stamped with `bounded`."""
    return bool(getattr(parse, BOUNDS_ATTR, None))


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
    setattr(parse, BOUNDS_ATTR, bound)
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
    setattr(parse, BOUNDS_ATTR, bound)
    return parse


def number_list(minimum: float = 0.0) -> Callable[[str], list[float]]:
    """An argparse type: comma-separated finite numbers >= ``minimum`` ('0.1,1,10')."""
    one = number(minimum)
    bound = f"finite numbers >= {minimum:g}"

    def parse(text: str) -> list[float]:
        try:
            values = [one(v.strip()) for v in text.split(",") if v.strip()]
        except argparse.ArgumentTypeError:
            values = []
        if not values:
            raise argparse.ArgumentTypeError(f"expected {bound}, separated by commas, got {text!r}")
        return values

    parse.__name__ = f"number list {bound}"
    setattr(parse, BOUNDS_ATTR, bound)
    return parse


def integer_tuple(minimum: int, count: int, example: str) -> Callable[[str], tuple[int, ...]]:
    """An argparse type: exactly ``count`` comma-separated integers >= ``minimum`` (``example``)."""
    one = integer(minimum)
    bound = f"{count} integers >= {minimum}"

    def parse(text: str) -> tuple[int, ...]:
        parts = text.split(",")
        try:
            values = tuple(one(v.strip()) for v in parts)
        except argparse.ArgumentTypeError:
            values = ()
        if len(values) != count:
            raise argparse.ArgumentTypeError(f"expected {bound} like {example}, got {text!r}")
        return values

    parse.__name__ = f"integer tuple {bound}"
    setattr(parse, BOUNDS_ATTR, bound)
    return parse


# Shared argument types: a seed feeds NumPy's SeedSequence (>= 0), a worker count is >= 1.
SEED = integer(0)
WORKERS = integer(1)
PORT = integer(0, 65535)  # a TCP port; 0: any free one
LEVEL_NAME = re.compile(r"[a-z0-9_-]+")  # it becomes part of a file name: no folders, no dots
LABEL_FORMATS: tuple[str, ...] = ("jsonl", "csv", "h5")  # h5: the original system's layout
# One vocabulary for --format: every command takes the subset it can write or read.
FILE_FORMATS: tuple[str, ...] = ("jsonl", "csv", "h5")


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
    reads: bool = False  # the value names a file the command reads (see INPUT_ATTR)

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
    reads=True,
)
_declare("--tasks", "use the first N tasks of the task set only", type=integer(1), metavar="N")
_declare("--library", "demo library file (.npz)", metavar="PATH", reads=True)
_declare("--model", "trained Q-model that ranks the candidates", metavar="PATH", reads=True)
_declare(
    "--labels",
    "labels file (.jsonl or .csv, as `knotlab labels export` writes)",
    metavar="FILE",
    reads=True,
)
_declare(
    "--top",
    "how many of a state's best-ranked candidate demos to use",
    type=integer(1),
    metavar="N",
    aliases=("--top-k",),  # `knotlab app`'s spelling before the flags were unified
)
_declare("--format", "file format", choices=FILE_FORMATS)
_declare(
    "--observation",
    "how the rope is perceived: centreline (a rope-state estimate), cloud (a camera's surface "
    "cloud), tracked (a centreline estimated from the camera cloud)",
    choices=OBSERVATIONS,
)
_declare(
    "--host",
    "interface to serve on (default 127.0.0.1: this machine only; another address is reachable "
    "by anyone on that network)",
    metavar="HOST",
)
_declare("--port", "TCP port to serve on, 0-65535 (0: any free port)", type=PORT, metavar="PORT")
_declare(
    "--token",
    "access token (default $KNOTLAB_TOKEN; required, and generated and printed when not given, "
    "for any host other than loopback)",
    metavar="TOKEN",
)
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
    if flag.reads:
        reads(action)
    value = {k: v for k, v in settings.items() if k in ("action", "type", "choices", "metavar")}
    for alias in flag.aliases:
        hidden = parser.add_argument(
            alias, dest=flag.dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **value
        )
        setattr(hidden, SHARED_ATTR, flag)
        if flag.reads:
            reads(hidden)
    return action


# --- Inputs: the arguments that name a file a command reads -------------------------------
#
# A missing one ends the command in one line (exit 2) before any work; tests/test_promises.py
# finds them through these marks and runs every command with a path that does not exist.

INPUT_ATTR = "reads_input"  # stamped on an argparse action whose value names a file to read
INPUT_POSITIONALS: tuple[str, ...] = ("path",)  # `demos info PATH`, `labels import PATH`, ...


def reads(action: argparse.Action) -> argparse.Action:
    """Mark ``action`` (a command's own argument) as naming a file the command reads."""
    setattr(action, INPUT_ATTR, True)
    return action


def is_input(action: argparse.Action) -> bool:
    """True for an argument that names a file the command reads: a `reads` flag (``--library``,
    ``--task-set``, ``--model``, ``--labels``, a command's own marked one) or a positional
    ``path``."""
    if getattr(action, INPUT_ATTR, False):
        return True
    return not action.option_strings and action.dest in INPUT_POSITIONALS


def check_input(path: str | Path, *, flag: str, kind: str) -> Path:
    """``path`` as given for ``flag``, refused in one line (exit 2) unless it is an existing
    file: for a command that would otherwise fall back on another file without a word."""
    from knotlab.core.errors import InvalidInputError

    path = Path(path)
    if path.is_dir():
        raise InvalidInputError(f"{flag} {path}: is a folder, expected a {kind} file")
    if not path.is_file():
        raise InvalidInputError(f"{flag} {path}: {kind} file not found")
    return path


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


def in_shipped_place(path: str | Path) -> bool:
    """True for a path, existing or not, in static/, results/ or a task's data folder."""
    protected = (defaults.STATIC_DIR, *defaults.shipped_dirs())
    resolved = Path(path).resolve()
    return any(resolved.is_relative_to(d.resolve()) for d in protected)


def is_committed(path: str | Path) -> bool:
    """True for an existing path in a shipped or committed place: static/, results/ or a task's
    data folder (decided cheaply, without asking git: such a path that exists is treated as
    committed)."""
    return Path(path).exists() and in_shipped_place(path)


def fresh_file(path: str | Path, *, own: Collection[Path] = ()) -> Path:
    """``path`` if nothing is there (or it is one of ``own``, the files this session wrote), else
    the first of ``stem-1.ext``, ``stem-2.ext``, ... that is free: for an output written without
    asking (the app's exports), which never replaces a file it did not make."""
    path = Path(path)
    candidate, n = path, 0
    while candidate.exists() and candidate not in own:
        n += 1
        candidate = path.with_name(f"{path.stem}-{n}{path.suffix}")
    return candidate


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


def warn_of_other_kinds(where: str, kinds: Iterable[str], what: str) -> None:
    """Print a warning when work about to be added to ``where`` joins ``what`` another numeric
    kind of CPU made (its near-ties can go the other way; the records say which is which)."""
    from knotlab.core.machine import other_kinds_warning

    warning = other_kinds_warning(where, kinds, what)
    if warning is not None:
        print(f"warning: {warning}", file=sys.stderr)
