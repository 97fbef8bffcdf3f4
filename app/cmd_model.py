"""`knotlab model info`: what a saved QModel is: features, hashes, settings and how it scored."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from knotlab.app.options import add_flag
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
    run = s["training_run"] or {}
    val = run.get("validation")
    if val:
        print(
            f"  validation:    top-1 {val['top1']:.3f}, top-3 {val['top3']:.3f}, mean expert rank "
            f"{val['mean_expert_rank']:.2f} ({val['n_states']} states; labels {run.get('labels')})"
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
