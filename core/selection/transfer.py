"""Q-models across libraries and tasks: the columns that mean the same everywhere, and moving
a model's weights on them onto another library's feature spec.

A model's columns are of two kinds. *Portable* ones are computed the same way from any library's
registration of any task's rope: the three registration costs, their six products, the grasp
distance, phase_match (does this demo's step look like the state's?) and, when on, the cost-rank
columns. The rest belong to one library: a one-hot per demo, a softmax weight per landmark state,
and phase_k per demo step (a task with four steps has four). The paper calls its features
task-independent; this module is how that claim is tested: fit on the portable columns of one
task's labels, or of several tasks' labels pooled, and rank another task's demos with them.

The per-library columns get weight 0 in a transplanted model. phase_k and the landmark weights
are the same for every demo of a state, so they shift Q by a constant per state and never change
a greedy ranking; they do shape V(s) = max_a Q(s, a), so lookahead with a transplanted model
values states by the portable columns alone.
Shape suffixes: a = actions (demos), d = feature columns.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.feature_spec import FeatureSpec
from knotlab.core.selection.learner import LabelledState, TrainingData
from knotlab.core.selection.qmodel import QModel

# Columns of one library: a demo's one-hot, a landmark's weight, a demo step's phase.
# (A pooled model names another library's such column "<library>:demo[...]".)
_PER_LIBRARY = re.compile(r"^(?:[^:\[]+:)?(demo\[.*\]|landmark\[.*\]|phase_\d+)$")
PORTABLE_FEATURE_SET = "knotlab-portable-v1"


def is_portable(name: str) -> bool:
    """True for a column computed the same way from any library and task."""
    return _PER_LIBRARY.match(name) is None


def portable_names(spec: FeatureSpec) -> tuple[str, ...]:
    """The spec's portable columns, in its order."""
    return tuple(n for n in spec.names if is_portable(n))


@dataclass(frozen=True)
class PortableColumns:
    """The column set a portable model is fitted on: names, which are one-hots, the phase
    temperature and observation model they were computed with (a learner's ``spec()`` source)."""

    names: tuple[str, ...]
    indicator_mask: tuple[bool, ...]
    phase_temperature: float
    observation_model: str
    rank_features: bool = False
    landmarks: None = None  # what the learner reads from a featurizer: portable models have none

    @classmethod
    def of(cls, spec: FeatureSpec) -> PortableColumns:
        """The portable part of a library's feature spec."""
        keep = [i for i, n in enumerate(spec.names) if is_portable(n)]
        if not keep:
            raise InvalidInputError("the feature spec has no portable columns")
        return cls(
            tuple(spec.names[i] for i in keep),
            tuple(spec.indicator_mask[i] for i in keep),
            spec.phase_temperature,
            spec.observation_model,
            spec.rank_features,
        )

    def check_same(self, other: PortableColumns) -> None:
        """Raise unless two libraries' portable columns can be pooled in one fit."""
        if other != self:
            raise InvalidInputError(
                "the libraries' portable columns differ (names, phase temperature, observation "
                f"model or rank features): {self.names} vs {other.names}"
            )

    def spec(self) -> dict:
        """The spec dict saved with a model fitted on these columns (no library, no task)."""
        return {
            "feature_set": PORTABLE_FEATURE_SET,
            "library_hash": "",
            "action_keys": [],
            "names": list(self.names),
            "indicator_mask": list(self.indicator_mask),
            "phase_steps": [],
            "phase_temperature": self.phase_temperature,
            "landmark_hash": None,
            "observation_model": self.observation_model,
            "rank_features": self.rank_features,
            "task": "",
        }


def project_training_data(
    data: TrainingData, names: Sequence[str], keep: Sequence[str]
) -> TrainingData:
    """The same QP inputs with only the columns ``keep`` (by name, in that order)."""
    index = {n: i for i, n in enumerate(names)}
    missing = [n for n in keep if n not in index]
    if missing:
        raise InvalidInputError(f"training data has no column {missing[0]!r}")
    cols = np.array([index[n] for n in keep], dtype=int)
    states = tuple(replace(s, phi_ad=s.phi_ad[:, cols]) for s in data.states)
    dead = tuple(phi[:, cols] for phi in data.dead_ends_phi)
    return TrainingData(states, data.bellman_pairs, data.goal_states, dead)


def pool_portable(
    parts: Sequence[tuple[TrainingData, FeatureSpec]],
) -> tuple[TrainingData, PortableColumns]:
    """Several libraries' (or tasks') QP inputs on their shared portable columns, in one set.

    Each part is one library's training data with the spec its columns follow; states keep
    their Bellman links and dead ends within their part (executions are renumbered).
    """
    return _pool([(str(i), data, spec) for i, (data, spec) in enumerate(parts)], own=False)


def pool_with_own_columns(
    parts: Sequence[tuple[str, TrainingData, FeatureSpec]],
) -> tuple[TrainingData, PortableColumns]:
    """Like :func:`pool_portable`, plus each part's demo one-hots as columns of its own, named
    ``<part>:demo[...]`` (zero in every other part's states): shared weights on the portable
    columns, a per-demo prior per library."""
    return _pool(parts, own=True)


def _pool(
    parts: Sequence[tuple[str, TrainingData, FeatureSpec]], *, own: bool
) -> tuple[TrainingData, PortableColumns]:
    if not parts:
        raise InvalidInputError("nothing to pool")
    base = PortableColumns.of(parts[0][2])
    demos = [
        f"{name}:{n}" for name, _, spec in parts if own for n in spec.names if n.startswith("demo[")
    ]
    names = base.names + tuple(demos)
    states: list[LabelledState] = []
    pairs: list[tuple[int, int]] = []
    goals: list[int] = []
    dead: list[np.ndarray] = []
    n_exec = 0
    for name, data, spec in parts:
        base.check_same(PortableColumns.of(spec))
        take, keep = _column_sources(name, spec.names, names)

        def place(
            phi_ad: np.ndarray, take: np.ndarray = take, keep: np.ndarray = keep
        ) -> np.ndarray:
            return np.where(keep, phi_ad[:, take], 0.0)  # another library's columns: 0

        off = len(states)
        states += [
            replace(s, phi_ad=place(s.phi_ad), execution=s.execution + n_exec) for s in data.states
        ]
        n_exec += 1 + max((s.execution for s in data.states), default=-1)
        pairs += [(i + off, j + off) for i, j in data.bellman_pairs]
        goals += [g + off for g in data.goal_states]
        dead += [place(phi) for phi in data.dead_ends_phi]
    columns = replace(base, names=names, indicator_mask=base.indicator_mask + (True,) * len(demos))
    return TrainingData(tuple(states), tuple(pairs), tuple(goals), tuple(dead)), columns


def _column_sources(
    part: str, names: Sequence[str], pooled: Sequence[str]
) -> tuple[np.ndarray, np.ndarray]:
    """For each pooled column, the part's own column it is read from, and whether there is
    one (portable columns by name; ``<part>:x`` from the part's column ``x``)."""
    index = {n: i for i, n in enumerate(names)}
    prefix = f"{part}:"
    src = []
    for n in pooled:
        if n.startswith(prefix):
            src.append(index.get(n.removeprefix(prefix), -1))
        elif is_portable(n):
            src.append(index.get(n, -1))
        else:
            src.append(-1)  # another part's own column
    src_arr = np.asarray(src, dtype=int)
    return np.maximum(src_arr, 0), src_arr >= 0


def transplant(
    model: QModel, target: FeatureSpec, *, also: Mapping[str, str] | None = None
) -> QModel:
    """``model``'s weights on the portable columns, placed on ``target``'s columns (another
    library's, possibly another task's); every per-library column of ``target`` gets weight 0.

    Its ranking of any state's demos is the source model's portable part (exactly its Q when
    the source was fitted on portable columns alone). ``target`` must have no landmarks.
    ``also`` maps more of the model's columns to target columns to carry (a pooled model's
    per-library columns onto that library's own: ``<library>:demo[k]`` -> ``demo[k]``).
    """
    if target.landmark_hash is not None:
        raise InvalidInputError(
            "transplant onto a feature spec without landmarks (its landmark columns would "
            "refer to states the source model never saw)"
        )
    source = model.feature_spec
    if source.phase_temperature != target.phase_temperature:
        raise InvalidInputError(
            f"phase temperatures differ (model {source.phase_temperature}, "
            f"target {target.phase_temperature}): phase_match would mean another thing"
        )
    if source.observation_model != target.observation_model:
        raise InvalidInputError(
            f"the model was fitted on '{source.observation_model}' observations, the target "
            f"library's are '{target.observation_model}'"
        )
    src_index = {n: i for i, n in enumerate(source.names) if is_portable(n)}
    for src_name, dst_name in (also or {}).items():
        if src_name not in source.names or dst_name not in target.names:
            raise InvalidInputError(f"cannot carry column {src_name!r} to {dst_name!r}")
        src_index[dst_name] = source.names.index(src_name)
    d = len(target.names)
    w = np.zeros(d)
    mean = np.zeros(d)
    scale = np.ones(d)
    moved: list[str] = []
    for j, name in enumerate(target.names):
        i = src_index.get(name)
        if i is None:
            continue
        w[j], mean[j], scale[j] = (
            model.weights_d[i],
            model.feature_mean_d[i],
            model.feature_scale_d[i],
        )
        moved.append(name)
    lost = [n for n in source.names if is_portable(n) and n not in moved]
    if lost:
        raise InvalidInputError(
            f"the target spec lacks the model's portable column {lost[0]!r} "
            "(rank features on one side only?)"
        )
    provenance = {
        "model_hash": model.content_hash(),
        "task": source.task,
        "feature_set": source.feature_set,
        "library_hash": source.library_hash,
        "columns": moved,
    }
    run = model.metrics.get("training_run") or {}
    if run.get("validation"):  # the source's own held-out scores, on the source's task
        provenance["source_validation"] = run["validation"]
    # The source's training metrics describe its own columns and labels, not this model: they
    # are left behind (a transplanted model has been trained on nothing of the target's).
    return QModel(
        w,
        model.bias,
        mean,
        scale,
        target.to_dict(),
        dict(model.hyperparameters),
        {"transplanted_from": provenance},
        None,
    )
