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
    args = ["suggest", "--task-set", str(tasks), "--model", str(model), "--library", str(lib)]
    assert main([*args, "--limit", "2", "--json", "--no-progress"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["rank"] for r in rows] == [1, 2]
    assert all(set(r["choices"]) == {"nn", "greedy"} for r in rows)
    assert all(r["key"].startswith("mini-train-") for r in rows)
    _, test_tasks = write_mini_files(tmp_path, n_tasks=1, split="test")
    assert main([*args[:1], "--tasks-file", str(test_tasks), *args[3:]]) == 2  # old spelling
    assert "training starts" in capsys.readouterr().err


def test_suggest_honours_knotlab_db_url_unless_a_task_set_is_given(
    tmp_path, capsys, monkeypatch
) -> None:
    from knotlab.app import cmd_suggest

    _, tasks = write_mini_files(tmp_path, n_tasks=2, split="train")
    read: list[str] = []

    def clouds_from_store(url: str) -> dict:
        read.append(url)
        return {}

    monkeypatch.setattr(cmd_suggest, "_clouds_from_store", clouds_from_store)
    monkeypatch.setenv("KNOTLAB_DB_URL", "sqlite:///env.db")
    args = ["suggest", "--no-progress", "--json"]  # the task's shipped model and library
    capsys.readouterr()
    assert main(args) == 0 and read == ["sqlite:///env.db"]
    assert main([*args, "--db", "sqlite:///flag.db"]) == 0 and read[-1] == "sqlite:///flag.db"
    capsys.readouterr()
    assert main([*args, "--task-set", str(tasks)]) == 0 and len(read) == 2  # the file wins
    assert sorted(r["key"] for r in json.loads(capsys.readouterr().out)) == [
        "mini-train-0000",
        "mini-train-0001",
    ]
    assert main([*args, "--db", "sqlite:///flag.db", "--task-set", str(tasks)]) == 2
    assert "give --db or --task-set, not both" in capsys.readouterr().err
