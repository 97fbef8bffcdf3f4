"""Agreement between labellers (top-1, Cohen's kappa, dead ends) and the overlap policy."""

from __future__ import annotations

import math

import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.agreement import (
    OverlapPolicy,
    StateVisit,
    cohen_kappa,
    pair_agreement,
    pairwise_agreement,
)


def _ratings(pairs: dict[tuple[str, str], int]) -> tuple[list[str], list[str]]:
    a: list[str] = []
    b: list[str] = []
    for (x, y), n in pairs.items():
        a += [x] * n
        b += [y] * n
    return a, b


def test_kappa_of_the_textbook_two_by_two_table_is_0_4() -> None:
    # 50 items: both yes 20, A yes/B no 5, A no/B yes 10, both no 15 (p_o 0.7, p_e 0.5).
    a, b = _ratings({("yes", "yes"): 20, ("yes", "no"): 5, ("no", "yes"): 10, ("no", "no"): 15})
    kappa, chance = cohen_kappa(a, b)
    assert chance == pytest.approx(0.5)
    assert kappa == pytest.approx(0.4)


def test_kappa_is_one_for_perfect_agreement_and_zero_at_chance() -> None:
    assert cohen_kappa(["x", "y", "z"], ["x", "y", "z"])[0] == pytest.approx(1.0)
    kappa, chance = cohen_kappa(["x", "x", "y", "y"], ["x", "y", "x", "y"])
    assert chance == pytest.approx(0.5) and kappa == pytest.approx(0.0)


def test_kappa_is_undefined_when_both_always_chose_one_demo() -> None:
    kappa, chance = cohen_kappa(["x", "x"], ["x", "x"])
    assert kappa is None and chance == 1.0
    kappa, chance = cohen_kappa([], [])
    assert kappa is None and math.isnan(chance)


def test_kappa_refuses_ratings_of_different_items() -> None:
    with pytest.raises(InvalidInputError, match="same items"):
        cohen_kappa(["x"], ["x", "y"])


def _visit(who: str, start: str, step: int, demo: str | None, path=(), dead=False) -> StateVisit:
    return StateVisit(who, start, step, tuple(path), demo, dead)


def test_pair_agreement_counts_shared_states_disagreements_and_dead_ends() -> None:
    visits = [
        _visit("ann", "t0", 0, "d1"),
        _visit("bob", "t0", 0, "d1"),
        _visit("ann", "t0", 1, "d2", ["d1"], dead=True),
        _visit("bob", "t0", 1, "d3", ["d1"], dead=True),
        _visit("ann", "t1", 0, "d1"),
        _visit("bob", "t1", 0, "d4", dead=True),
        _visit("ann", "t2", 0, "d1"),  # only ann: not shared
        _visit("bob", "t1", 1, "d2", ["d4"]),  # bob's own path: not shared
    ]
    pa = pair_agreement(visits, "ann", "bob")
    assert (pa.n_shared, pa.n_compared, pa.n_agree) == (3, 3, 1)
    assert pa.top1 == pytest.approx(1 / 3)
    # ann: d1, d2, d1; bob: d1, d3, d4 -> p_e = (2/3)(1/3) = 2/9; kappa = (1/3 - 2/9)/(7/9).
    assert pa.chance == pytest.approx(2 / 9)
    assert pa.kappa == pytest.approx((1 / 3 - 2 / 9) / (7 / 9))
    assert (pa.dead_end_both, pa.dead_end_only_a, pa.dead_end_only_b) == (1, 0, 1)
    assert pa.dead_end_neither == 1
    assert {(d.start, d.step_index, d.demo_a, d.demo_b) for d in pa.disagreements} == {
        ("t0", 1, "d2", "d3"),
        ("t1", 0, "d1", "d4"),
    }


def test_match_by_step_pairs_states_whatever_came_before() -> None:
    visits = [_visit("ann", "t1", 1, "d2", ["d1"]), _visit("bob", "t1", 1, "d2", ["d4"])]
    assert pair_agreement(visits, "ann", "bob").n_shared == 0
    assert pair_agreement(visits, "ann", "bob", match="step").n_agree == 1


def test_a_later_visit_of_the_same_state_replaces_the_earlier_choice() -> None:
    visits = [
        _visit("ann", "t0", 0, "d9"),
        _visit("ann", "t0", 0, "d1"),
        _visit("bob", "t0", 0, "d1"),
    ]
    assert pair_agreement(visits, "ann", "bob").top1 == 1.0


def test_pairwise_agreement_lists_every_pair_once_even_without_shared_states() -> None:
    visits = [
        _visit(name, "t0" if name != "cy" else "t9", 0, "d1") for name in ("bob", "ann", "cy")
    ]
    pairs = [(p.labeller_a, p.labeller_b, p.n_shared) for p in pairwise_agreement(visits)]
    assert pairs == [("ann", "bob", 1), ("ann", "cy", 0), ("bob", "cy", 0)]
    none = pairwise_agreement(visits)[1]
    assert none.top1 is None and none.kappa is None and none.chance is None


def test_overlap_policy_is_seeded_per_start_and_offers_about_the_share_asked() -> None:
    keys = [f"main-train-{i:04d}" for i in range(4000)]
    policy = OverlapPolicy(0.1, seed=3)
    offered = [k for k in keys if policy.offers_second(k)]
    assert 0.08 < len(offered) / len(keys) < 0.12
    assert offered == [k for k in reversed(keys) if policy.offers_second(k)][::-1]
    assert offered != [k for k in keys if OverlapPolicy(0.1, seed=4).offers_second(k)]
    assert not any(OverlapPolicy(0.0).offers_second(k) for k in keys[:100])
    assert all(OverlapPolicy(1.0).offers_second(k) for k in keys[:100])


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_overlap_policy_refuses_a_share_outside_zero_one(bad: float) -> None:
    with pytest.raises(InvalidInputError, match="overlap"):
        OverlapPolicy(bad)
