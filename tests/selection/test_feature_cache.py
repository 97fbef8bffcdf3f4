"""FeatureCache: a refit on a grown label set featurises only the executions it has not seen."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.selection import model_selection
from knotlab.core.selection.model_selection import FeatureCache, QModelSearch
from tests.minilib import mini_executions, mini_library


def _search(cache: FeatureCache) -> QModelSearch:
    return QModelSearch(
        C=[10.0], D=[1.0], landmarks=(0, 0), validation_fraction=0.0, workers=1,
        progress=False, feature_cache=cache,
    )  # fmt: skip


@pytest.mark.slow
def test_a_cached_refit_featurises_only_new_executions_and_fits_the_same(monkeypatch) -> None:
    executions, library = mini_executions(3), mini_library(3)
    cache = FeatureCache()
    first = _search(cache).fit(executions[:2], library)
    assert len(cache) == 2
    seen: list[str] = []
    real = model_selection.featurize_executions

    def counting(execs, *args, **kwargs):
        seen.extend(e.execution_id for e in execs)
        return real(execs, *args, **kwargs)

    monkeypatch.setattr(model_selection, "featurize_executions", counting)
    grown = _search(cache).fit(executions, library)
    assert seen == [executions[2].execution_id] and len(cache) == 3
    again = _search(cache).fit(executions[:2], library)
    assert seen == [executions[2].execution_id]  # nothing new to featurise
    assert np.allclose(again.best_model_.weights_d, first.best_model_.weights_d)
    assert grown.n_train_executions_ == 3


def test_the_cache_keys_include_the_landmarks() -> None:
    executions, library = mini_executions(3), mini_library(3)
    cache = FeatureCache()
    _search(cache).fit(executions, library)
    with_landmarks = _search(cache)
    with_landmarks.landmarks = (2, 0)
    with_landmarks.fit(executions, library)
    assert len(cache) == 6
