"""The robustness study's settings and its paired comparison with the matched world."""

from __future__ import annotations

import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.experiments.robustness import (
    paired_row,
    parse_study_settings,
    worst_factors,
)
from knotlab.core.world.estimate import EstimatorKind
from knotlab.core.world.mismatch import MismatchFactor


def test_settings_parse_names_families_the_tracker_and_controls():
    settings = parse_study_settings("combined25,tracker,video,mass-10,combined50:known,families25")
    by_name = {s.name: s for s in settings}
    assert by_name["tracker"].estimator is EstimatorKind.TRACKER
    assert by_name["tracker"].world == "nominal"
    assert by_name["video"].estimator is EstimatorKind.VIDEO and by_name["video"].world == "nominal"
    assert by_name["combined50_known"].agent_model == "combined50"
    measured = parse_study_settings("radius+25:measured")[0]
    assert (measured.name, measured.world, measured.agent_model) == (
        "radius+25_measured",
        "radius+25",
        "measured",
    )
    assert by_name["mass-10"].factor is MismatchFactor.MASS
    assert by_name["mass-10"].level == pytest.approx(0.1)
    assert by_name["combined25"].level == 0.25
    families = [s for s in settings if s.factor is not None and s.name != "mass-10"]
    assert len(families) == 2 * len(MismatchFactor)  # +-25 % is a possible world for each
    assert "length-25" in by_name and "radius+25" in by_name
    with pytest.raises(InvalidInputError, match="unknown physics setting"):
        parse_study_settings("combined25,heavy")
    with pytest.raises(InvalidInputError, match="no study settings"):
        parse_study_settings(" , ")


def _rec(task: int, success: bool, kind: str | None = None) -> dict:
    return {"task_id": f"t{task}", "success": success, "failure_kind": kind}


def test_paired_rows_count_lost_and_gained_tasks_on_the_tasks_both_ran():
    matched = {f"t{i}": _rec(i, i < 8) for i in range(10)}  # 8 of 10 knotted when matched
    here = [_rec(i, i < 5 or i == 9) for i in range(10)] + [_rec(11, True)]  # t11: not matched
    row = paired_row("combined25", "la2x5", here, matched)
    assert (row.n, row.successes, row.matched_successes) == (10, 6, 8)
    assert (row.lost, row.gained) == (3, 1)
    assert row.change_points == pytest.approx(-20.0)
    assert 0.0 < row.p_value <= 1.0
    lo, hi = row.wilson
    assert lo < row.rate < hi
    errored = paired_row("x", "nn", [_rec(0, False, "error")], matched)
    assert errored.errored == 1


def test_the_worst_factor_is_the_single_factor_that_cost_most():
    matched = {f"t{i}": _rec(i, True) for i in range(4)}
    rows = [
        paired_row("mass+50", "greedy", [_rec(i, i > 0) for i in range(4)], matched),
        paired_row("grip_force-50", "greedy", [_rec(i, i > 2) for i in range(4)], matched),
        paired_row("combined50", "greedy", [_rec(i, False) for i in range(4)], matched),
        paired_row("tracker", "greedy", [_rec(i, False) for i in range(4)], matched),
    ]
    assert worst_factors(rows) == {"greedy": ("grip_force-50", -75.0)}


def test_a_part_run_setting_does_not_rank_as_the_worst_factor_by_its_few_tasks():
    matched = {f"t{i}": _rec(i, True) for i in range(8)}
    rows = [
        paired_row("radius-10", "nn", [_rec(i, i > 1) for i in range(8)], matched),  # -25
        paired_row("mass-10", "nn", [_rec(i, i > 3) for i in range(8)], matched),  # -50
        paired_row("table_friction+10", "nn", [_rec(0, False)], matched),  # 1 task: -100
        paired_row("length-50", "nn", [_rec(i, i > 2) for i in range(4)], matched),  # -75, 4 tasks
    ]
    # Each level's settings compete at that level's most tasks: the 1-task ±10 % setting is
    # left out, the ±50 % one on 4 tasks (all its level ran) is not.
    assert worst_factors(rows) == {"nn": ("length-50", -75.0)}
    assert worst_factors(rows[:3]) == {"nn": ("mass-10", -50.0)}
