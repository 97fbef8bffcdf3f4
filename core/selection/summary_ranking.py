"""Rank a stored state from its scan summary and register only the demos that are shown.

Showing a state ranks every demo (which needs each demo's registration costs, and with a model
the features phi) and draws the best few warped onto the rope (which needs those demos' warps).
For a state whose scan summary is stored (`scan_cache`: the shipped training starts), the
ranking is rebuilt from the summary and only the shown demos are registered again. Both are the
full scan's numbers bit for bit on the CPU kind the summaries were made on, with one BLAS thread
(as every knotlab process runs): phi from a summary is phi from the scan
(`tests/selection/test_scan_cache.py`), and a demo's registration does not depend on which other
demos are registered beside it (`tests/selection/test_summary_ranking.py`). On another CPU kind
the summaries' last bits differ from a live scan's, so nothing is taken from them there.
Shape suffix: a = demos (actions).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.machine import numeric_kind
from knotlab.core.registration import ScanResult
from knotlab.core.registration.tps import ThinPlateSpline
from knotlab.core.selection.features import LibraryFeaturizer, ScanSummary
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.ranking import demo_scores, rank_order
from knotlab.core.selection.scan_cache import ScanCacheIdentity, ScanSummaryCache


@dataclass(frozen=True)
class SummaryScan:
    """A state's registration costs from its summary, with the warps of a few demos only."""

    summary: ScanSummary
    registered: ScanResult  # the registrations of ``demos``, in that order
    demos: tuple[int, ...]

    @property
    def ok_a(self) -> np.ndarray:
        """Whether each demo registered (the summary's)."""
        return self.summary.ok_a

    @property
    def nn_cost_a(self) -> np.ndarray:
        """Each demo's registration cost (the summary's)."""
        return self.summary.nn_cost_a

    def f(self, a: int) -> ThinPlateSpline:
        """f_a: demo a's cloud -> the scene, for a demo that was registered here."""
        if a not in self.demos:
            raise InvalidInputError(f"demo {a} was not registered for this state: {self.demos}")
        return self.registered.f(self.demos.index(a))


def summary_scan(
    cache: ScanSummaryCache,
    featurizer: LibraryFeaturizer,
    model: QModel | None,
    cloud_n3: np.ndarray,
    top_k: int,
) -> tuple[np.ndarray | None, SummaryScan] | None:
    """(phi or None without a model, the scan) of a cloud ``cache`` holds, with its ``top_k``
    best demos registered; None when the cache does not hold it, belongs to another library or
    preset, or was made on another CPU kind (then scan the state in full)."""
    if cache.made_on != numeric_kind() or ScanCacheIdentity.of(featurizer) != cache.identity:
        return None
    summary = cache.get(cloud_n3)
    if summary is None:
        return None
    phi = None if model is None else cache.features(featurizer, cloud_n3).phi_ad
    best = tuple(int(a) for a in rank_order(demo_scores(summary, phi, model))[:top_k])
    return phi, SummaryScan(summary, featurizer.scan_demos(cloud_n3, best), best)
