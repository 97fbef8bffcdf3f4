"""bench/table1_report.py: the paired comparison of two policies' Table I episodes."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest


def _report_module(project_root: Path):
    spec = importlib.util.spec_from_file_location(
        "table1_report", project_root / "bench" / "table1_report.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _recs(successes: dict[int, bool]) -> list[dict]:
    return [{"task_index": t, "success": s} for t, s in successes.items()]


def test_paired_counts_only_common_tasks_and_gives_the_exact_sign_test(project_root) -> None:
    """Discordant tasks counted each way on the tasks both ran; p is the exact binomial test."""
    report = _report_module(project_root)
    a = _recs({0: True, 1: True, 2: False, 3: True, 4: True, 5: True})
    b = _recs({0: True, 1: False, 2: True, 3: False, 4: False})  # task 5 only in a
    n, a_only, b_only, p = report.paired(a, b)
    assert (n, a_only, b_only) == (5, 3, 1)
    assert p == pytest.approx(0.625)  # 2 * P(X <= 1), X ~ Bin(4, 1/2) = 2 * 5/16
    assert report.paired(a, a)[1:] == (0, 0, 1.0)  # no discordant task: p = 1
