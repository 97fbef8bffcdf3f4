"""The learned Q-function: Q(s, a) = w . standardise(phi(s, a)) + w0, its file and its hash.

Shape suffixes: a = actions (library demos), d = feature dimension.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from knotlab.core.atomic import atomic_open
from knotlab.core.errors import CorruptFileError, InvalidInputError
from knotlab.core.hashing import ContentHash
from knotlab.core.selection.feature_spec import FeatureSpec
from knotlab.core.selection.landmarks import Landmarks
from knotlab.core.textinput import LineError, parse_json

QMODEL_FORMAT_VERSION = 1


@dataclass(frozen=True, eq=False)
class QModel:
    """A learned linear Q-function over a saved feature spec: Q = w . standardise(phi) + w0.

    ``spec_dict`` is the feature spec exactly as stored (and hashed): files made before a spec
    key existed lack it, so it is kept as read; :attr:`feature_spec` is its typed form.
    """

    weights_d: np.ndarray
    bias: float
    feature_mean_d: np.ndarray
    feature_scale_d: np.ndarray
    spec_dict: dict
    hyperparameters: dict
    metrics: dict = field(default_factory=dict)
    landmarks: Landmarks | None = None  # landmark states the features refer to (saved along)

    def __post_init__(self) -> None:
        if self.landmarks is not None and self.spec_dict.get("landmark_hash") != (
            self.landmarks.content_hash()
        ):
            raise InvalidInputError("QModel landmarks do not match its feature spec")
        w = np.asarray(self.weights_d, dtype=float)
        mean = np.asarray(self.feature_mean_d, dtype=float)
        scale = np.asarray(self.feature_scale_d, dtype=float)
        if w.ndim != 1 or mean.shape != w.shape or scale.shape != w.shape:
            raise InvalidInputError(
                f"QModel arrays disagree: weights {w.shape}, mean {mean.shape}, scale {scale.shape}"
            )
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(mean)) and np.isfinite(self.bias)):
            raise InvalidInputError("QModel weights must be finite")
        if not np.all(np.isfinite(scale)) or np.any(scale <= 0):
            raise InvalidInputError("QModel feature scales must be finite and positive")
        object.__setattr__(self, "weights_d", w)
        object.__setattr__(self, "feature_mean_d", mean)
        object.__setattr__(self, "feature_scale_d", scale)
        object.__setattr__(self, "bias", float(self.bias))

    @cached_property
    def feature_spec(self) -> FeatureSpec:
        """The typed feature spec (InvalidInputError naming the key a partial spec lacks)."""
        return FeatureSpec.from_dict(self.spec_dict)

    @property
    def n_features(self) -> int:
        """Feature dimension d."""
        return int(self.weights_d.shape[0])

    def q(self, phi_ad: np.ndarray) -> np.ndarray:
        """Q-values of every action: phi_ad -> q_a (non-finite feature rows give -inf)."""
        phi = np.asarray(phi_ad, dtype=float)
        if phi.ndim != 2 or phi.shape[1] != self.n_features:
            raise InvalidInputError(
                f"phi_ad must have shape (A, {self.n_features}), got {phi.shape}"
            )
        with np.errstate(invalid="ignore"):
            q = ((phi - self.feature_mean_d) / self.feature_scale_d) @ self.weights_d + self.bias
        q[~np.isfinite(q)] = -np.inf
        return q

    def content_hash(self) -> str:
        """Stable hash of weights, standardisation and feature spec (identifies a model)."""
        h = ContentHash()
        for arr in (self.weights_d, self.feature_mean_d, self.feature_scale_d):
            h.array(arr, dtype="<f8")
        h.array(np.float64(self.bias)).json(self.spec_dict)
        if self.landmarks is not None:  # (absent for models without landmarks: hashes unchanged)
            h.text(self.landmarks.content_hash())
        return h.hexdigest()

    def to_parts(self) -> tuple[dict[str, np.ndarray], dict]:
        """The model as named arrays and a JSON-able header (for a file or a database row)."""
        meta = {
            "format": "knotlab-qmodel",
            "version": QMODEL_FORMAT_VERSION,
            "bias": self.bias,
            "feature_spec": self.spec_dict,
            "hyperparameters": self.hyperparameters,
            "metrics": self.metrics,
            "hash": self.content_hash(),
        }
        arrays = {
            "weights_d": self.weights_d,
            "feature_mean_d": self.feature_mean_d,
            "feature_scale_d": self.feature_scale_d,
            **(self.landmarks.to_arrays() if self.landmarks is not None else {}),
        }
        return arrays, meta

    @classmethod
    def from_parts(cls, arrays: dict[str, np.ndarray], meta: dict, where: str) -> QModel:
        """Inverse of :meth:`to_parts`; checks format, version and content hash (``where`` names
        the source in errors)."""
        missing = {"weights_d", "feature_mean_d", "feature_scale_d"} - set(arrays)
        if missing:
            raise CorruptFileError(f"{where}: model lacks {sorted(missing)}")
        if meta.get("format") != "knotlab-qmodel":
            raise CorruptFileError(f"{where}: not a knotlab model (format {meta.get('format')!r})")
        if meta.get("version") != QMODEL_FORMAT_VERSION:
            raise CorruptFileError(
                f"{where}: model format version {meta.get('version')} is not supported "
                f"(this knotlab reads version {QMODEL_FORMAT_VERSION})"
            )
        try:
            landmarks = Landmarks.from_arrays(arrays) if "landmark_points_n3" in arrays else None
            model = cls(
                arrays["weights_d"],
                meta["bias"],
                arrays["feature_mean_d"],
                arrays["feature_scale_d"],
                meta["feature_spec"],
                meta["hyperparameters"],
                meta.get("metrics", {}),
                landmarks,
            )
        except (KeyError, InvalidInputError) as exc:
            raise CorruptFileError(f"{where}: invalid model contents ({exc})") from exc
        if meta.get("hash") != model.content_hash():
            raise CorruptFileError(f"{where}: content hash mismatch (altered or truncated)")
        return model

    def save(self, path: str | Path) -> Path:
        """Write the model to a versioned .npz file; returns the path."""
        path = Path(path)
        arrays, meta = self.to_parts()
        payload = {"meta": np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays}
        with atomic_open(path, "wb") as fh:  # a crash never leaves a half-written model
            np.savez(fh, **payload)  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: str | Path) -> QModel:
        """Read and validate a model written by :meth:`save`."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"model file not found: {path}")
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a folder; expected a model file (.npz)")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: np.array(data[k]) for k in data.files}
        except Exception as exc:
            raise CorruptFileError(f"{path}: not a readable knotlab model file ({exc})") from exc
        if "meta" not in arrays:
            raise CorruptFileError(f"{path}: model file lacks ['meta']")
        try:  # bounded depth and integers, one line whatever the bytes (core.textinput)
            meta = parse_json(arrays.pop("meta").tobytes(), path)
        except LineError as exc:
            raise CorruptFileError(f"{path}: model metadata is not valid ({exc.problem})") from None
        if not isinstance(meta, dict):
            raise CorruptFileError(f"{path}: model metadata is not a JSON object")
        return cls.from_parts(arrays, meta, str(path))
