"""`knotlab labels export|import|tries`: move labels between databases as JSONL or CSV files (or
the original system's HDF5 layout), and try the candidates of labelled states in simulation
(richer labels for training)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Literal, cast

from knotlab.app.options import (
    LABEL_FORMATS,
    add_db_argument,
    add_flag,
    add_no_progress_argument,
    add_task_argument,
    check_output,
    db_url,
    library_file,
    load_library,
    warn_of_other_kinds,
)

LabelFormat = Literal["jsonl", "csv", "h5"]
FORMATS = cast(tuple[LabelFormat, ...], LABEL_FORMATS)
SUFFIXES: dict[str, LabelFormat] = {
    ".jsonl": "jsonl",
    ".ndjson": "jsonl",
    ".csv": "csv",
    ".h5": "h5",
    ".hdf5": "h5",
}


def export_format(out: str | None, fmt: str | None) -> LabelFormat:
    """The format to export: --format, else the --out extension; a mismatch is refused."""
    from pathlib import Path

    from knotlab.core.errors import OutputPathError

    if out in (None, "-"):
        return cast(LabelFormat, fmt or "jsonl")
    suffix = Path(out).suffix.lower()
    implied = SUFFIXES.get(suffix)
    if implied is None:
        raise OutputPathError(
            f"--out {out}: expected a .jsonl or .csv file name (the format follows the extension)"
        )
    if fmt is not None and fmt != implied:
        raise OutputPathError(
            f"--out {out} says {implied} but --format is {fmt}; make them agree "
            "(or drop --format: the extension decides)"
        )
    return implied


def _export(args: argparse.Namespace) -> int:
    from knotlab.core.atomic import atomic_open
    from knotlab.labeling_db.interchange import export_labels
    from knotlab.labeling_db.store import open_store

    _check_library_arg(args)
    fmt = export_format(args.out, args.format)
    to_file = args.out not in (None, "-")
    if to_file:
        check_output(args.out, force=args.force, kind="labels file", suffixes=tuple(SUFFIXES))
    if fmt == "h5":
        return _export_h5(args)
    with open_store(db_url(args), create=False, auto_upgrade=False) as store:
        if to_file:  # atomic: a failed export never leaves half a file behind
            with atomic_open(args.out, newline="") as fh:
                n = export_labels(store, fh, fmt, source=args.source)
        else:
            n = export_labels(store, sys.stdout, fmt, source=args.source)
    print(f"exported {n} executions ({fmt}) from {store.url}", file=sys.stderr)
    return 0


def _check_library_arg(args: argparse.Namespace) -> None:
    """A --library that does not exist is refused first, whatever the format reads."""
    from knotlab.core.errors import InvalidInputError

    if args.library is not None and not Path(args.library).is_file():
        raise InvalidInputError(f"--library {args.library}: no such demo library file")


def _export_h5(args: argparse.Namespace) -> int:
    """Export to the original HDF5 layout (lossy by design: states, actions, knots, dead ends)."""
    from knotlab.core.errors import OutputPathError
    from knotlab.core.interop.h5_labels import export_labels_h5
    from knotlab.labeling_db.store import open_store

    if args.out in (None, "-"):
        raise OutputPathError("--format h5 writes a file: give --out FILE.h5")
    library = load_library(library_file(args), args)  # its segment names label the actions
    with open_store(db_url(args), create=False, auto_upgrade=False) as store:
        executions = [item.execution for item in store.stored_executions(source=args.source)]
        states, dead = export_labels_h5(executions, library, args.out)
    print(
        f"exported {states} labelled states and {dead} dead ends (HDF5, the original layout: "
        f"no candidates, scores or provenance) from {store.url} to {args.out}",
        file=sys.stderr,
    )
    return 0


def _read_h5(args: argparse.Namespace) -> list:
    """An HDF5 labels file as stored executions of the library's task."""
    from knotlab.core.interop.h5_labels import import_labels_h5
    from knotlab.labeling_db.records import StoredExecution

    library = load_library(library_file(args), args)
    got = import_labels_h5(args.path, library)
    task = None if library.task == "overhand" else library.task
    return [StoredExecution(ex, task=task) for ex in got.executions]


def _import(args: argparse.Namespace) -> int:
    from knotlab.labeling_db.interchange import import_labels, read_labels
    from knotlab.labeling_db.store import open_store

    _check_library_arg(args)
    h5 = (args.format or SUFFIXES.get(Path(args.path).suffix.lower())) == "h5"
    # a bad file is refused before the database opens; then one import path for every format
    items = _read_h5(args) if h5 else read_labels(args.path, args.format)
    with open_store(db_url(args), create=True, auto_upgrade=False, persistent=True) as store:
        n = import_labels(store, args.path, if_exists=args.if_exists, items=items)
    print(f"imported {n} executions into {store.url}", file=sys.stderr)
    return 0


def _tries(args: argparse.Namespace) -> int:
    import json

    from knotlab.core.experiments.tries import check_tries_match, try_candidates, try_jobs
    from knotlab.core.selection.tries import read_tries
    from knotlab.labeling_db.interchange import read_labels

    executions = [item.execution for item in read_labels(args.labels)]

    def own_tries(path: Path) -> bool:  # its own tries file, of these labels and --top, or raise
        check_tries_match(read_tries(path), executions, args.top, where=path)
        return True

    # Resumable: the states already in OUT are kept and skipped, when OUT is this command's
    # tries file of these labels (another file, or tries of other labels, are refused: a torn or
    # foreign line is named by read_tries rather than silently dropped).
    out = check_output(args.out, force=args.force, kind="tries file", suffixes=(), resume=own_tries)
    library = load_library(library_file(args), args)
    done = read_tries(out) if out.exists() else {}
    jobs = try_jobs(executions, args.top, set(done))
    if jobs:
        warn_of_other_kinds(str(out), (t.numeric_kind for t in done.values()), "tries")
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("a", encoding="utf-8") as fh:
        for rec in try_candidates(
            jobs, library, workers=args.workers, progress=not args.no_progress
        ):
            fh.write(json.dumps(rec.to_dict()) + "\n")
            fh.flush()
    print(
        f"tried the {args.top} cheapest candidates of {len(jobs)} states "
        f"({len(done)} already in {out})",
        file=sys.stderr,
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab labels ...` to the command line."""
    labels = subparsers.add_parser("labels", help="export or import labels (JSONL or CSV)")
    sub = labels.add_subparsers(dest="labels_command", required=True, metavar="ACTION")
    p = sub.add_parser("export", help="write every labelled execution to a file or stdout")
    add_flag(
        p,
        "--format",
        default=None,
        detail="default: from the --out extension (.jsonl, .csv or .h5); jsonl on stdout; h5 is "
        "the original system's layout and keeps only states, actions, knots and dead ends",
    )
    add_flag(p, "--out", default=None, detail=".jsonl, .csv or .h5 (default: stdout)")
    add_flag(p, "--force", detail="here: the labels file --out names")
    p.add_argument("--source", choices=("oracle", "human"), default=None, help="only this source")
    add_flag(p, "--library", detail="for h5: whose segment names the file uses (default shipped)")
    add_db_argument(p)
    p.set_defaults(func=_export)
    p = sub.add_parser("import", help="validate a labels file, then store all of it or nothing")
    p.add_argument(
        "path",
        help="a .jsonl or .csv file written by `knotlab labels export`, or an .h5 file in the "
        "original system's layout ((task, step) groups and f<k> dead ends)",
    )
    add_flag(p, "--format", default=None, detail="default: by suffix")
    add_flag(p, "--library", detail="for h5: whose segment names the file uses (default shipped)")
    p.add_argument(
        "--if-exists",
        choices=("error", "skip"),
        default="error",
        help="an execution id already stored: abort the import (default) or skip it",
    )
    add_db_argument(p)
    p.set_defaults(func=_import)
    p = sub.add_parser(
        "tries",
        help="try the cheapest candidates of every labelled state once in simulation "
        "(for `knotlab train --tries`)",
    )
    add_flag(p, "--labels", required=True)
    add_task_argument(p)
    add_flag(p, "--library", detail="default: the task's shipped library")
    add_flag(p, "--top", default=5, detail="each tried once in simulation, cheapest first (5)")
    add_flag(
        p, "--out", required=True, detail="JSONL to append to (resumed if it is tries of --labels)"
    )
    add_flag(p, "--force", detail="here: the --out file (needed to resume one in results/)")
    add_flag(p, "--workers")
    add_no_progress_argument(p)
    p.set_defaults(func=_tries)
    from knotlab.app.cmd_agreement import register_agreement

    register_agreement(sub)
