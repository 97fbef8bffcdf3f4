"""`knotlab labels agreement`: the per-pair table and its JSON form."""

from __future__ import annotations

import json

from knotlab.app.cli import main
from knotlab.core.selection.labels import LabelledStep
from knotlab.labeling_db.store import StateProvenance, open_store
from tests.db_fixtures import cloud


def _store_two_labellers(url: str) -> None:
    with open_store(url) as store:
        (sid,) = store.add_start_states([cloud(1)], provenance=[StateProvenance("task-a", 0, 1)])
        for who, demo in (("ann", "d1"), ("bob", "d2")):
            ep = store.start_episode(who, state_id=sid, task_id="task-a")
            assert ep is not None
            store.add_label(ep.episode_id, LabelledStep(0, cloud(2), demo, "progressed"))
            store.finish_episode(ep.episode_id)


def test_agreement_prints_the_pair_and_its_disagreement(tmp_path, capsys) -> None:
    url = f"sqlite:///{tmp_path / 'k.db'}"
    _store_two_labellers(url)
    assert main(["labels", "agreement", "--db", url]) == 0
    out = capsys.readouterr().out
    assert "ann" in out and "bob" in out and "task-a step 0: d1 vs d2" in out
    assert main(["labels", "agreement", "--db", url, "--json"]) == 0
    (pair,) = json.loads(capsys.readouterr().out)
    assert (pair["n_compared"], pair["n_agree"], pair["top1"]) == (1, 0, 0.0)


def test_agreement_on_a_missing_database_is_a_one_line_error(tmp_path, capsys) -> None:
    assert main(["labels", "agreement", "--db", f"sqlite:///{tmp_path / 'none.db'}"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("knotlab labels agreement: error:") and "\n" not in err
