"""Command-line options shared by every `knotlab` command, defined once (one rule for defaults).

`--db URL` names the labelling database everywhere; its default is ``$KNOTLAB_DB_URL`` when set,
else the SQLite file ``knotlab.db`` in the working directory. ``--url`` is kept as a hidden alias
for scripts written before the flags were unified.
"""

from __future__ import annotations

import argparse
import os
import sys

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


def fail(exc: Exception | str) -> int:
    """Print an error the way the command line reports errors (one line); exit code 2."""
    print(f"knotlab: error: {exc}", file=sys.stderr)
    return 2
