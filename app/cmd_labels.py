"""`knotlab labels export|import`: move labels between databases as JSONL or CSV files."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from knotlab.app.options import add_db_argument, db_url, fail


def _export(args: argparse.Namespace) -> int:
    from knotlab.labeling_db.errors import LabelingDbError
    from knotlab.labeling_db.interchange import export_labels
    from knotlab.labeling_db.store import open_store

    url = db_url(args)
    try:
        with open_store(url, create=False, auto_upgrade=False) as store:
            if args.out in (None, "-"):
                n = export_labels(store, sys.stdout, args.format, source=args.source)
            else:
                out = Path(args.out)
                tmp = out.with_name(out.name + ".tmp")
                with open(tmp, "w", encoding="utf-8", newline="") as fh:
                    n = export_labels(store, fh, args.format, source=args.source)
                tmp.replace(out)  # a failed export never leaves half a file behind
    except (LabelingDbError, OSError) as exc:
        return fail(exc)
    print(f"exported {n} executions from {store.url}", file=sys.stderr)
    return 0


def _import(args: argparse.Namespace) -> int:
    from knotlab.labeling_db.errors import LabelingDbError
    from knotlab.labeling_db.interchange import import_labels
    from knotlab.labeling_db.store import open_store

    url = db_url(args)
    try:
        with open_store(url, create=True, auto_upgrade=False) as store:
            n = import_labels(store, args.path, args.format, if_exists=args.if_exists)
    except (LabelingDbError, OSError) as exc:
        return fail(exc)
    print(f"imported {n} executions into {store.url}", file=sys.stderr)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab labels ...` to the command line."""
    labels = subparsers.add_parser("labels", help="export or import labels (JSONL or CSV)")
    sub = labels.add_subparsers(dest="labels_command", required=True, metavar="ACTION")
    p = sub.add_parser("export", help="write every labelled execution to a file or stdout")
    p.add_argument("--format", choices=("jsonl", "csv"), default="jsonl")
    p.add_argument("--out", default=None, help="output file (default: stdout)")
    p.add_argument("--source", choices=("oracle", "human"), default=None, help="only this source")
    add_db_argument(p)
    p.set_defaults(func=_export)
    p = sub.add_parser("import", help="validate a labels file, then store all of it or nothing")
    p.add_argument("path", help="a .jsonl or .csv file written by `knotlab labels export`")
    p.add_argument("--format", choices=("jsonl", "csv"), default=None, help="default: by suffix")
    p.add_argument(
        "--if-exists",
        choices=("error", "skip"),
        default="error",
        help="an execution id already stored: abort the import (default) or skip it",
    )
    add_db_argument(p)
    p.set_defaults(func=_import)
    from knotlab.app.cmd_agreement import register_agreement

    register_agreement(sub)
