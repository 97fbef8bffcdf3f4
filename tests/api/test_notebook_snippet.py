"""The README's notebook snippet runs as written and ties the knot; the Agent's seams behave."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def _readme_snippet() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## From a notebook", 1)[1]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "the README's notebook section has no python block"
    return match.group(1)


@pytest.mark.slow
def test_the_readme_notebook_snippet_ties_a_knot_in_at_most_8_lines() -> None:
    code = _readme_snippet()
    lines = [ln for ln in code.splitlines() if ln.strip()]
    assert len(lines) <= 8, lines
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README.md", "exec"), {})
    printed = out.getvalue().strip()
    assert printed.startswith("True"), printed


def test_the_package_exports_the_public_api_lazily() -> None:
    import knotlab

    assert {"Agent", "RopeWorld", "Task", "get_task", "__version__"} <= set(knotlab.__all__)
    assert (Path(knotlab.__file__).parent / "py.typed").exists()
    with pytest.raises(AttributeError):
        knotlab.NoSuchThing  # noqa: B018


@pytest.fixture(scope="module")
def mini_agent():
    from knotlab import Agent
    from tests.minilib import mini_library

    return Agent(mini_library(2), policy="nn", top_k=3)


def test_rank_offers_warped_trajectories_best_first_and_never_a_failed_registration(
    mini_agent,
) -> None:
    from knotlab import RopeWorld

    lib = mini_agent.library
    with RopeWorld() as world:
        world.reset(lib[lib.index_of("s000-t1")].pre_nodes_k3)
        cloud = mini_agent.observe(world)
    ranked = mini_agent.rank(cloud)
    assert [c.rank for c in ranked] == [1, 2, 3]
    costs = [c.nn_cost for c in ranked]
    assert costs == sorted(costs) and all(c.q is None for c in ranked)
    assert all(c.trajectory is not None and c.failure is None for c in ranked)
    scan = mini_agent.scan(cloud)
    ok = set(np.flatnonzero(scan.ok_a))
    assert {c.demo_index for c in mini_agent.rank(cloud, top_k=len(lib))} <= ok


def test_choose_leaves_the_world_as_it_was_and_act_reports_the_tasks_stage(mini_agent) -> None:
    from knotlab import RopeWorld

    lib = mini_agent.library
    oracle = mini_agent.with_policy("oracle")
    with RopeWorld() as world:
        world.reset(lib[lib.index_of("s000-t2")].pre_nodes_k3)
        before = world.snapshot()
        decision = oracle.choose(world, step_index=4)
        assert world.snapshot().equals(before)
        outcome = oracle.act(world, decision.action)
    assert outcome.knot and outcome.stage == 3
    assert outcome.stage == mini_agent.task.stage(outcome.nodes_after_k3).stage


def test_the_constructor_refuses_what_does_not_belong_together_in_one_line() -> None:
    from knotlab import Agent
    from knotlab.core.errors import InvalidInputError
    from tests.minilib import mini_library

    lib = mini_library(2)
    with pytest.raises(InvalidInputError, match="needs a trained Q-model"):
        Agent(lib, None, "greedy")
    with pytest.raises(InvalidInputError, match="unknown policy"):
        Agent(lib, None, "la0x3")
    with pytest.raises(InvalidInputError, match="depth/width apply to policy 'lookahead'"):
        Agent(lib, None, "greedy", depth=2, width=5)
    with pytest.raises(InvalidInputError, match="unknown task"):
        Agent(lib, None, "nn", task="figure9")
    other = type(lib)(lib.segments, {**lib.metadata, "task": "figure8"})
    with pytest.raises(InvalidInputError, match="made for task 'figure8', not 'overhand'"):
        Agent(other, None, "nn", task="overhand")
