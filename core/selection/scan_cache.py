"""Scan summaries of many states, kept in memory and in a file: what makes scoring every start fast.

Ranking a state's demos needs its library scan (one TPS-RPM registration per demo, ~0.05 s on
one core) and, with a model that has landmarks, the state's landmark weights. Scoring all 300
unlabelled starts for "what to label next" repeats the same scans every time it is asked, and a
retrain changes neither the starts nor the library. The scan summary (`ScanSummary`: costs,
which demos registered, grasp distances) is a pure function of the cloud's exact bytes, the
library and the registration preset; this cache keys it by the cloud's digest under that
identity, and a file written by `save` ships precomputed summaries of a level's training starts.

A summary equals a live scan's bit for bit on the CPU kind it was made on (the file records it)
with one BLAS thread, as every knotlab process runs; another kernel (AVX2 against AVX-512) or
another BLAS thread count moves costs by up to ~1e-3 relative (TPS-RPM's iterations carry the
last bits on). Summaries rank "what to label next", and a start the app shows when they were made
on this CPU kind (`summary_ranking.py`: the full scan's ranking, bit for bit); every other
ranking a labeller is shown is computed from a live scan.
"""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from knotlab.core.arrays import cloud_digest
from knotlab.core.errors import InvalidInputError
from knotlab.core.hashing import ContentHash
from knotlab.core.machine import numeric_kind
from knotlab.core.npzfile import read_npz, write_npz
from knotlab.core.selection.features import LibraryFeaturizer, ScanSummary

FILE_FORMAT = "knotlab-scan-summaries"
FILE_VERSION = 1


@dataclass(frozen=True)
class ScanFeatures:
    """A state's features phi_ad and the scan summary they came from."""

    phi_ad: np.ndarray
    summary: ScanSummary


@dataclass(frozen=True)
class ScanCacheIdentity:
    """What a summary depends on besides the cloud: the library and the registration preset."""

    library_hash: str
    params_hash: str

    @classmethod
    def of(cls, featurizer: LibraryFeaturizer) -> ScanCacheIdentity:
        """The identity of the summaries ``featurizer`` computes."""
        params = ContentHash().json(asdict(featurizer.params)).hexdigest()
        return cls(featurizer.library_hash, params)


class ScanSummaryCache:
    """Scan summaries by cloud digest, for one library and preset (thread-safe)."""

    def __init__(self, identity: ScanCacheIdentity, made_on: str | None = None) -> None:
        self.identity = identity
        # The CPU kind (core.machine.numeric_kind) the stored summaries were computed on.
        self.made_on = made_on or numeric_kind()
        self._items: dict[str, ScanSummary] = {}
        # (landmark set's hash, cloud digest) -> the state's landmark weights (a model's
        # landmarks; a retrain draws new ones)
        self._near: dict[tuple[str, str], np.ndarray] = {}
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._items)

    def get(self, cloud_n3: np.ndarray) -> ScanSummary | None:
        """The stored summary of this exact cloud, or None."""
        with self._lock:
            return self._items.get(cloud_digest(cloud_n3))

    def summary(self, featurizer: LibraryFeaturizer, cloud_n3: np.ndarray) -> ScanSummary:
        """This cloud's summary: stored, or scanned now with ``featurizer`` and kept."""
        if ScanCacheIdentity.of(featurizer) != self.identity:
            raise InvalidInputError(
                "this scan cache belongs to another library or registration preset"
            )
        key = cloud_digest(cloud_n3)
        with self._lock:
            hit = self._items.get(key)
            if hit is not None:
                self.hits += 1
                return hit
            self.misses += 1
        made = featurizer.summarise(featurizer.scan(cloud_n3), cloud_n3)
        with self._lock:
            return self._items.setdefault(key, made)

    def landmark_weights(self, featurizer: LibraryFeaturizer, cloud_n3: np.ndarray) -> np.ndarray:
        """This cloud's weights over ``featurizer``'s landmarks: stored, or computed and kept."""
        if featurizer.landmark_hash is None:
            raise InvalidInputError("this featurizer has no landmarks")
        key = (featurizer.landmark_hash, cloud_digest(cloud_n3))
        with self._lock:
            hit = self._near.get(key)
        if hit is not None:
            return hit
        made = featurizer.landmark_weights(cloud_n3)
        with self._lock:
            return self._near.setdefault(key, made)

    def features(self, featurizer: LibraryFeaturizer, cloud_n3: np.ndarray) -> ScanFeatures:
        """phi_ad of this cloud for ``featurizer`` and the summary it came from (each part
        stored, or computed and kept)."""
        summary = self.summary(featurizer, cloud_n3)
        near = None if featurizer.landmarks is None else self.landmark_weights(featurizer, cloud_n3)
        return ScanFeatures(featurizer.features_from_summary(summary, cloud_n3, near), summary)

    def save(self, path: str | Path) -> Path:
        """Write every summary to an .npz (atomic; digests sorted, so same content, same bytes)."""
        with self._lock:
            keys = sorted(self._items)
            items = [self._items[k] for k in keys]
            near = dict(self._near)
        if not items:
            raise InvalidInputError("no scan summaries to save")
        arrays = {
            "digests": np.array(keys),
            "costs_sac": np.stack([s.costs_ac for s in items]),
            "ok_sa": np.stack([s.ok_a for s in items]),
            "grasp_sa": np.stack([s.grasp_a for s in items]),
        }
        landmark_sets = sorted({h for h, _ in near})
        for i, h in enumerate(landmark_sets):
            rows = [near.get((h, k)) for k in keys]
            width = next(len(r) for r in rows if r is not None)
            arrays[f"near_{i}_sl"] = np.stack(
                [np.full(width, np.nan) if r is None else r for r in rows]
            )
        header = {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            **asdict(self.identity),
            "made_on": self.made_on,
            "landmark_sets": landmark_sets,  # near_<i>_sl: weights over set i (NaN: not known)
        }
        return write_npz(path, arrays, header)

    @classmethod
    def load(cls, path: str | Path, identity: ScanCacheIdentity) -> ScanSummaryCache:
        """Summaries from a file written by `save`; refused if made for another identity."""
        arrays, header = read_npz(path, "scan summaries")
        if header.get("format") != FILE_FORMAT or header.get("version") != FILE_VERSION:
            raise InvalidInputError(f"{path}: not a {FILE_FORMAT} v{FILE_VERSION} file")
        stored = ScanCacheIdentity(str(header.get("library_hash")), str(header.get("params_hash")))
        if stored != identity:
            raise InvalidInputError(
                f"{path}: summaries of library {stored.library_hash} (preset "
                f"{stored.params_hash}), not of {identity.library_hash} ({identity.params_hash})"
            )
        cache = cls(identity, str(header.get("made_on") or "unknown"))
        digests = [str(k) for k in arrays["digests"]]
        for i, key in enumerate(digests):
            cache._items[key] = ScanSummary(
                arrays["costs_sac"][i], arrays["ok_sa"][i].astype(bool), arrays["grasp_sa"][i]
            )
        for j, h in enumerate(header.get("landmark_sets") or []):
            for key, row in zip(digests, arrays[f"near_{j}_sl"], strict=True):
                if not np.isnan(row).any():
                    cache._near[(str(h), key)] = row
        return cache
