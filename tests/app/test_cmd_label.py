"""`knotlab label --oracle` writes oracle executions into the labelling store, resumably."""

from __future__ import annotations

import json

import pytest

from knotlab.app import cli
from knotlab.labeling_db.store import open_store
from tests.minilib import write_mini_files

pytestmark = pytest.mark.xdist_group("minilib")


def test_oracle_labelling_fills_the_store_and_resumes(tmp_path, capsys):
    lib_path, tasks_path = write_mini_files(tmp_path, n_tasks=2)
    url = f"sqlite:///{tmp_path / 'labels.db'}"
    args = ["label", "--oracle", "--task-file", str(tasks_path), "--library", str(lib_path)]
    args += ["--db", url, "--limit", "1", "--sim-budget", "3", "--workers", "1", "--json"]
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
