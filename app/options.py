"""Command-line options shared by every `knotlab` command, defined once (one rule for defaults).

`--db URL` names the labelling database everywhere; its default is ``$KNOTLAB_DB_URL`` when set,
else the SQLite file ``knotlab.db`` in the working directory. ``--url`` is kept as a hidden alias
for scripts written before the flags were unified.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path

from knotlab.app import defaults

DB_ENV = "KNOTLAB_DB_URL"


def default_db_url() -> str:
    """The database URL used when --db is not given: $KNOTLAB_DB_URL, else the SQLite file."""
    return os.environ.get(DB_ENV) or defaults.DB_URL


def add_db_argument(parser: argparse.ArgumentParser | argparse._ActionsContainer) -> None:
    """Add ``--db URL`` (default: $KNOTLAB_DB_URL or the SQLite file) and its ``--url`` alias."""
    parser.add_argument(
        "--db",
        "--url",
        dest="db",
        default=None,
        metavar="URL",
        help=f"labelling database URL (default: ${DB_ENV} or {defaults.DB_URL}); "
        "e.g. postgresql+psycopg://user@host/db",
    )


def db_url(args: argparse.Namespace) -> str:
    """The database URL a command should open: its --db, else the default."""
    return getattr(args, "db", None) or default_db_url()


def add_no_progress_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--no-progress`` (every command that can draw a progress bar takes it)."""
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_task_set_argument(parser: argparse.ArgumentParser, help: str) -> None:
    """Add ``--task-set PATH``, the one name of a task-set file flag (``--task-file`` hidden)."""
    parser.add_argument("--task-set", default=None, metavar="PATH", help=help)
    # the spelling `knotlab label` used before the flags were unified, kept for old scripts
    parser.add_argument("--task-file", dest="task_set", help=argparse.SUPPRESS)


def integer(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum`` (one-line message otherwise)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return value

    parse.__name__ = f"integer >= {minimum}"
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


def check_not_shipped(
    path: str | Path, *, flag: str = "--out", force: bool, kind: str = "file"
) -> None:
    """Refuse to replace an existing file under static/ or results/ unless ``force``."""
    from knotlab.core.errors import OutputPathError

    path = Path(path)
    protected = (defaults.STATIC_DIR, defaults.RESULTS_DIR)
    inside = any(path.resolve().is_relative_to(d.resolve()) for d in protected)
    if path.exists() and inside and not force:
        raise OutputPathError(
            f"{flag} {path} would replace a shipped or committed {kind}; "
            "write elsewhere or pass --force"
        )
