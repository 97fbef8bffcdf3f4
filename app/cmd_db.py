"""`knotlab db init|upgrade|stats`: create, migrate and summarise the labelling database."""

from __future__ import annotations

import argparse
import json

from knotlab.app.options import add_db_argument, add_flag, db_url


def _init(args: argparse.Namespace) -> int:
    from knotlab.labeling_db.store import upgrade_database

    url = db_url(args)
    before, after = upgrade_database(url, create=True, persistent=True)
    if before.state == "empty":
        print(f"created the knotlab schema at revision {after.revision} in {after.url}")
    elif before.revision == after.revision:
        print(f"{after.url} is already at the newest schema revision {after.revision}")
    else:
        print(f"upgraded {after.url} from revision {before.revision} to {after.revision}")
    return 0


def _upgrade(args: argparse.Namespace) -> int:
    from knotlab.labeling_db.store import upgrade_database

    url = db_url(args)
    before, after = upgrade_database(url, create=False, persistent=True)
    if before.revision == after.revision:
        print(f"{after.url} is already at the newest schema revision {after.revision}")
    else:
        print(f"upgraded {after.url} from revision {before.revision} to {after.revision}")
    return 0


def _stats(args: argparse.Namespace) -> int:
    from knotlab.labeling_db.store import open_store, schema_status

    url = db_url(args)
    status = schema_status(url)
    with open_store(url, create=False, auto_upgrade=False) as store:
        stats = store.stats()
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
    add_db_argument(p)
    p.set_defaults(func=_init)
    p = sub.add_parser("upgrade", help="migrate an existing database to the newest schema")
    add_db_argument(p)
    p.set_defaults(func=_upgrade)
    p = sub.add_parser("stats", help="row counts, labels by source and outcome, schema revision")
    add_db_argument(p)
    add_flag(p, "--json")
    p.set_defaults(func=_stats)
