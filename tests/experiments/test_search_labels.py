"""A search policy's knotted episodes become labels; its failed ones never do."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.agent import Agent
from knotlab.core.experiments.search_labels import (
    execution_from_episode,
    floor_tries,
    root_tries,
)
from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.tries import TriedDemo
from knotlab.core.world.sim import RopeWorld
from tests.minilib import mini_library, mini_tasks

pytestmark = pytest.mark.xdist_group("minilib")


def _search_agent() -> Agent:
    lib = mini_library(2)
    featurizer = Agent(lib).featurizer
    phi = featurizer.features_from_scan(*_scan(featurizer))
    d = phi.shape[1]
    w = np.zeros(d)
    w[-len(lib) :] = np.arange(len(lib))
    model = QModel(w, 0.0, np.zeros(d), np.ones(d), featurizer.spec(), {})
    return Agent(lib, model, "la1x6")


def _scan(featurizer):
    with RopeWorld() as world:
        world.reset(mini_tasks(2)[0].start_nodes_k3)
        cloud = featurizer.observe(world)
    return featurizer.scan(cloud), cloud


def test_a_knotted_episode_is_a_labelled_execution_with_its_choices_and_model():
    # any policy's episode converts; the simulation oracle knots one of these mini starts (which
    # one depends on the CPU kind: AVX2 and AVX-512 machines simulate and scan with other last
    # bits, docs/determinism.md)
    agent = Agent(mini_library(2), None, "oracle")
    for task in mini_tasks(3):
        with RopeWorld() as world:
            record = agent.run_episode(world, task)
        if record.success:
            break
    assert record.success
    ex = execution_from_episode(
        record,
        agent.library.keys,
        execution_id="search-oracle-t0",
        labeller="search-oracle",
        model_hash="m0",
        library_hash=agent.library.content_hash(),
        metadata={"labelled_by": {"policy": "oracle"}},
    )
    assert ex is not None and ex.ended_in_knot and ex.labeller == "search-oracle"
    assert ex.task_id == record.task_id and ex.metadata["labelled_by"] == {"policy": "oracle"}
    assert [s.chosen_demo for s in ex.steps] == [s.chosen_key for s in record.steps]
    assert [s.outcome for s in ex.steps][-1] == StepOutcome.KNOT
    for step, rec in zip(ex.steps, record.steps, strict=True):
        assert step.chosen_demo in step.candidates  # the policy's choice scores highest
        assert np.all(np.isfinite(step.candidate_scores_c))
        assert step.model_version == "m0"
        np.testing.assert_array_equal(step.cloud_n3, rec.cloud_n3)
        np.testing.assert_array_equal(step.rope_nodes_k3, rec.nodes_before_k3)


def test_a_search_episode_that_misses_the_goal_gives_no_label_but_its_root_tries():
    agent = _search_agent()
    with RopeWorld() as world:
        short = agent.run_episode(world, mini_tasks(2)[0], max_steps=1)
    assert not short.success
    keys = agent.library.keys
    assert (
        execution_from_episode(
            short, keys, execution_id="x", labeller="l", model_hash="m", library_hash="h"
        )
        is None
    )
    tried = root_tries(short.steps[0].info, keys)
    assert sorted(t.demo for t in tried) == sorted(keys)  # width 6: every demo simulated once
    assert all(not t.knot for t in tried)  # else the episode would have knotted


def test_floor_tries_keep_only_the_root_candidates_that_did_not_advance_from_the_steps_stage():
    roots = [
        (TriedDemo("a", 1, False, None), TriedDemo("b", 0, False, None)),
        (TriedDemo("c", 1, False, None), TriedDemo("d", 2, False, "misgrasp")),
        (TriedDemo("e", 3, True, None),),
    ]
    recs = floor_tries("ex", [0, 1, 2], roots)
    assert [r.stage_before for r in recs] == [0, 1, 2]
    assert [[t.demo for t in r.tried] for r in recs] == [["b"], ["c", "d"], []]
    with pytest.raises(ValueError):
        floor_tries("ex", [0, 1], roots)  # one stage per step
