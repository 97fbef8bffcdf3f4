"""`knotlab model info`: what a saved QModel is: features, hashes, settings and how it scored.
`knotlab model transfer`: a model's portable weights moved onto another task's library."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from knotlab.app.options import (
    add_flag,
    add_task_argument,
    check_input,
    check_output,
    library_file,
    load_library,
)
from knotlab.core.jsonsafe import json_safe

if TYPE_CHECKING:
    from knotlab.core.selection.qmodel import QModel

# Training metrics worth a line in the text view (the rest are in --json).
_SHOWN_METRICS = ("train_top1", "train_mean_expert_rank", "bellman_mean_abs_error", "status")


def model_summary(model: QModel) -> dict:
    """The `knotlab model info --json` keys of a loaded QModel."""
    spec = model.feature_spec  # (models saved before observation_model read as 'cloud')
    return {
        "hash": model.content_hash(),
        "library_hash": spec.library_hash,
        "observation_model": spec.observation_model,
        "feature_set": spec.feature_set,
        "n_features": model.n_features,
        "feature_names": list(spec.names),
        "n_actions": len(spec.action_keys),
        "landmark_hash": spec.landmark_hash,
        "hyperparameters": model.hyperparameters,
        "metrics": {k: v for k, v in model.metrics.items() if k != "training_run"},
        "training_run": model.metrics.get("training_run"),
    }


def run_info(args: argparse.Namespace) -> int:
    """Load (validating) a model and print what it is."""
    from knotlab.core.selection.qmodel import QModel

    s = model_summary(QModel.load(args.path))
    if args.json:
        print(json.dumps(json_safe({"path": str(args.path), **s}), sort_keys=True))
        return 0
    print(f"{args.path}: knotlab QModel, hash {s['hash']}")
    print(f"  library:       {s['library_hash']} ({s['n_actions']} demos)")
    print(f"  observation:   {s['observation_model']}")
    names = s["feature_names"]
    more = f", ... ({len(names) - 12} more; all in --json)" if len(names) > 12 else ""
    print(f"  features:      {s['n_features']} ({s['feature_set']}): {', '.join(names[:12])}{more}")
    print(f"  landmarks:     {s['landmark_hash'] or 'none'}")
    hyper = ", ".join(f"{k}={v}" for k, v in s["hyperparameters"].items())
    print(f"  hyper-params:  {hyper}")
    metrics = s["metrics"]
    shown = [
        f"{k}={metrics[k]:.3g}" if isinstance(metrics[k], float) else f"{k}={metrics[k]}"
        for k in _SHOWN_METRICS
        if k in metrics
    ]
    print(f"  training:      {', '.join(shown) or '-'}")
    moved = metrics.get("transplanted_from")
    if moved:
        print(
            f"  transplanted: from the {moved['task']} model {moved['model_hash']} (library "
            f"{moved['library_hash']}), {len(moved['columns'])} portable columns; not trained "
            "on this library's labels"
        )
    run = s["training_run"] or {}
    val = run.get("validation")
    if val:
        print(
            f"  validation:    top-1 {val['top1']:.3f}, top-3 {val['top3']:.3f}, mean expert rank "
            f"{val['mean_expert_rank']:.2f} ({val['n_states']} states; labels {run.get('labels')})"
        )
    return 0


def run_transfer(args: argparse.Namespace) -> int:
    """Move a model's weights on the portable columns onto a task's library and save it."""
    from pathlib import Path

    from knotlab.core.selection.features import LibraryFeaturizer
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.selection.transfer import transplant

    out = check_output(Path(args.out), force=args.force, kind="model")
    # Both inputs before either is read: a missing one is named, whichever it is.
    source = check_input(args.path, flag="PATH", kind="model")
    library_path = library_file(args)
    if args.library:
        library_path = check_input(library_path, flag="--library", kind="demo library")
    model = QModel.load(source)
    library = load_library(library_path, args)
    target = LibraryFeaturizer(
        library,
        phase_temperature=model.feature_spec.phase_temperature,
        rank_features=model.feature_spec.rank_features,
    ).feature_spec
    moved = transplant(model, target)
    moved.save(out)
    columns = moved.metrics["transplanted_from"]["columns"]
    summary = {
        "model": str(out),
        "model_hash": moved.content_hash(),
        "from_model_hash": model.content_hash(),
        "from_task": model.feature_spec.task,
        "task": library.task,
        "library_hash": library.content_hash(),
        "columns": columns,
        "zeroed": [n for n in target.names if n not in columns],
    }
    if args.json:
        print(json.dumps(json_safe(summary), sort_keys=True))
        return 0
    print(
        f"model {summary['model_hash']} saved to {out}: the {summary['from_task']} model "
        f"{summary['from_model_hash']}'s weights on {len(columns)} portable columns "
        f"({', '.join(columns)}) on the {library.task} library {summary['library_hash']}; "
        f"its {len(summary['zeroed'])} per-library columns (demo, phase, landmark) get weight 0"
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab model info` to the command line."""
    parser = subparsers.add_parser("model", help="inspect a trained Q-function model")
    sub = parser.add_subparsers(dest="model_command", required=True, metavar="ACTION")
    info = sub.add_parser(
        "info",
        help="features, hashes, observation model, hyper-parameters and training metrics",
    )
    info.add_argument("path", help="model file (.npz) written by `knotlab train`")
    add_flag(info, "--json")
    info.set_defaults(func=run_info)
    transfer = sub.add_parser(
        "transfer",
        help="a model's weights on the portable columns (costs, grasp distance, phase match) "
        "moved onto another task's library, the per-library columns zeroed: no retraining",
    )
    transfer.add_argument("path", help="model file (.npz) written by `knotlab train`")
    add_task_argument(transfer)
    add_flag(transfer, "--library", detail="default: the task's shipped library")
    add_flag(transfer, "--out", required=True, detail="the moved model (.npz)")
    add_flag(transfer, "--force")
    add_flag(transfer, "--json")
    transfer.set_defaults(func=run_transfer)
