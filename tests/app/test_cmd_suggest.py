"""`knotlab suggest`: unlabelled training starts ranked by acquisition score."""

from __future__ import annotations

import json

import pytest

from knotlab.app.cli import main
from tests.minilib import mini_train_args, write_mini_files

pytestmark = pytest.mark.xdist_group("bench")


def test_suggest_ranks_the_training_starts_of_a_task_set(tmp_path, capsys) -> None:
    train_args, model = mini_train_args(tmp_path)
    assert main(train_args) == 0
    lib, tasks = write_mini_files(tmp_path, n_tasks=3, split="train")
    capsys.readouterr()
    args = ["suggest", "--tasks-file", str(tasks), "--model", str(model), "--library", str(lib)]
    assert main([*args, "--limit", "2", "--json", "--no-progress"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["rank"] for r in rows] == [1, 2]
    assert all(set(r["choices"]) == {"nn", "greedy"} for r in rows)
    assert all(r["key"].startswith("mini-train-") for r in rows)
    _, test_tasks = write_mini_files(tmp_path, n_tasks=1, split="test")
    assert main([*args[:1], "--tasks-file", str(test_tasks), *args[3:]]) == 2
    assert "training starts" in capsys.readouterr().err
