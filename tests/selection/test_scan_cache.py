"""Scan summaries: phi and scores rebuilt from a summary are the live ones, bit for bit; a
cache file round-trips and refuses another library."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.acquisition import score_scan, score_starts
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.scan_cache import ScanCacheIdentity, ScanSummaryCache
from knotlab.core.tasks import get_task


@pytest.fixture(scope="module")
def shipped():
    files = get_task("overhand").files
    library = DemoLibrary.load(files.library_path)
    model = QModel.load(files.model_path)
    assert model.landmarks is not None  # the features then need the landmark scan too
    return library, model, LibraryFeaturizer.for_model(library, model)


def _clouds(library: DemoLibrary, n: int = 4) -> list[np.ndarray]:
    """Demo clouds, a little moved (not the library's own, which register perfectly)."""
    rng = np.random.default_rng(0)
    return [library[i].pre_cloud_n3 + rng.normal(0, 0.003, (1, 3)) for i in range(0, 8 * n, 8)]


def test_features_and_scores_from_a_summary_are_the_live_ones_bit_for_bit(shipped) -> None:
    library, model, featurizer = shipped
    cache = ScanSummaryCache(ScanCacheIdentity.of(featurizer))
    starts = [(f"s{i}", c) for i, c in enumerate(_clouds(library))]
    from_cache = score_starts(starts, featurizer, model, cache)
    assert cache.misses == len(starts) and len(cache) == len(starts)
    for (key, cloud), got in zip(starts, from_cache, strict=True):
        phi, scan = featurizer.features(cloud)
        summary = cache.get(cloud)
        assert summary is not None
        assert np.array_equal(featurizer.features_from_summary(summary, cloud), phi)
        assert got == score_scan(key, scan, phi, model, library.keys)
    again = score_starts(starts, featurizer, model, cache)
    assert again == from_cache and cache.hits == len(starts)


class _NoLandmarkScans:
    """A featurizer whose landmark weights must come from the cache."""

    def __init__(self, featurizer: LibraryFeaturizer) -> None:
        self.landmark_hash = featurizer.landmark_hash

    def landmark_weights(self, cloud):
        raise AssertionError("scanned the landmarks")


def test_a_cache_file_round_trips_and_refuses_another_library(shipped, tmp_path) -> None:
    library, _model, with_model = shipped
    featurizer = LibraryFeaturizer(library)  # the summaries need no model
    identity = ScanCacheIdentity.of(featurizer)
    cache = ScanSummaryCache(identity)
    with pytest.raises(InvalidInputError, match="no scan summaries"):
        cache.save(tmp_path / "empty.npz")
    clouds = _clouds(library, 2)
    for cloud in clouds:
        cache.summary(featurizer, cloud)
    cache.features(with_model, clouds[0])  # the model's landmark weights of one cloud too
    path = cache.save(tmp_path / "scans.npz")
    loaded = ScanSummaryCache.load(path, identity)
    assert loaded.made_on == cache.made_on
    weights = loaded.landmark_weights(_NoLandmarkScans(with_model), clouds[0])  # stored: no scan
    assert np.array_equal(weights, with_model.landmark_weights(clouds[0]))
    with pytest.raises(AssertionError, match="scanned"):
        loaded.landmark_weights(_NoLandmarkScans(with_model), clouds[1])  # not stored
    for cloud in clouds:
        a, b = cache.get(cloud), loaded.get(cloud)
        assert a is not None and b is not None
        for name in ("costs_ac", "ok_a", "grasp_a"):
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True)
    assert loaded.get(clouds[0] + 1e-9) is None  # keyed by the exact bytes
    other = ScanCacheIdentity("0123456789abcdef", identity.params_hash)
    with pytest.raises(InvalidInputError, match="summaries of library"):
        ScanSummaryCache.load(path, other)
    with pytest.raises(InvalidInputError, match="another library"):
        ScanSummaryCache(other).summary(featurizer, clouds[0])
    same = ScanSummaryCache(identity)
    for cloud in clouds:
        same.summary(featurizer, cloud)
    same.features(with_model, clouds[0])
    assert same.save(tmp_path / "again.npz").read_bytes() == path.read_bytes()
