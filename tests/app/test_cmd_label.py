"""`knotlab label --oracle` writes oracle executions into the labelling store, resumably."""

from __future__ import annotations

import json

import pytest

from knotlab.app import cli
from knotlab.labeling_db.store import open_store
from tests.minilib import write_mini_files

pytestmark = pytest.mark.xdist_group("minilib")


def test_oracle_labels_name_their_cpu_kind_and_a_resume_on_another_kind_warns(
    tmp_path, capsys, monkeypatch
):
    from knotlab.core import machine

    lib_path, tasks_path = write_mini_files(tmp_path, n_tasks=2, split="train")
    url = f"sqlite:///{tmp_path / 'labels.db'}"
    args = ["label", "--oracle", "--task-set", str(tasks_path), "--library", str(lib_path)]
    args += ["--db", url, "--sim-budget", "1", "--workers", "1", "--no-progress"]
    assert cli.main([*args, "--tasks", "1"]) == 0
    assert "warning" not in capsys.readouterr().err  # a fresh store mixes nothing
    here = machine.numeric_kind()
    with open_store(url) as store:
        (ex,) = store.training_executions(include_unfinished=True)
    assert ex.metadata["numeric_kind"] == here
    # The same store resumed on a machine of another kind: one line says so, and labels on.
    monkeypatch.setattr(machine, "numeric_kind", lambda: "avx9000")
    assert cli.main([*args, "--tasks", "2"]) == 0
    err = capsys.readouterr().err
    assert f"holds labels made on {here}; this machine is avx9000" in err
    with open_store(url) as store:
        assert len(store.training_executions(include_unfinished=True)) == 2
    assert cli.main([*args, "--tasks", "2"]) == 0  # nothing left to label: nothing to say
    assert "warning" not in capsys.readouterr().err


def test_oracle_labelling_fills_the_store_and_resumes(tmp_path, capsys):
    lib_path, tasks_path = write_mini_files(tmp_path, n_tasks=2, split="train")
    url = f"sqlite:///{tmp_path / 'labels.db'}"
    args = ["label", "--oracle", "--task-set", str(tasks_path), "--library", str(lib_path)]
    args += ["--db", url, "--tasks", "1", "--sim-budget", "3", "--workers", "1", "--json"]
    assert cli.main(args) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert first["tasks"] == 1 and first["simulations"] <= 3
    with open_store(url) as store:
        stored = store.training_executions(include_unfinished=True)
    assert len(stored) == 1
    ex = stored[0]
    assert ex.source == "oracle" and ex.execution_id.startswith("oracle-")
    assert first["solved"] == int(ex.ended_in_knot)
    # A second run skips the task already in the store.
    assert cli.main(args) == 0
    second = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert second["tasks"] == 0 and second["skipped_already_labelled"] == 1


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--top", "0"], "argument --top: expected an integer >= 1, got '0'"),
        (["--top", "-3"], "argument --top: expected an integer >= 1, got '-3'"),
        (["--sim-budget", "0"], "argument --sim-budget: expected an integer >= 1"),
        (["--tasks", "0"], "argument --tasks: expected an integer >= 1, got '0'"),
        (["--tasks", "train"], "argument --tasks: expected an integer, got 'train'"),
    ],
)
def test_label_refuses_budgets_that_would_simulate_nothing(tmp_path, capsys, extra, message):
    lib_path, tasks_path = write_mini_files(tmp_path, n_tasks=1, split="train")
    url = f"sqlite:///{tmp_path / 'labels.db'}"
    args = ["label", "--oracle", "--task-file", str(tasks_path), "--library", str(lib_path)]
    assert cli.main([*args, "--db", url, *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "labels.db").exists()  # refused before anything was written


def test_label_refuses_a_test_split(tmp_path, capsys):
    lib_path, test_path = write_mini_files(tmp_path, n_tasks=1, split="test")
    url = f"sqlite:///{tmp_path / 'labels.db'}"
    args = ["label", "--oracle", "--library", str(lib_path), "--db", url, "--workers", "1"]
    assert cli.main([*args, "--task-file", str(test_path)]) == 2
    assert "'test' task set" in capsys.readouterr().err
    assert cli.main([*args, "--split", "test"]) == 2  # the task's shipped test set
    assert "'test' task set" in capsys.readouterr().err
    assert not (tmp_path / "labels.db").exists()


def test_label_defaults_are_the_tasks_shipped_files() -> None:
    from knotlab.app import defaults, options

    args = cli.build_parser().parse_args(["label", "--oracle"])
    assert (args.task, args.split, args.top, args.tasks) == ("overhand", "train", 10, None)
    assert options.task_set_file(args, args.split) == defaults.task_set_path("main", "train")
    assert options.library_file(args) == defaults.library_path("overhand")
    args = cli.build_parser().parse_args(["label", "--oracle", "--level", "hard"])
    assert options.task_set_file(args, "train") == defaults.task_set_path("hard", "train")
