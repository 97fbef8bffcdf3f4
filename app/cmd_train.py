"""`knotlab train`: fit the max-margin Q-function on labelled executions and save the QModel.

Labels come from a labels file written by `knotlab labels export` (JSONL or CSV) or straight
from the labelling database. Executions are split (seeded, by execution, never by state) into a
training part and a held-out validation part; the model is fitted on the training part and scored
on the validation part (top-1 agreement with the expert, mean rank of the expert's demo). With
``--refit-all`` the saved model is refitted on every execution after validation.
Featurising is one library scan per labelled state (~0.2 s), done over worker processes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

from knotlab.app import defaults
from knotlab.app.options import (
    add_db_argument,
    add_flag,
    add_no_progress_argument,
    add_task_argument,
    check_output,
    default_db_url,
    integer_tuple,
    library_file,
    load_library,
    number,
    number_list,
    reads,
)
from knotlab.core.jsonsafe import json_safe
from knotlab.core.selection.labels import LabelledExecution

log = logging.getLogger(__name__)


# --C and --D: '0.1,1,10' -> [0.1, 1.0, 10.0]; a slack weight is finite and >= 0.
_SLACK_WEIGHTS = number_list(0.0)
# --landmarks: '50,20' -> (50, 20), counts of landmark states.
_LANDMARK_COUNTS = integer_tuple(0, 2, "50,20")


def load_executions(labels: str | None, db_url: str | None) -> list[LabelledExecution]:
    """Labelled executions from a labels file, or the labelling database's completed episodes."""
    if labels is not None:
        from knotlab.labeling_db.interchange import read_labels

        return [item.execution for item in read_labels(labels)]
    from knotlab.labeling_db.store import open_store

    with open_store(db_url or default_db_url(), create=False, auto_upgrade=False) as store:
        return store.training_executions()


def _run(args: argparse.Namespace) -> int:
    from knotlab.core.atomic import check_output_dir
    from knotlab.core.errors import InvalidInputError
    from knotlab.core.selection.model_selection import QModelSearch, SelectBy
    from knotlab.core.selection.tries import read_tries

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    library_path = library_file(args)
    out_path = Path(args.out) if args.out else None
    if out_path is not None:  # before featurising and solving, not after
        check_output(out_path, force=args.force, kind="model")
    else:
        check_output_dir(defaults.MODELS_DIR, flag="--out (default folder)")
    tries = read_tries(args.tries) if args.tries else None  # a bad file: before the library
    library = load_library(library_path, args)
    executions = load_executions(args.labels, args.db)
    if not executions:
        raise InvalidInputError(
            f"no labelled executions in {args.labels or args.db or default_db_url()} "
            "(label some with `knotlab label` first)"
        )
    lib_hash = library.content_hash()
    other_lib = sum(1 for e in executions if e.library_hash not in (None, lib_hash))
    if other_lib:
        print(
            f"warning: {other_lib} of {len(executions)} executions were labelled with another "
            f"library than {lib_hash}; their features are recomputed with this one",
            file=sys.stderr,
        )
    search = QModelSearch(
        C=args.C,
        D=args.D,
        margin_scale=args.margin_scale,
        landmarks=args.landmarks,
        select=SelectBy(args.select),
        rank_features=args.rank_features,
        portable=args.portable,
        tries=tries,
        validation_fraction=args.validation_fraction,
        refit_all=args.refit_all,
        random_state=args.seed,
        workers=args.workers,
        progress=not args.no_progress,
        on_warning=lambda msg: print(f"warning: {msg}", file=sys.stderr),
    )
    search.fit(executions, library)
    best = search.best_
    model, validation, final = best.model, search.validation_, search.best_model_
    if len(search.sweep_) > 1:
        print("  C        D        val top-1  val top-3  val mean rank  val V-AUC  train top-1")
        nan = float("nan")
        for point in search.sweep_:
            v = point.validation or {
                "top1": nan,
                "top3": nan,
                "mean_expert_rank": nan,
                "value_auc": nan,
            }
            mark = "  <- chosen" if point is best else ""
            print(
                f"  {point.C:<8g} {point.D:<8g} {v['top1']:9.3f}  {v['top3']:9.3f}  "
                f"{v['mean_expert_rank']:13.2f}  {v['value_auc']:9.3f}  "
                f"{point.model.metrics['train_top1']:11.3f}{mark}"
            )
    info = {
        "labels": args.labels or (args.db or default_db_url()),
        "tries": args.tries,
        **search.info_,
    }
    final = dataclasses.replace(final, metrics={**final.metrics, "training_run": info})
    if out_path is None:  # never the shipped default: a new file named by the model's hash
        out_path = defaults.MODELS_DIR / f"model-{final.content_hash()}.npz"
    final.save(out_path)
    featurize_s, fit_s = search.featurize_s_, best.fit_s
    train_n, val_n = search.n_train_executions_, search.n_validation_executions_

    m = model.metrics
    print(
        f"knotlab train: {train_n} training executions ({m.get('n_states')} states, "
        f"{m.get('n_margin_rows')} margin rows, {m.get('n_bellman_rows')} Bellman rows, "
        f"{m.get('n_dead_ends')} dead ends), {val_n} held out; "
        f"featurised in {featurize_s:.1f} s, QP solved in {fit_s:.2f} s ({m.get('status')})"
    )
    print(
        f"  train:      top-1 {m['train_top1']:.3f}, mean expert rank "
        f"{m['train_mean_expert_rank']:.2f}"
        + (
            f", Bellman |error| {m['bellman_mean_abs_error']:.2f}"
            if "bellman_mean_abs_error" in m
            else ""
        )
    )
    if validation is not None:
        print(
            f"  validation: top-1 {validation['top1']:.3f}, top-3 {validation['top3']:.3f}, "
            f"mean expert rank {validation['mean_expert_rank']:.2f} "
            f"({validation['n_states']} states); V(expert state) > V(dead end) "
            f"{validation['value_auc']:.3f} of pairs ({validation['n_dead_ends']} dead ends)"
        )
    else:
        print("  validation: none (no held-out executions)")
    print(f"model {final.content_hash()} saved to {out_path}")
    if args.json:
        print(
            json.dumps(
                json_safe(
                    {
                        "model": str(out_path),
                        "model_hash": final.content_hash(),
                        "train_metrics": {k: v for k, v in m.items() if k != "training_run"},
                        **info,
                    }
                )
            )
        )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab train` to the command line."""
    p = subparsers.add_parser(
        "train",
        help="fit the max-margin Q-function on labelled executions and save the model",
        description=__doc__.split("\n\n")[0],
    )
    src = p.add_mutually_exclusive_group()
    add_flag(src, "--labels", default=None, detail="to train on (instead of --db)")
    add_db_argument(src)
    add_task_argument(p)
    add_flag(p, "--library", detail="default: the task's shipped library")
    p.add_argument(
        "--C",
        dest="C",
        type=_SLACK_WEIGHTS,
        default=[1.0],
        help="margin slack weight, >= 0; a comma list (0.1,1,10) is swept on the validation split",
    )
    p.add_argument(
        "--D",
        dest="D",
        type=_SLACK_WEIGHTS,
        default=[1.0],
        help="Bellman slack weight, >= 0; a comma list is swept like --C",
    )
    p.add_argument(
        "--margin-scale",
        type=number(0.0, above=True),
        default=1.0,
        help="value units the median margin is worth (1.0 = one step)",
    )
    p.add_argument(
        "--landmarks",
        type=_LANDMARK_COUNTS,
        default=(50, 20),
        help="landmark states sampled from the training split: LABELLED,DEAD_ENDS "
        "(default 50,20 as in the original; 0,0 for none)",
    )
    p.add_argument(
        "--rank-features",
        action="store_true",
        help="add where each demo stands in the state's registration-cost order (relative cost, "
        "rank one-hots) to the features",
    )
    p.add_argument(
        "--portable",
        action="store_true",
        help="fit on the columns any library computes alike (costs, their products, grasp "
        "distance, phase match; no demo one-hots, landmarks or per-step phases): a model "
        "another task can use (`knotlab model transfer`); --landmarks is then ignored",
    )
    reads(
        p.add_argument(
            "--tries",
            default=None,
            metavar="FILE",
            help="tried candidates of the labelled states (`knotlab labels tries`): no margin "
            "row against a demo that advanced as well as the label's, a full one against one "
            "that did not",
        )
    )
    add_flag(
        p,
        "--out",
        default=None,
        detail=f"the model (default: a new {defaults.MODELS_DIR.name}/model-HASH.npz in the "
        "working directory; the shipped default model is never overwritten implicitly)",
    )
    add_flag(p, "--force", detail="here: the model --out names")
    p.add_argument(
        "--select",
        choices=("top1", "value_auc"),
        default="top1",
        help="how a swept (C, D) is chosen on the validation split: expert demo ranked first "
        "(greedy's measure, default) or values that rank expert states above dead ends "
        "(lookahead's measure)",
    )
    p.add_argument(
        "--validation-fraction",
        type=number(0.0, maximum=1.0),
        default=0.2,
        help="share of executions held out for validation, 0 <= f < 1 (0.2)",
    )
    add_flag(p, "--seed", default=0, detail="of the train/validation split (0)")
    p.add_argument(
        "--refit-all", action="store_true", help="after validating, refit on every execution"
    )
    add_flag(p, "--workers", detail="they featurise the labelled states")
    add_no_progress_argument(p)
    add_flag(p, "--json", detail="a summary after the text")
    p.set_defaults(func=_run)
