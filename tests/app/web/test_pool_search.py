"""The app's lookahead, a level's expansions side by side in the SimPool's worker processes,
chooses and reports exactly what the in-process search does."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.app.web.sim_pool import PoolRunner, SimPool
from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.selection.decision import StepContext
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.lookahead import LookaheadPolicy
from knotlab.core.selection.qmodel import QModel
from knotlab.core.world.sim import RopeWorld
from tests.minilib import mini_library

pytestmark = pytest.mark.xdist_group("minilib")


def _ctx(world, featurizer, transferer, snapshot):
    world.restore(snapshot)
    cloud = featurizer.observe(world)
    return StepContext(world, cloud, featurizer.scan(cloud), featurizer, transferer, 0, 5)


@pytest.mark.slow
def test_pool_search_matches_the_sequential_search(tmp_path):
    lib = mini_library(2)
    path = lib.save(tmp_path / "lib.npz")
    featurizer, transferer = LibraryFeaturizer(lib), DemoTransferer(lib)
    with RopeWorld() as world:
        world.reset(lib[lib.index_of("s000-t0")].pre_nodes_k3)
        start = world.snapshot()
        phi = featurizer.features(featurizer.observe(world))[0]
        w = np.zeros(phi.shape[1])
        w[-len(lib) :] = np.arange(len(lib))
        model = QModel(w, 0.0, np.zeros(phi.shape[1]), np.ones(phi.shape[1]), featurizer.spec(), {})
        here = LookaheadPolicy(model, depth=2, width=3).choose(
            _ctx(world, featurizer, transferer, start)
        )
        pool = SimPool(str(path), workers=2)
        try:
            counted = []
            runner = PoolRunner(pool, lambda: counted.append(1))
            there = LookaheadPolicy(model, depth=2, width=3, runner=runner).choose(
                _ctx(world, featurizer, transferer, start)
            )
        finally:
            pool.close()
        assert world.snapshot().equals(start)  # the search leaves the world where it found it
    assert there.action == here.action
    assert there.info["backed_up"] == here.info["backed_up"]
    assert there.info["tree"] == here.info["tree"]
    assert len(counted) == there.info["expansions"] - there.info["reused_expansions"]
    # The second level was under way before the first finished (certain members, prefetched).
    assert max(node["level"] for node in there.info["tree"]) == 2
    assert runner.prefetch_hits > 0
    assert there.outcome is not None and here.outcome is not None
    assert there.outcome.snapshot_after.equals(here.outcome.snapshot_after)
