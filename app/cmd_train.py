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
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from app import defaults
from core.errors import KnotlabError
from core.labels import LabelledExecution
from core.learn import LabelledState, QModel, TrainingData

log = logging.getLogger(__name__)


def _float_list(text: str) -> list[float]:
    """'0.1,1,10' -> [0.1, 1.0, 10.0] (argparse type)."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas, got {text!r}"
        ) from None
    if not values or any(not math.isfinite(v) or v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected finite non-negative numbers, got {text!r}")
    return values


def _count_pair(text: str) -> tuple[int, int]:
    """'50,20' -> (50, 20) (argparse type)."""
    parts = text.split(",")
    try:
        pair = tuple(int(v) for v in parts)
    except ValueError:
        pair = ()
    if len(pair) != 2 or min(pair) < 0:
        raise argparse.ArgumentTypeError(f"expected two counts >= 0 like 50,20, got {text!r}")
    return pair


def _fail(message: str) -> int:
    print(f"knotlab train: error: {message}", file=sys.stderr)
    return 2


def load_executions(labels: str | None, db_url: str | None) -> list[LabelledExecution]:
    """Labelled executions from a labels file, or the labelling database's completed episodes."""
    if labels is not None:
        from labeling_db.interchange import read_labels

        return [item.execution for item in read_labels(labels)]
    from labeling_db.store import open_store

    with open_store(db_url or defaults.DB_URL, create=False, auto_upgrade=False) as store:
        return store.training_executions()


def split_executions(
    n: int, validation_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of training and validation executions (seeded; >= 1 of each when n >= 2)."""
    if not 0.0 <= validation_fraction < 1.0:
        raise ValueError(f"validation fraction must be in [0, 1), got {validation_fraction}")
    order = np.random.default_rng(seed).permutation(n)
    n_val = round(validation_fraction * n)
    n_val = min(max(n_val, 1), n - 1) if validation_fraction > 0 and n >= 2 else 0
    return np.sort(order[n_val:]), np.sort(order[:n_val])


# --------------------------------------------------------------- featurising (worker processes)

_FEATURIZER = None  # this process's LibraryFeaturizer, built once by the initializer


def _init_featurizer(library, landmarks=None) -> None:
    global _FEATURIZER
    from core.features import LibraryFeaturizer

    _FEATURIZER = LibraryFeaturizer(library, landmarks=landmarks)


def _featurize(execution: LabelledExecution) -> TrainingData | str:
    """QP inputs of one execution, or why it cannot be used (a message)."""
    from core.learn import build_training_data

    try:
        return build_training_data([execution], _FEATURIZER)
    except (KnotlabError, ValueError, np.linalg.LinAlgError) as exc:
        return f"{type(exc).__name__}: {exc}"


def merge_training_data(parts: Sequence[TrainingData]) -> TrainingData:
    """Concatenate per-execution training data, renumbering states and executions."""
    states: list[LabelledState] = []
    pairs: list[tuple[int, int]] = []
    goals: list[int] = []
    dead: list[np.ndarray] = []
    for e, part in enumerate(parts):
        off = len(states)
        states += [
            LabelledState(s.phi_ad, s.expert_action, s.margins_a, e, s.step) for s in part.states
        ]
        pairs += [(i + off, j + off) for i, j in part.bellman_pairs]
        goals += [g + off for g in part.goal_states]
        dead += list(part.dead_ends_phi)
    return TrainingData(tuple(states), tuple(pairs), tuple(goals), tuple(dead))


def featurize_executions(
    executions: Sequence[LabelledExecution],
    library,
    *,
    workers: int | None,
    progress: bool,
    landmarks=None,
) -> tuple[list[TrainingData | None], list[str]]:
    """Per-execution training data (None where unusable) and the warnings about those."""
    results = _map_featurize(executions, library, workers, progress, landmarks)
    parts: list[TrainingData | None] = []
    warnings: list[str] = []
    for ex, r in zip(executions, results, strict=True):
        if isinstance(r, str):
            warnings.append(f"execution {ex.execution_id} skipped: {r}")
            parts.append(None)
        else:
            parts.append(r)
    return parts, warnings


def _map_featurize(executions, library, workers, progress, landmarks):
    from functools import partial

    from core.parallel import map_processes

    return map_processes(
        _featurize,
        list(executions),
        workers=workers,
        initializer=partial(_init_featurizer, library, landmarks),
        desc="featurising labelled states",
        progress=progress,
    )


def ranking_metrics(model: QModel, data: TrainingData) -> dict:
    """Top-1 agreement with the expert and the expert demo's mean rank (0 = first) under Q."""
    ranks = []
    for s in data.states:
        q = model.q(s.phi_ad)
        ranks.append(int(np.sum(q > q[s.expert_action])))
    r = np.asarray(ranks)
    return {
        "n_states": len(ranks),
        "top1": float(np.mean(r == 0)),
        "top3": float(np.mean(r < 3)),
        "mean_expert_rank": float(r.mean()),
        "median_expert_rank": float(np.median(r)),
        **value_metrics(model, data),
    }


def value_metrics(model: QModel, data: TrainingData) -> dict:
    """How well V(s) = max_a Q(s, a) tells expert states from dead ends (what lookahead uses).

    ``value_auc`` is P(V(expert state) > V(dead end)) over all pairs (0.5 = no better than chance).
    """
    v_states = np.array([np.max(model.q(s.phi_ad)) for s in data.states])
    v_dead = np.array([np.max(model.q(phi)) for phi in data.dead_ends_phi])
    out = {
        "n_dead_ends": len(v_dead),
        "mean_value_states": float(v_states.mean()) if len(v_states) else float("nan"),
        "mean_value_dead_ends": float(v_dead.mean()) if len(v_dead) else float("nan"),
        "value_auc": float("nan"),
    }
    if len(v_states) and len(v_dead):
        greater = (v_states[:, None] > v_dead[None, :]).mean()
        ties = (v_states[:, None] == v_dead[None, :]).mean()
        out["value_auc"] = float(greater + 0.5 * ties)
    return out


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.floating | np.integer):
        return _json_safe(value.item())
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _run(args: argparse.Namespace) -> int:
    from core.demos import DemoLibrary
    from core.features import LibraryFeaturizer
    from core.landmarks import sample_landmarks
    from core.learn import MaxMarginQLearner

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.labels is not None and args.db is not None:
        return _fail("give --labels or --db, not both")
    library_path = Path(args.library) if args.library else defaults.LIBRARY_PATH
    out_path = Path(args.out) if args.out else defaults.MODEL_PATH
    try:
        library = DemoLibrary.load(library_path)
    except (FileNotFoundError, KnotlabError) as exc:
        return _fail(str(exc))
    try:
        executions = load_executions(args.labels, args.db)
    except FileNotFoundError as exc:
        return _fail(f"labels file not found: {exc.filename or exc}")
    except Exception as exc:  # labeling_db errors: one clear line, not a traceback
        return _fail(f"cannot read labels: {type(exc).__name__}: {exc}")
    if not executions:
        return _fail("no labelled executions found (label some with `knotlab label` first)")
    lib_hash = library.content_hash()
    other_lib = sum(1 for e in executions if e.library_hash not in (None, lib_hash))
    if other_lib:
        print(
            f"warning: {other_lib} of {len(executions)} executions were labelled with another "
            f"library than {lib_hash}; their features are recomputed with this one",
            file=sys.stderr,
        )
    try:
        train_idx, val_idx = split_executions(len(executions), args.validation_fraction, args.seed)
    except ValueError as exc:
        return _fail(str(exc))

    # Landmarks come from the training split only, so validation states stay unseen.
    n_landmark_labelled, n_landmark_dead = args.landmarks
    landmarks = sample_landmarks(
        [executions[i] for i in train_idx],
        n_labelled=n_landmark_labelled,
        n_dead_ends=n_landmark_dead,
        seed=args.seed,
    )
    t0 = time.perf_counter()
    parts, warnings = featurize_executions(
        executions,
        library,
        workers=args.workers,
        progress=not args.no_progress,
        landmarks=landmarks,
    )
    featurize_s = time.perf_counter() - t0
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    train_parts = [parts[i] for i in train_idx if parts[i] is not None]
    val_parts = [parts[i] for i in val_idx if parts[i] is not None]
    if not train_parts:
        return _fail("no usable training executions after featurising (see warnings)")
    train_data = merge_training_data(train_parts)
    val_data = merge_training_data(val_parts) if val_parts else None
    if val_data is not None and not val_data.states:
        val_data = None  # held-out executions with dead ends only: nothing to rank
    featurizer = LibraryFeaturizer(library, landmarks=landmarks)
    # A grid of (C, D) is fitted on the training split and ranked on the validation split only
    # (top-1 agreement with the expert, then the expert's mean rank): the test set never
    # chooses hyper-parameters.
    sweep = []
    for C in args.C:
        for D in args.D:
            learner = MaxMarginQLearner(
                C=C, D=D, margin_scale=args.margin_scale, featurizer=featurizer
            )
            t1 = time.perf_counter()
            try:
                fitted = learner.fit(train_data)
            except KnotlabError as exc:
                print(f"warning: C={C:g}, D={D:g}: training failed: {exc}", file=sys.stderr)
                continue
            val = ranking_metrics(fitted, val_data) if val_data is not None else None
            sweep.append((C, D, fitted, val, learner, time.perf_counter() - t1))
    if not sweep:
        return _fail("training failed for every (C, D)")

    def score(entry):
        _, _, fitted, val, _, _ = entry
        if val is None:
            return (fitted.metrics["train_top1"], -fitted.metrics["train_mean_expert_rank"])
        ranking = (val["top1"], -val["mean_expert_rank"])
        if args.select == "value_auc":  # for lookahead: values that tell dead ends apart
            auc = val["value_auc"]
            return (auc if math.isfinite(auc) else -1.0, *ranking)
        return ranking

    best = max(sweep, key=score)
    C_best, D_best, model, validation, learner, fit_s = best
    if len(sweep) > 1:
        print("  C        D        val top-1  val top-3  val mean rank  val V-AUC  train top-1")
        for C, D, fitted, val, _, _ in sweep:
            v = val or {
                "top1": float("nan"),
                "top3": float("nan"),
                "mean_expert_rank": float("nan"),
                "value_auc": float("nan"),
            }
            mark = "  <- chosen" if (C_best, D_best) == (C, D) else ""
            print(
                f"  {C:<8g} {D:<8g} {v['top1']:9.3f}  {v['top3']:9.3f}  "
                f"{v['mean_expert_rank']:13.2f}  {v['value_auc']:9.3f}  "
                f"{fitted.metrics['train_top1']:11.3f}{mark}"
            )
    final = model
    if args.refit_all and val_parts:
        final = learner.fit(merge_training_data(train_parts + val_parts))
    info = {
        "labels": args.labels or (args.db or defaults.DB_URL),
        "library_hash": lib_hash,
        "n_executions": len(executions),
        "n_train_executions": len(train_parts),
        "n_validation_executions": len(val_parts),
        "n_skipped_executions": len(warnings),
        "validation_fraction": args.validation_fraction,
        "split_seed": args.seed,
        "refit_all": bool(args.refit_all and val_parts),
        "validation": validation,
        "select": args.select,
        "landmarks": {
            "labelled": n_landmark_labelled,
            "dead_end": n_landmark_dead,
            "n": len(landmarks),
            "hash": landmarks.content_hash(),
        },
        "C": C_best,
        "D": D_best,
        "sweep": [
            {"C": C, "D": D, "validation": val, "train_top1": f.metrics["train_top1"]}
            for C, D, f, val, _, _ in sweep
        ],
        "featurize_s": round(featurize_s, 3),
        "fit_s": round(fit_s, 3),
    }
    final = dataclasses.replace(final, metrics={**final.metrics, "training_run": info})
    final.save(out_path)

    m = model.metrics
    print(
        f"knotlab train: {len(train_parts)} training executions ({m.get('n_states')} states, "
        f"{m.get('n_margin_rows')} margin rows, {m.get('n_bellman_rows')} Bellman rows, "
        f"{m.get('n_dead_ends')} dead ends), {len(val_parts)} held out; "
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
                _json_safe(
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
    src.add_argument("--labels", default=None, help="labels file (.jsonl or .csv) to train on")
    src.add_argument(
        "--db",
        default=None,
        help=f"labelling database URL (default when no --labels: {defaults.DB_URL})",
    )
    p.add_argument(
        "--library", default=None, help=f"demo library (default {defaults.LIBRARY_PATH})"
    )
    p.add_argument(
        "--C",
        dest="C",
        type=_float_list,
        default=[1.0],
        help="margin slack weight; a comma list (0.1,1,10) is swept on the validation split",
    )
    p.add_argument(
        "--D",
        dest="D",
        type=_float_list,
        default=[1.0],
        help="Bellman slack weight; a comma list is swept like --C",
    )
    p.add_argument(
        "--margin-scale",
        type=float,
        default=1.0,
        help="value units the median margin is worth (1.0 = one step)",
    )
    p.add_argument(
        "--landmarks",
        type=_count_pair,
        default=(50, 20),
        help="landmark states sampled from the training split: LABELLED,DEAD_ENDS "
        "(default 50,20 as in the original; 0,0 for none)",
    )
    p.add_argument("--out", default=None, help=f"model file (default {defaults.MODEL_PATH})")
    p.add_argument(
        "--select",
        choices=("top1", "value_auc"),
        default="top1",
        help="how a swept (C, D) is chosen on the validation split: expert demo ranked first "
        "(greedy's measure, default) or values that rank expert states above dead ends "
        "(lookahead's measure)",
    )
    p.add_argument("--validation-fraction", type=float, default=0.2)
    p.add_argument("--seed", type=int, default=0, help="seed of the train/validation split")
    p.add_argument(
        "--refit-all", action="store_true", help="after validating, refit on every execution"
    )
    p.add_argument(
        "--workers", type=int, default=None, help="featurising processes (default: cores)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    p.set_defaults(func=_run)
