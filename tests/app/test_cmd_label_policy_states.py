"""`knotlab label --oracle --from-policy greedy`: labels where the policy goes, with provenance."""

from __future__ import annotations

import json

from knotlab.app.cli import main
from knotlab.core.experiments.policy_states import REACHED_BY
from knotlab.core.machine import numeric_kind
from knotlab.core.selection.qmodel import QModel
from knotlab.core.tasks import get_task
from knotlab.labeling_db.store import open_store

MODEL = get_task("overhand").files.model_path


def test_a_round_labels_the_states_greedy_reaches_records_who_reached_them_and_resumes(
    tmp_path, capsys
):
    db = f"sqlite:///{tmp_path / 'l.db'}"
    argv = [
        "label",
        "--oracle",
        "--from-policy",
        "greedy",
        "--model",
        str(MODEL),
        "--round",
        "2",
        "--tasks",
        "1",
        "--db",
        db,
        "--workers",
        "1",
        "--no-progress",
        "--json",
    ]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["starts"] == 1 and summary["model_hash"] == QModel.load(MODEL).content_hash()
    with open_store(db) as store:
        executions = store.training_executions(include_unfinished=True)
    assert executions, "greedy reaches at least one state after the start"
    steps = []
    for ex in executions:
        reached = ex.metadata[REACHED_BY]
        assert reached["policy"] == "greedy" and reached["round"] == 2
        assert reached["model"] == summary["model_hash"]
        assert reached["start_task_id"] == "main-train-0000"
        assert ex.metadata["numeric_kind"] == numeric_kind()  # the CPU kind that labelled it
        assert ex.execution_id == f"policy-greedy-r2-main-train-0000-t{reached['step']}"
        assert len(reached["chosen_before"]) == reached["step"] >= 1
        assert ex.steps or ex.dead_ends  # a way to the knot from there, or a dead end
        steps.append(reached["step"])
    assert sorted(steps) == list(range(1, len(steps) + 1))
    # resumable: a second run finds the start done and adds nothing
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["starts"] == 0
    # and the labels files carry the provenance
    out = tmp_path / "l.jsonl"
    assert main(["labels", "export", "--db", db, "--out", str(out)]) == 0
    line = json.loads(out.read_text().splitlines()[1])
    assert line["metadata"][REACHED_BY]["model"] == summary["model_hash"]


def test_from_policy_needs_a_model(tmp_path, capsys):
    db = f"sqlite:///{tmp_path / 'l.db'}"
    assert main(["label", "--oracle", "--from-policy", "greedy", "--db", db]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--from-policy needs --model" in err[0]
