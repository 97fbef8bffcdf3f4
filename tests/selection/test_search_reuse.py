"""The search reuses what it already simulated or scanned, and reports its whole tree."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.selection.decision import LevelDecision, StepContext
from knotlab.core.selection.explain import search_tree_lines
from knotlab.core.selection.lookahead import LookaheadPolicy
from knotlab.core.selection.qmodel import QModel

pytestmark = pytest.mark.xdist_group("minilib")


def _ctx(world, featurizer, transferer, nodes=None, snapshot=None):
    if snapshot is not None:
        world.restore(snapshot)
    else:
        world.reset(nodes)
    cloud = featurizer.observe(world)
    return StepContext(world, cloud, featurizer.scan(cloud), featurizer, transferer, 0, 5)


def _model(featurizer, phi):
    d = phi.shape[1]
    w = np.zeros(d)
    w[-len(featurizer.library) :] = np.arange(len(featurizer.library))  # prefers late demos
    return QModel(w, 0.0, np.zeros(d), np.ones(d), featurizer.spec(), {})


def test_a_state_scanned_lately_is_not_scanned_again(lib, world, featurizer):
    world.reset(lib[0].pre_nodes_k3)
    cloud = featurizer.observe(world)
    hits, _ = featurizer.memo_stats
    first = featurizer.scan(cloud)
    again = featurizer.scan(cloud.copy())  # equal bytes, another array
    assert again is first and featurizer.memo_stats[0] == hits + 1
    phi = featurizer.features_from_scan(first, cloud)
    assert not phi.flags.writeable  # shared with later callers: nobody may edit it
    fresh = featurizer.registrar.scan(cloud, lib.clouds(), key="uncached-check")
    assert np.array_equal(featurizer.features_from_scan(fresh, cloud), phi)
    moved = cloud + np.array([0.001, 0.0, 0.0])
    assert featurizer.scan(moved) is not first  # a different state is scanned


@pytest.mark.slow
def test_a_repeated_search_reuses_every_expansion_and_decides_the_same(
    lib, world, featurizer, transferer
):
    ctx = _ctx(world, featurizer, transferer, lib[lib.index_of("s000-t0")].pre_nodes_k3)
    policy = LookaheadPolicy(_model(featurizer, ctx.phi_ad), depth=2, width=3)
    before = world.snapshot()
    first = policy.choose(ctx)
    assert first.info["reused_expansions"] == 0 and first.info["expansions"] > 3
    assert world.snapshot().equals(before)
    second = policy.choose(_ctx(world, featurizer, transferer, snapshot=before))
    assert second.info["reused_expansions"] == second.info["expansions"]
    assert second.action == first.action
    assert second.info["backed_up"] == first.info["backed_up"]
    assert first.outcome is not None and second.outcome is not None
    assert second.outcome.snapshot_after.equals(first.outcome.snapshot_after)
    # A fresh policy (no memo) simulates again and gets bit-identical results.
    fresh = LookaheadPolicy(policy.model, depth=2, width=3).choose(
        _ctx(world, featurizer, transferer, snapshot=before)
    )
    assert fresh.info["reused_expansions"] == 0
    assert fresh.info["backed_up"] == first.info["backed_up"]
    strip = [{k: v for k, v in e.items() if k != "reused"} for e in first.info["tree"]]
    assert strip == [{k: v for k, v in e.items() if k != "reused"} for e in fresh.info["tree"]]


def test_the_search_tree_lists_every_expansion_under_its_parent(lib, world, featurizer, transferer):
    ctx = _ctx(world, featurizer, transferer, lib[lib.index_of("s000-t0")].pre_nodes_k3)
    decision = LookaheadPolicy(_model(featurizer, ctx.phi_ad), depth=2, width=3).choose(ctx)
    tree = decision.info["tree"]
    assert len(tree) == decision.info["expansions"]
    level_of = {0: 0} | {e["node"]: e["level"] for e in tree}
    for e in tree:
        assert level_of[e["parent"]] == e["level"] - 1
        if e["level"] == 1:
            assert e["root_action"] == e["action"]
    assert {e["level"] for e in tree} == {1, 2}
    lines = search_tree_lines(decision.info, lib.keys)
    assert len(lines) == len(tree)
    assert sum(line.startswith("  - ") for line in lines) == sum(e["level"] == 2 for e in tree)
    assert (
        all(
            f"`{lib.keys[e['action']]}`" in line
            for e, line in zip(tree, lines, strict=False)
            if e["level"] == 1
        )
        or lines
    )


def test_an_anytime_search_reports_each_level_and_decides_as_the_batch_one(
    lib, world, featurizer, transferer
):
    ctx = _ctx(world, featurizer, transferer, lib[lib.index_of("s000-t0")].pre_nodes_k3)
    model = _model(featurizer, ctx.phi_ad)
    before = world.snapshot()
    batch = LookaheadPolicy(model, depth=2, width=3).choose(ctx)
    assert not batch.info["goal_found"]  # both levels run (the mini rope knots in no step)
    reports: list[LevelDecision] = []
    anytime = _ctx(world, featurizer, transferer, snapshot=before)
    anytime.on_level = reports.append
    final = LookaheadPolicy(model, depth=2, width=3).choose(anytime)
    assert [(r.level, r.levels) for r in reports] == [(1, 2), (2, 2)]
    assert final.action == batch.action and np.array_equal(final.scores_a, batch.scores_a)
    assert reports[-1].decision.action == final.action
    assert reports[-1].decision.info["backed_up"] == final.info["backed_up"]
    # After level 1 the choice so far is lookahead(1, 3)'s: the same first level.
    depth1 = LookaheadPolicy(model, depth=1, width=3).choose(
        _ctx(world, featurizer, transferer, snapshot=before)
    )
    assert reports[0].decision.action == depth1.action
    assert len(reports[0].decision.info["tree"]) == depth1.info["expansions"]
