"""What each feature column means, for one library: the spec saved with every Q-model.

Kept apart from features.py (registration, scipy) so that the model file code (qmodel.py) can
parse a stored spec without importing the featurizer.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from knotlab.core.errors import InvalidInputError
from knotlab.core.tasks.base import DEFAULT_TASK
from knotlab.core.world.observation import ObservationModel

_REQUIRED = (
    "feature_set",
    "library_hash",
    "action_keys",
    "names",
    "indicator_mask",
    "phase_steps",
    "phase_temperature",
)


@dataclass(frozen=True)
class FeatureSpec:
    """What each feature column means, for one library: saved with every model."""

    feature_set: str
    library_hash: str
    action_keys: tuple[str, ...]
    names: tuple[str, ...]
    indicator_mask: tuple[bool, ...]
    phase_steps: tuple[int, ...]
    phase_temperature: float
    landmark_hash: str | None = None
    observation_model: str = ObservationModel.CLOUD.value
    rank_features: bool = False
    task: str = DEFAULT_TASK

    def to_dict(self) -> dict:
        """JSON-able form (what QModel stores); rank_features only when on and task only when
        not the overhand knot, so models made before they existed keep their spec (and hash)."""
        out = {
            "feature_set": self.feature_set,
            "library_hash": self.library_hash,
            "action_keys": list(self.action_keys),
            "names": list(self.names),
            "indicator_mask": list(self.indicator_mask),
            "phase_steps": list(self.phase_steps),
            "phase_temperature": self.phase_temperature,
            "landmark_hash": self.landmark_hash,
            "observation_model": self.observation_model,
        }
        if self.rank_features:
            out["rank_features"] = True
        if self.task != DEFAULT_TASK:
            out["task"] = self.task
        return out

    @classmethod
    def from_dict(cls, spec: Mapping[str, Any]) -> FeatureSpec:
        """Inverse of :meth:`to_dict`; keys older files lack get their old meaning
        (observation_model 'cloud', no rank features, no landmarks, the overhand task)."""
        if not isinstance(spec, Mapping):
            raise InvalidInputError(f"feature spec must be a mapping, got {type(spec).__name__}")
        missing = [key for key in _REQUIRED if key not in spec]
        if missing:
            raise InvalidInputError(f"feature spec lacks key {missing[0]!r} (has {sorted(spec)})")
        landmark_hash = spec.get("landmark_hash")
        task = spec.get("task")
        return cls(
            feature_set=str(spec["feature_set"]),
            library_hash=str(spec["library_hash"]),
            action_keys=tuple(str(k) for k in spec["action_keys"]),
            names=tuple(str(n) for n in spec["names"]),
            indicator_mask=tuple(bool(b) for b in spec["indicator_mask"]),
            phase_steps=tuple(int(k) for k in spec["phase_steps"]),
            phase_temperature=float(spec["phase_temperature"]),
            landmark_hash=None if landmark_hash is None else str(landmark_hash),
            observation_model=str(spec.get("observation_model") or ObservationModel.CLOUD.value),
            rank_features=bool(spec.get("rank_features", False)),
            task=DEFAULT_TASK if task is None else str(task),
        )
