"""bench/table1_report.py: the paired comparison of two policies' Table I episodes."""

from __future__ import annotations

import pytest

from tests.bench_modules import load_bench_module


def _recs(successes: dict[int, bool]) -> list[dict]:
    return [{"task_index": t, "success": s} for t, s in successes.items()]


def test_paired_counts_only_common_tasks_and_gives_the_exact_sign_test(project_root) -> None:
    """Discordant tasks counted each way on the tasks both ran; p is the exact binomial test."""
    report = load_bench_module(project_root, "table1_report")
    a = _recs({0: True, 1: True, 2: False, 3: True, 4: True, 5: True})
    b = _recs({0: True, 1: False, 2: True, 3: False, 4: False})  # task 5 only in a
    n, a_only, b_only, p = report.paired(a, b)
    assert (n, a_only, b_only) == (5, 3, 1)
    assert p == pytest.approx(0.625)  # 2 * P(X <= 1), X ~ Bin(4, 1/2) = 2 * 5/16
    assert report.paired(a, a)[1:] == (0, 0, 1.0)  # no discordant task: p = 1


def test_segments_pair_each_start_with_its_stop_and_keep_unstopped_ones_open(project_root) -> None:
    """Three resumed stretches: two stopped (by the trap, at the end), one killed."""
    report = load_bench_module(project_root, "table1_report")
    log = (
        "start 2026-12-03T09:46:10Z cpu='AMD EPYC avx512' workers=2 commit=5b8053e\n"
        "stop  2026-12-03T10:33:46Z seconds=2856 (written by hand)\n"
        "start 2026-12-03T10:42:59Z cpu='AMD EPYC avx512' workers=2 commit=725812d\n"
        "end   2026-12-03T10:59:41Z seconds=1002\n"
        "start 2026-12-03T13:34:56Z cpu='Intel Xeon avx2' workers=4 commit=2d182f1\n"
    )
    segments = report.read_segments(log)
    assert [s.seconds for s in segments] == [2856, 1002, None]
    assert [s.commit for s in segments] == ["5b8053e", "725812d", "2d182f1"]
    assert (segments[2].cpu, segments[2].workers) == ("Intel Xeon avx2", 4)
    # a stop line with no open segment before it is ignored, not paired with a closed one
    assert [s.seconds for s in report.read_segments(log.splitlines(True)[1] + log)] == [
        2856,
        1002,
        None,
    ]


def test_agreement_compares_success_and_choices_on_common_tasks(project_root) -> None:
    """Per policy: tasks both runs have, how many end alike, how many chose the same demos."""
    report = load_bench_module(project_root, "table1_report")
    here = [
        {"task_index": 0, "success": True, "chosen": ["a", "b"]},
        {"task_index": 1, "success": False, "chosen": ["a", "c"]},
        {"task_index": 2, "success": True, "chosen": ["d"]},
        {"task_index": 9, "success": True, "chosen": ["e"]},  # not in the other run
    ]
    there = [
        {"task_index": 0, "success": True, "chosen": ["a", "b"]},
        {"task_index": 1, "success": False, "chosen": ["a", "d"]},
        {"task_index": 2, "success": False, "chosen": ["d", "e"]},
    ]
    assert report.agreement(here, there) == (3, 2, 1, 2, 1)  # knots here / there on tasks 0-2
