"""Landmark states: a fixed sample of labelled and dead-end clouds that state features refer to.

The original sampled 20 failure states and 50 labelled states at random (docs/reference/learning.md,
"Landmarks") and described a state by its registration cost to each. Those costs, turned into a
softmax, let the value V(s) = max_a Q(s, a) tell "looks like a state the expert went on from" apart
from "looks like a dead end", which the Bellman and dead-end rows of the QP can then learn; the
greedy ranking within a state is unaffected (the columns are the same for every action).
Landmarks come from *training* executions only and travel inside the model file.
Shape suffixes: n = points, l = landmarks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from knotlab.core.arrays import points_n3
from knotlab.core.errors import InvalidInputError
from knotlab.core.hashing import ContentHash
from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.labels import LabelledExecution

LANDMARK_KINDS = ("labelled", "dead_end")


@dataclass(frozen=True, eq=False)
class Landmarks:
    """Landmark clouds and what each one is (a state the expert labelled, or a dead end)."""

    clouds: tuple[np.ndarray, ...]
    kinds: tuple[str, ...]

    def __post_init__(self) -> None:
        if len(self.clouds) != len(self.kinds):
            raise InvalidInputError(
                f"{len(self.clouds)} landmark clouds but {len(self.kinds)} kinds"
            )
        bad = sorted({k for k in self.kinds} - set(LANDMARK_KINDS))
        if bad:
            raise InvalidInputError(f"unknown landmark kinds {bad}; expected {LANDMARK_KINDS}")
        clouds = tuple(points_n3(f"landmark {i}", c) for i, c in enumerate(self.clouds))
        object.__setattr__(self, "clouds", clouds)
        object.__setattr__(self, "kinds", tuple(self.kinds))

    def __len__(self) -> int:
        return len(self.clouds)

    def content_hash(self) -> str:
        """SHA-256 (hex, 16 chars) of the clouds and kinds."""
        h = ContentHash()
        for cloud, kind in zip(self.clouds, self.kinds, strict=True):
            h.text(kind).array(np.int64(len(cloud))).array(cloud, dtype="<f8")
        return h.hexdigest()

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat arrays for an .npz file: points, per-landmark sizes, kind codes."""
        if not self.clouds:
            return {
                "landmark_points_n3": np.zeros((0, 3)),
                "landmark_sizes_l": np.zeros(0, dtype=np.int64),
                "landmark_kinds_l": np.zeros(0, dtype=np.int64),
            }
        return {
            "landmark_points_n3": np.concatenate(self.clouds).astype(float),
            "landmark_sizes_l": np.array([len(c) for c in self.clouds], dtype=np.int64),
            "landmark_kinds_l": np.array(
                [LANDMARK_KINDS.index(k) for k in self.kinds], dtype=np.int64
            ),
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Landmarks:
        """Inverse of :meth:`to_arrays` (raises InvalidInputError on inconsistent arrays)."""
        points = np.asarray(arrays["landmark_points_n3"], dtype=float)
        sizes = np.asarray(arrays["landmark_sizes_l"], dtype=np.int64)
        codes = np.asarray(arrays["landmark_kinds_l"], dtype=np.int64)
        if sizes.ndim != 1 or codes.shape != sizes.shape or np.any(sizes < 1):
            raise InvalidInputError("landmark arrays: sizes and kinds disagree or are empty")
        if points.ndim != 2 or points.shape[1] != 3 or len(points) != int(sizes.sum()):
            raise InvalidInputError(
                f"landmark arrays: {len(points)} points but the sizes add up to {int(sizes.sum())}"
            )
        if np.any((codes < 0) | (codes >= len(LANDMARK_KINDS))):
            raise InvalidInputError("landmark arrays: unknown kind code")
        clouds = tuple(np.split(points, np.cumsum(sizes)[:-1]))
        return cls(clouds, tuple(LANDMARK_KINDS[c] for c in codes))


def sample_landmarks(
    executions: Sequence[LabelledExecution],
    *,
    n_labelled: int = 50,
    n_dead_ends: int = 20,
    seed: int = 0,
) -> Landmarks:
    """A seeded sample of labelled states and dead ends (the original's 50 + 20) from executions."""
    if n_labelled < 0 or n_dead_ends < 0:
        raise InvalidInputError("landmark counts must be >= 0")
    labelled = [s.cloud_n3 for e in executions for s in e.steps if s.outcome != StepOutcome.SKIPPED]
    dead = [d.cloud_n3 for e in executions for d in e.dead_ends]
    rng = np.random.default_rng(seed)
    pick_l = np.sort(rng.permutation(len(labelled))[:n_labelled])
    pick_d = np.sort(rng.permutation(len(dead))[:n_dead_ends])
    clouds = [labelled[i] for i in pick_l] + [dead[i] for i in pick_d]
    kinds = ["labelled"] * len(pick_l) + ["dead_end"] * len(pick_d)
    return Landmarks(tuple(clouds), tuple(kinds))
