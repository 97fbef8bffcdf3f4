"""`knotlab suggest`: which unlabelled training starts to label next (most informative first)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys

from knotlab.app.options import (
    DB_ENV,
    add_db_argument,
    add_flag,
    add_no_progress_argument,
    add_task_argument,
    add_task_set_argument,
    integer,
    library_file,
    load_library,
    load_task_set,
    model_file,
    task_set_file,
)
from knotlab.core.selection.acquisition import RANK_BY, RankedState


def format_suggestions(ranked: list[RankedState]) -> str:
    """Rank, state, Q margin, disagreement and each policy's choice, one line per state."""
    head = f"{'rank':>4}  {'start':<18} {'Q margin':>9} {'disagree':>8}  choices"
    lines = [head, "-" * len(head)]
    for r in ranked:
        s = r.score
        margin = f"{s.margin:.4f}" if math.isfinite(s.margin) else "inf"
        choices = ", ".join(f"{k} {v}" for k, v in s.choices.items())
        lines.append(f"{r.rank:>4}  {s.key:<18} {margin:>9} {s.disagreement:>8.2f}  {choices}")
    return "\n".join(lines)


def _clouds_from_store(url: str) -> dict:
    from knotlab.labeling_db.store import open_store

    with open_store(url, create=False, auto_upgrade=False) as store:
        states = store.start_states_to_label()
    clouds = {}
    for s in states:
        key = s.provenance.task_id or f"state:{s.state_id}"
        clouds[key if key not in clouds else f"{key}#state:{s.state_id}"] = s.cloud_n3
    return clouds


def _score(clouds: dict, featurizer, model, args: argparse.Namespace, progress: bool) -> list:
    """Every cloud's acquisition score; the level's shipped start scans are used where they fit
    (the clouds a labelling store holds for its starts), the rest are scanned here."""
    from tqdm import tqdm

    from knotlab.app import defaults
    from knotlab.app.options import resolve_level, task_of
    from knotlab.core.errors import KnotlabError
    from knotlab.core.selection.acquisition import score_starts
    from knotlab.core.selection.scan_cache import ScanCacheIdentity, ScanSummaryCache

    identity = ScanCacheIdentity.of(featurizer)
    try:
        path = defaults.scans_path(resolve_level(args), "train", task_of(args))
        scans = ScanSummaryCache.load(path, identity)
    except (KnotlabError, OSError, ValueError):  # another library, or no shipped scans
        scans = ScanSummaryCache(identity)
    with tqdm(total=len(clouds), desc="scoring states", disable=not progress) as bar:
        return score_starts(
            list(clouds.items()),
            featurizer,
            model,
            scans,
            report=lambda done, _total: bar.update(done - bar.n),
        )


def _run(args: argparse.Namespace) -> int:
    from knotlab.core.errors import InvalidInputError, KnotlabError
    from knotlab.core.selection.acquisition import rank_for_labelling, task_start_clouds
    from knotlab.core.selection.features import LibraryFeaturizer
    from knotlab.core.selection.qmodel import QModel
    from knotlab.labeling_db.errors import LabelingDbError

    if args.db is not None and args.task_set is not None:
        raise InvalidInputError("give --db or --task-set, not both")
    # As in every database command $KNOTLAB_DB_URL stands for a missing --db; a --task-set
    # still chooses the file over it, and with neither the task's shipped train set is ranked.
    url = args.db or (None if args.task_set else os.environ.get(DB_ENV) or None)
    progress = not args.no_progress
    try:
        library = load_library(library_file(args), args)
        model = QModel.load(model_file(args))
        featurizer = LibraryFeaturizer.for_model(library, model)
        if url is not None:
            clouds = _clouds_from_store(url)
            where = f"{url} (start states without a completed episode)"
        else:
            path = task_set_file(args, "train")
            tasks = load_task_set(path, args)
            if tasks.split != "train":
                raise InvalidInputError(
                    f"{path} is a {tasks.split!r} task set; suggest labels training starts"
                )
            clouds = task_start_clouds(list(tasks), featurizer, progress=progress)
            where = str(path)
        scores = _score(clouds, featurizer, model, args, progress)
    except FileNotFoundError as exc:
        raise InvalidInputError(f"file not found: {exc.filename or exc}") from None
    except (KnotlabError, LabelingDbError) as exc:
        if isinstance(exc, KnotlabError):
            raise
        raise InvalidInputError(str(exc)) from exc
    ranked = rank_for_labelling(scores, by=args.by, seed=args.seed)[: args.limit]
    if args.json:
        rows = [
            {
                "rank": r.rank,
                **dataclasses.asdict(r.score),
                "margin": r.score.margin if math.isfinite(r.score.margin) else None,
                "disagreement": r.score.disagreement,
            }
            for r in ranked
        ]
        print(json.dumps(rows))
        return 0
    print(f"{len(scores)} unlabelled starts from {where}; the {len(ranked)} to label first:")
    print(format_suggestions(ranked))
    if not scores:
        print("nothing left to label", file=sys.stderr)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab suggest` to the command line."""
    p = subparsers.add_parser(
        "suggest",
        help="rank unlabelled training starts by how much a label would teach the model",
        description=(
            "Score every unlabelled training start by the Q margin between its two best demos "
            "and by whether NN and greedy disagree there, and list the most informative first. "
            f"Starts come from the labelling database (--db, or ${DB_ENV} when set: those "
            "without a completed episode) or from a training task set (--task-set; default: the "
            "task's shipped train set of the level)."
        ),
    )
    add_db_argument(p)
    add_task_set_argument(p, "training starts to rank (instead of the database)")
    add_task_argument(p)
    add_flag(p, "--level")
    add_flag(p, "--model", detail="default: the task's shipped default model")
    add_flag(p, "--library", detail="default: the task's shipped library")
    p.add_argument("--limit", type=integer(1), default=20, help="how many to list (default 20)")
    p.add_argument("--by", choices=RANK_BY, default="combined", help="ranking (default combined)")
    add_flag(p, "--seed", default=0, detail="breaks ties (0)")
    add_no_progress_argument(p)
    add_flag(p, "--json", detail="the ranking instead of the text")
    p.set_defaults(func=_run)
