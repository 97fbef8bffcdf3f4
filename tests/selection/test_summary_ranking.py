"""A state ranked from its stored scan summary, with only its shown demos registered: the full
scan's ranking and warps, bit for bit; never from summaries made on another CPU kind."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.ranking import rank_demos
from knotlab.core.selection.scan_cache import ScanCacheIdentity, ScanSummaryCache
from knotlab.core.selection.summary_ranking import SummaryScan, summary_scan
from knotlab.core.tasks import get_task


@pytest.fixture(scope="module")
def shipped():
    files = get_task("overhand").files
    library = DemoLibrary.load(files.library_path)
    model = QModel.load(files.model_path)
    return library, model, LibraryFeaturizer.for_model(library, model)


def _cloud(library: DemoLibrary, i: int) -> np.ndarray:
    """A demo's cloud a little moved (the library's own registers perfectly)."""
    rng = np.random.default_rng(i)
    return library[i].pre_cloud_n3 + rng.normal(0, 0.003, (1, 3))


@pytest.mark.parametrize("with_model", [True, False])
def test_a_summary_ranks_and_warps_as_the_full_scan_bit_for_bit(shipped, with_model) -> None:
    library, model, featurizer = shipped
    q = model if with_model else None
    cache = ScanSummaryCache(ScanCacheIdentity.of(featurizer))
    for i in (3, 40, 97):
        cloud = _cloud(library, i)
        cache.features(featurizer, cloud)  # stored, as the shipped start scans are
        got = summary_scan(cache, featurizer, q, cloud, 5)
        assert got is not None
        phi, quick = got
        full_phi, full = featurizer.features(cloud)
        if with_model:
            assert np.array_equal(phi, full_phi)
        else:
            assert phi is None
        want = rank_demos(full, full_phi if with_model else None, q, library.keys, 5)
        assert rank_demos(quick, phi, q, library.keys, 5) == want
        assert quick.demos == tuple(r.demo_index for r in want)
        points = library[0].pre_cloud_n3
        for r in want:  # the shown candidates' warps: the full scan's
            assert np.array_equal(
                quick.f(r.demo_index).evaluate(points), full.f(r.demo_index).evaluate(points)
            )
        shown = set(quick.demos)
        other = next(a for a in range(len(library)) if a not in shown)
        with pytest.raises(InvalidInputError, match="was not registered"):
            quick.f(other)


def test_nothing_is_taken_from_summaries_of_another_cpu_kind_library_or_cloud(shipped) -> None:
    library, model, featurizer = shipped
    cloud = _cloud(library, 5)
    cache = ScanSummaryCache(ScanCacheIdentity.of(featurizer))
    assert summary_scan(cache, featurizer, model, cloud, 5) is None  # not stored
    summary = cache.summary(featurizer, cloud)
    assert isinstance(summary_scan(cache, featurizer, model, cloud, 5)[1], SummaryScan)
    other_kind = ScanSummaryCache(cache.identity, made_on="avx2-elsewhere")
    other_kind._items = dict(cache._items)
    assert summary_scan(other_kind, featurizer, model, cloud, 5) is None
    other_library = ScanSummaryCache(ScanCacheIdentity("another", cache.identity.params_hash))
    other_library._items = dict(cache._items)
    assert summary_scan(other_library, featurizer, model, cloud, 5) is None
    assert summary is cache.get(cloud)


def test_the_grasp_distances_warp_and_query_as_each_demos_own_spline_bit_for_bit(shipped) -> None:
    from scipy.spatial import cKDTree

    library, _, featurizer = shipped
    for i in (3, 40, 97):
        cloud = _cloud(library, i)
        scan = featurizer.scan(cloud)
        tree = cKDTree(cloud)
        expected = np.full(len(library), np.nan)
        for a in np.flatnonzero(scan.ok_a):
            for pts in (featurizer._grasp_pts[a], featurizer._margin_pts[a]):
                # the fast path is the spline's own evaluation, to the last bit
                assert np.array_equal(scan.f_points(a, pts), scan.f(a).evaluate(pts))
            expected[a] = tree.query(scan.f(a).evaluate(featurizer._grasp_pts[a]))[0].max()
        # one query over every demo's points: each point's distance is the one it gets alone
        assert np.array_equal(featurizer.summarise(scan, cloud).grasp_a, expected, equal_nan=True)
