"""Labels in the original HDF5 layout: a store's labels out and back, refusals named."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from knotlab.app.cli import main
from knotlab.core.outcomes import StepOutcome
from knotlab.labeling_db.interchange import read_labels
from knotlab.labeling_db.store import open_store

ROOT = Path(__file__).resolve().parents[2]
LABELS = ROOT / "results/labels_oracle_main.jsonl"


@pytest.fixture(scope="module")
def source_db(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, list]:
    items = read_labels(LABELS)[:12]
    url = f"sqlite:///{tmp_path_factory.mktemp('db') / 'src.db'}"
    with open_store(url, create=True, persistent=True) as store:
        store.add_executions(items)
    return url, [i.execution for i in items]


def test_export_then_import_keeps_states_actions_knots_and_dead_ends(source_db, tmp_path, capsys):
    url, executions = source_db
    out = tmp_path / "labels.h5"
    assert main(["labels", "export", "--db", url, "--out", str(out)]) == 0
    with h5py.File(out) as f:  # the original layout: (task, step) groups and f<k> dead ends
        assert "(0, 0)" in f and f["(0, 0)/action"][()].decode().endswith("-seg00")
        assert set(f["(0, 0)"]) >= {"cloud_xyz", "action", "knot"}
    dest = f"sqlite:///{tmp_path / 'dest.db'}"
    assert main(["labels", "import", str(out), "--db", dest]) == 0
    with open_store(dest) as store:
        back = [i.execution for i in store.stored_executions()]
    solved = [e for e in executions if e.steps]
    tasks = [e for e in back if e.steps]
    assert len(tasks) == len(solved)
    for mine, theirs in zip(solved, tasks, strict=True):
        assert [s.chosen_demo for s in theirs.steps] == [s.chosen_demo for s in mine.steps]
        assert [s.outcome for s in theirs.steps] == [s.outcome for s in mine.steps]
        assert theirs.source == "human" and theirs.labeller == "hdf5:labels.h5"
        for a, b in zip(mine.steps, theirs.steps, strict=True):
            assert np.allclose(a.cloud_n3, b.cloud_n3, atol=1e-6)
    assert theirs.steps[-1].outcome is StepOutcome.KNOT
    dead = sum(len(e.dead_ends) for e in executions)
    assert sum(len(e.dead_ends) for e in back) == dead


def test_a_bad_labels_file_is_refused_naming_group_and_key(source_db, tmp_path, capsys):
    url, _ = source_db
    out = tmp_path / "labels.h5"
    assert main(["labels", "export", "--db", url, "--out", str(out)]) == 0
    with h5py.File(out, "a") as f:
        del f["(1, 0)/action"]
        f["(1, 0)/action"] = "demo9-seg07"
    capsys.readouterr()
    dest = tmp_path / "dest.db"
    assert main(["labels", "import", str(out), "--db", f"sqlite:///{dest}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "(1, 0)/action: segment 'demo9-seg07' is not in the library" in err[0]
    assert not dest.exists()
