"""`knotlab tasks generate|info` from the mini library: both splits, checked and summarised."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from knotlab.app import cli
from knotlab.core.demos.tasks import TaskSet
from tests.minilib import mini_library

pytestmark = pytest.mark.xdist_group("minilib")


def test_tasks_generate_writes_both_splits_and_info_reads_them(tmp_path: Path, capsys) -> None:
    lib = mini_library(2).save(tmp_path / "lib.npz")
    out = tmp_path / "sets"
    argv = ["tasks", "generate", "--library", str(lib), "--seed", "3", "--level", "mini_1"]
    argv += ["--train", "1", "--test", "2", "--workers", "1", "--no-progress"]
    assert cli.main([*argv, "--out-dir", str(out)]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == [
        "tasks_mini_1_test.npz",
        "tasks_mini_1_train.npz",
    ]
    test = TaskSet.load(out / "tasks_mini_1_test.npz")
    assert len(test) == 2 and test.split == "test"
    assert test.metadata["library_hash"] == mini_library(2).content_hash()
    assert cli.main(["tasks", "info", str(out / "tasks_mini_1_test.npz"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["tasks"] == 2 and info["level"] == "mini_1" and info["rope_nodes"] == 41
    assert info["hash"] == test.content_hash()
    assert cli.main(["tasks", "info", str(out / "tasks_mini_1_train.npz")]) == 0
    assert "1 train tasks, level mini_1" in capsys.readouterr().out
