"""`knotlab db init|upgrade|stats`: create, migrate and summarise the labelling database."""

from __future__ import annotations

import argparse
import json
import os
import sys

from labeling_db.errors import LabelingDbError
from labeling_db.store import DEFAULT_URL, open_store, schema_status, upgrade_database

URL_ENV = "KNOTLAB_DB_URL"


def default_url() -> str:
    """The database URL used when --url is not given: $KNOTLAB_DB_URL, else the SQLite file."""
    return os.environ.get(URL_ENV, DEFAULT_URL)


def add_url_argument(parser: argparse.ArgumentParser) -> None:
    """Add the shared --url option."""
    parser.add_argument(
        "--url",
        default=None,
        help=f"database URL (default: ${URL_ENV} or {DEFAULT_URL}); "
        "e.g. postgresql+psycopg://user@host/db",
    )


def fail(exc: Exception) -> int:
    """Print a labelling-database error the way the command line reports errors; exit code 2."""
    print(f"knotlab: error: {exc}", file=sys.stderr)
    return 2


def _init(args: argparse.Namespace) -> int:
    url = args.url or default_url()
    try:
        before, after = upgrade_database(url, create=True)
    except LabelingDbError as exc:
        return fail(exc)
    if before.state == "empty":
        print(f"created the knotlab schema at revision {after.revision} in {after.url}")
    elif before.revision == after.revision:
        print(f"{after.url} is already at the newest schema revision {after.revision}")
    else:
        print(f"upgraded {after.url} from revision {before.revision} to {after.revision}")
    return 0


def _upgrade(args: argparse.Namespace) -> int:
    url = args.url or default_url()
    try:
        before, after = upgrade_database(url, create=False)
    except LabelingDbError as exc:
        return fail(exc)
    if before.revision == after.revision:
        print(f"{after.url} is already at the newest schema revision {after.revision}")
    else:
        print(f"upgraded {after.url} from revision {before.revision} to {after.revision}")
    return 0


def _stats(args: argparse.Namespace) -> int:
    url = args.url or default_url()
    try:
        status = schema_status(url)
        with open_store(url, create=False, auto_upgrade=False) as store:
            stats = store.stats()
    except LabelingDbError as exc:
        return fail(exc)
    stats["schema_head"] = status.head
    if args.json:
        print(json.dumps(stats, sort_keys=True))
        return 0
    width = max(len(k) for k in stats)
    for key, value in stats.items():
        if isinstance(value, dict):
            value = ", ".join(f"{k}={v}" for k, v in sorted(value.items())) or "-"
        print(f"{key:<{width}}  {value}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab db ...` to the command line."""
    db = subparsers.add_parser("db", help="create, migrate and inspect the labelling database")
    sub = db.add_subparsers(dest="db_command", required=True, metavar="ACTION")
    p = sub.add_parser("init", help="create the schema (or report that it exists)")
    add_url_argument(p)
    p.set_defaults(func=_init)
    p = sub.add_parser("upgrade", help="migrate an existing database to the newest schema")
    add_url_argument(p)
    p.set_defaults(func=_upgrade)
    p = sub.add_parser("stats", help="row counts, labels by source and outcome, schema revision")
    add_url_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_stats)
