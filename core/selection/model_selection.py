"""Model selection for the Q-function, scikit-learn style: split by execution, score, search, refit.

`knotlab train`, the app's retrain button and a notebook all call the same object:

    search = QModelSearch(C=[1, 10], D=[1, 10], landmarks=(50, 20), random_state=0)
    search.fit(executions, library)          # featurises once, fits every (C, D)
    search.best_model_, search.best_params_, search.validation_, search.sweep_

What it does, in order:
1. executions are split (seeded by ``random_state``, by execution, never by state, so the states
   of one episode never sit on both sides) into training and validation parts;
2. landmark states are sampled from the training part only (validation states stay unseen);
3. every execution is featurised once (one library scan per labelled state, over processes);
4. each (C, D) of the grid is fitted on the training part and scored on the validation part:
   ranking (top-1 agreement with the expert's demo, its mean rank) and value separation
   (``value_auc`` = P(V(expert state) > V(dead end)), the Mann-Whitney U statistic / (n1 n2));
5. the best is chosen by ``select`` ("top1": ranking, greedy's measure; "value_auc": value
   separation first, lookahead's measure), and with ``refit_all`` refitted on every execution.
The test set never enters: callers pass training executions only.
Shape suffixes: a = actions (demos), d = features.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import mannwhitneyu

from knotlab.core.errors import InvalidInputError, KnotlabError
from knotlab.core.parallel import PerProcess
from knotlab.core.selection.labels import LabelledExecution
from knotlab.core.selection.learner import LabelledState, MaxMarginQLearner, TrainingData
from knotlab.core.selection.qmodel import QModel

if TYPE_CHECKING:  # the featurizer pulls in registration (numba): imported where it is used
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.selection.features import LibraryFeaturizer
    from knotlab.core.selection.landmarks import Landmarks


class SelectBy(StrEnum):
    """How a swept (C, D) is chosen on the validation split."""

    TOP1 = "top1"  # expert's demo ranked first, then its mean rank (greedy's measure)
    VALUE_AUC = "value_auc"  # expert states valued above dead ends (lookahead's measure)


def split_executions(
    n: int, validation_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of training and validation executions (seeded; >= 1 of each when n >= 2)."""
    if not 0.0 <= validation_fraction < 1.0:
        raise InvalidInputError(f"validation fraction must be in [0, 1), got {validation_fraction}")
    order = np.random.default_rng(seed).permutation(n)
    n_val = round(validation_fraction * n)
    n_val = min(max(n_val, 1), n - 1) if validation_fraction > 0 and n >= 2 else 0
    return np.sort(order[n_val:]), np.sort(order[:n_val])


def merge_training_data(parts: Sequence[TrainingData]) -> TrainingData:
    """Concatenate per-execution training data, renumbering states and executions."""
    states: list[LabelledState] = []
    pairs: list[tuple[int, int]] = []
    goals: list[int] = []
    dead: list[np.ndarray] = []
    for e, part in enumerate(parts):
        off = len(states)
        states += [replace(s, execution=e) for s in part.states]
        pairs += [(i + off, j + off) for i, j in part.bellman_pairs]
        goals += [g + off for g in part.goal_states]
        dead += list(part.dead_ends_phi)
    return TrainingData(tuple(states), tuple(pairs), tuple(goals), tuple(dead))


def value_metrics(model: QModel, data: TrainingData) -> dict:
    """How well V(s) = max_a Q(s, a) tells expert states from dead ends (what lookahead uses)."""
    v_states = np.array([np.max(model.q(s.phi_ad)) for s in data.states])
    v_dead = np.array([np.max(model.q(phi)) for phi in data.dead_ends_phi])
    out = {
        "n_dead_ends": len(v_dead),
        "mean_value_states": float(v_states.mean()) if len(v_states) else float("nan"),
        "mean_value_dead_ends": float(v_dead.mean()) if len(v_dead) else float("nan"),
        "value_auc": float("nan"),
    }
    if len(v_states) and len(v_dead):
        # U / (n1 n2) = P(V_state > V_dead) + P(tie) / 2: the ROC AUC of values as a classifier.
        u = mannwhitneyu(v_states, v_dead, alternative="two-sided").statistic
        out["value_auc"] = float(u / (len(v_states) * len(v_dead)))
    return out


def ranking_metrics(model: QModel, data: TrainingData) -> dict:
    """Top-1/top-3 agreement with the expert, the expert demo's rank under Q, and value metrics."""
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


# --------------------------------------------------------------- featurising (worker processes)


def _build_featurizer(key: tuple[DemoLibrary, Landmarks | None, bool]) -> LibraryFeaturizer:
    from knotlab.core.selection.features import LibraryFeaturizer

    library, landmarks, rank_features = key
    return LibraryFeaturizer(library, landmarks=landmarks, rank_features=rank_features)


_FEATURIZER = PerProcess(_build_featurizer)  # this process's featurizer (set by the initializer)


def _init_featurizer(
    library: DemoLibrary, landmarks: Landmarks | None = None, rank_features: bool = False
) -> None:
    _FEATURIZER.get((library, landmarks, rank_features))


def _featurize(execution: LabelledExecution) -> TrainingData | str:
    """QP inputs of one execution, or why it cannot be used (a message)."""
    from knotlab.core.selection.learner import build_training_data

    try:
        return build_training_data([execution], _FEATURIZER.current())
    except (KnotlabError, ValueError, np.linalg.LinAlgError) as exc:
        return f"{type(exc).__name__}: {exc}"


def featurize_executions(
    executions: Sequence[LabelledExecution],
    library: DemoLibrary,
    *,
    workers: int | None = None,
    progress: bool = True,
    landmarks: Landmarks | None = None,
    rank_features: bool = False,
) -> tuple[list[TrainingData | None], list[str]]:
    """Per-execution training data (None where unusable) and the warnings about those."""
    from knotlab.core.parallel import map_processes

    results = map_processes(
        _featurize,
        list(executions),
        workers=workers,
        initializer=partial(_init_featurizer, library, landmarks, rank_features),
        desc="featurising labelled states",
        progress=progress,
    )
    parts: list[TrainingData | None] = []
    warnings: list[str] = []
    for ex, r in zip(executions, results, strict=True):
        if isinstance(r, str):
            warnings.append(f"execution {ex.execution_id} skipped: {r}")
            parts.append(None)
        else:
            parts.append(r)
    return parts, warnings


class FeatureCache:
    """Per-execution training data kept between fits, keyed by library, landmarks and execution.

    Featurising (one library scan per state) dominates a fit; a loop that refits on growing
    label sets (active learning, the app's retrain) reuses the rows of executions it has already
    featurised. Only valid while the landmark set is the same: it is part of the key.
    """

    def __init__(self) -> None:
        self._parts: dict[tuple[str, str | None, bool, str], TrainingData | str] = {}

    def __len__(self) -> int:
        return len(self._parts)

    def featurize(
        self,
        executions: Sequence[LabelledExecution],
        library: DemoLibrary,
        *,
        landmarks: Landmarks | None = None,
        workers: int | None = None,
        progress: bool = True,
        rank_features: bool = False,
    ) -> tuple[list[TrainingData | None], list[str]]:
        """Like `featurize_executions`, featurising only executions not seen before."""
        lm_hash = landmarks.content_hash() if landmarks is not None and len(landmarks) else None
        lib_hash = library.content_hash()
        keys = [(lib_hash, lm_hash, rank_features, ex.execution_id) for ex in executions]
        todo = {k: ex for k, ex in zip(keys, executions, strict=True) if k not in self._parts}
        if todo:
            parts, warnings = featurize_executions(
                list(todo.values()),
                library,
                workers=workers,
                progress=progress,
                landmarks=landmarks,
                rank_features=rank_features,
            )
            for k, part, ex in zip(todo, parts, todo.values(), strict=True):
                self._parts[k] = part if part is not None else _skip_reason(warnings, ex)
        out: list[TrainingData | None] = []
        msgs: list[str] = []
        for k in keys:
            got = self._parts[k]
            if isinstance(got, str):
                msgs.append(got)
                out.append(None)
            else:
                out.append(got)
        return out, msgs


def _skip_reason(warnings: list[str], execution: LabelledExecution) -> str:
    prefix = f"execution {execution.execution_id} skipped"
    return next((w for w in warnings if w.startswith(prefix)), f"{prefix}: unusable")


# --------------------------------------------------------------------------- the search object


@dataclass(frozen=True)
class SweepPoint:
    """One fitted (C, D): its model, validation scores (None without a validation split), time."""

    C: float
    D: float
    model: QModel
    validation: dict | None
    fit_s: float

    def score(self, select: SelectBy) -> tuple:
        """Sort key: larger is better."""
        if self.validation is None:
            m = self.model.metrics
            return (m["train_top1"], -m["train_mean_expert_rank"])
        ranking = (self.validation["top1"], -self.validation["mean_expert_rank"])
        if select is SelectBy.VALUE_AUC:
            auc = self.validation["value_auc"]
            return (auc if math.isfinite(auc) else -1.0, *ranking)
        return ranking


@dataclass
class QModelSearch:
    """Grid search over (C, D) for `MaxMarginQLearner`, validated by execution; see module doc."""

    C: Sequence[float] = (1.0,)
    D: Sequence[float] = (1.0,)
    margin_scale: float = 1.0
    landmarks: tuple[int, int] = (50, 20)  # labelled, dead-end landmark states (0, 0 = none)
    select: SelectBy = SelectBy.TOP1
    rank_features: bool = False  # the cost-rank columns of `LibraryFeaturizer`
    # Fit on the portable columns only (core/selection/transfer.py: no demo one-hots, landmarks
    # or per-step phases; landmark counts are then ignored): a model another task can use.
    portable: bool = False
    # Tried candidates (`core.selection.tries`) by (execution id, step): margin rows follow them
    tries: dict | None = field(default=None, repr=False)
    validation_fraction: float = 0.2
    # Executions held out by id (overrides the seeded fraction): a fixed validation set, so
    # models fitted on growing label sets are compared on the same held-out executions.
    validation_ids: frozenset[str] | None = None
    refit_all: bool = False
    random_state: int = 0
    workers: int | None = None
    progress: bool = True
    on_warning: Callable[[str], None] = field(default=lambda _msg: None, repr=False)
    feature_cache: FeatureCache | None = field(default=None, repr=False)

    def _check(self) -> None:
        for name in ("C", "D"):
            values = list(getattr(self, name))
            if not values or any(not (math.isfinite(v) and v >= 0) for v in values):
                raise InvalidInputError(f"{name} must be finite numbers >= 0, got {values}")
        if min(self.landmarks) < 0:
            raise InvalidInputError(f"landmark counts must be >= 0, got {self.landmarks}")
        self.select = SelectBy(self.select)

    def fit(self, executions: Sequence[LabelledExecution], library: DemoLibrary) -> QModelSearch:
        """Split, featurise, fit every (C, D), choose and (optionally) refit; returns self."""
        from knotlab.core.selection.features import LibraryFeaturizer
        from knotlab.core.selection.landmarks import sample_landmarks

        self._check()
        executions = list(executions)
        if not executions:
            raise InvalidInputError("no labelled executions to train on")
        if self.validation_ids is not None:
            held = np.array([e.execution_id in self.validation_ids for e in executions])
            train_idx, val_idx = np.flatnonzero(~held), np.flatnonzero(held)
        else:
            train_idx, val_idx = split_executions(
                len(executions), self.validation_fraction, self.random_state
            )
        counts = (0, 0) if self.portable else self.landmarks
        landmarks = sample_landmarks(
            [executions[i] for i in train_idx],
            n_labelled=counts[0],
            n_dead_ends=counts[1],
            seed=self.random_state,
        )
        t0 = time.perf_counter()
        featurize = (
            featurize_executions if self.feature_cache is None else self.feature_cache.featurize
        )
        parts, warnings = featurize(
            executions,
            library,
            workers=self.workers,
            progress=self.progress,
            landmarks=landmarks,
            rank_features=self.rank_features,
        )
        self.featurize_s_ = time.perf_counter() - t0
        for w in warnings:
            self.on_warning(w)
        n_tried = 0
        if self.tries:
            from knotlab.core.selection.tries import apply_tries

            keys = tuple(library.keys)
            n_tried = sum(
                (e.execution_id, st.step_index) in self.tries for e in executions for st in e.steps
            )
            parts = [
                None if p is None else apply_tries(p, e.execution_id, self.tries, keys)
                for p, e in zip(parts, executions, strict=True)
            ]
        train_parts = [parts[i] for i in train_idx if parts[i] is not None]
        val_parts = [parts[i] for i in val_idx if parts[i] is not None]
        if not train_parts:
            raise InvalidInputError("no usable training executions after featurising")
        train_data = merge_training_data(train_parts)
        val_data = merge_training_data(val_parts) if val_parts else None
        if val_data is not None and not val_data.states:
            val_data = None  # held-out executions with dead ends only: nothing to rank
        featurizer = LibraryFeaturizer(
            library, landmarks=landmarks, rank_features=self.rank_features
        )
        sweep: list[SweepPoint] = []
        for C in self.C:
            for D in self.D:
                learner = MaxMarginQLearner(C=C, D=D, margin_scale=self.margin_scale)
                t1 = time.perf_counter()
                try:
                    fitted = self._fit_one(learner, train_data, featurizer)
                except KnotlabError as exc:
                    self.on_warning(f"C={C:g}, D={D:g}: training failed: {exc}")
                    continue
                val = ranking_metrics(fitted, val_data) if val_data is not None else None
                sweep.append(SweepPoint(C, D, fitted, val, time.perf_counter() - t1))
        if not sweep:
            raise InvalidInputError("training failed for every (C, D)")
        best = max(sweep, key=lambda p: p.score(self.select))
        final = best.model
        refitted = bool(self.refit_all and val_parts)
        if refitted:
            learner = MaxMarginQLearner(C=best.C, D=best.D, margin_scale=self.margin_scale)
            final = self._fit_one(learner, merge_training_data(train_parts + val_parts), featurizer)
        self.sweep_ = sweep
        self.best_ = best
        self.best_params_ = {"C": best.C, "D": best.D}
        self.validation_ = best.validation
        self.landmarks_ = landmarks
        self.warnings_ = warnings
        self.n_train_executions_ = len(train_parts)
        self.n_validation_executions_ = len(val_parts)
        self.library_hash_ = library.content_hash()
        self.info_ = {
            "library_hash": self.library_hash_,
            "n_executions": len(executions),
            "n_train_executions": len(train_parts),
            "n_validation_executions": len(val_parts),
            "n_skipped_executions": len(warnings),
            "validation_fraction": self.validation_fraction,
            "split_seed": self.random_state,
            "refit_all": refitted,
            "validation": best.validation,
            "select": self.select.value,
            "rank_features": self.rank_features,
            "portable": self.portable,
            "tried_states": n_tried,
            "landmarks": {
                "labelled": self.landmarks[0],
                "dead_end": self.landmarks[1],
                "n": len(landmarks),
                "hash": landmarks.content_hash(),
            },
            "C": best.C,
            "D": best.D,
            "sweep": [
                {
                    "C": p.C,
                    "D": p.D,
                    "validation": p.validation,
                    "train_top1": p.model.metrics["train_top1"],
                }
                for p in sweep
            ],
            "featurize_s": round(self.featurize_s_, 3),
            "fit_s": round(best.fit_s, 3),
        }
        self.best_model_ = replace(final, metrics={**final.metrics, "training_run": self.info_})
        return self

    def _fit_one(
        self, learner: MaxMarginQLearner, data: TrainingData, featurizer: LibraryFeaturizer
    ) -> QModel:
        """One fit on the featurizer's columns, or on its portable ones placed back onto them
        (weight 0 on the rest) when ``portable``."""
        if not self.portable:
            return learner.fit(data, featurizer)
        from knotlab.core.selection.transfer import (
            PortableColumns,
            project_training_data,
            transplant,
        )

        spec = featurizer.feature_spec
        columns = PortableColumns.of(spec)
        fitted = learner.fit(project_training_data(data, spec.names, columns.names), columns)
        # Trained on this library's own labels: its metrics are its own, not a transplant's.
        return replace(transplant(fitted, spec), metrics={**fitted.metrics, "portable": True})
