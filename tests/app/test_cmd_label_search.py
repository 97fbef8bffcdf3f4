"""`knotlab label --search la2x5`: the search's own knotted episodes as labels, with provenance."""

from __future__ import annotations

import json

from knotlab.app.cli import main
from knotlab.core.machine import numeric_kind
from knotlab.core.selection.qmodel import QModel
from knotlab.core.selection.tries import read_tries
from knotlab.core.tasks import get_task
from knotlab.labeling_db.store import open_store

MODEL = get_task("overhand").files.model_path


def _argv(db: str, *extra: str) -> list[str]:
    return ["label", "--search", "la2x5", "--model", str(MODEL), "--tasks", "1", "--db", db,
            "--workers", "1", "--no-progress", "--json", *extra]  # fmt: skip


def test_the_search_labels_a_start_with_its_choices_records_its_model_and_resumes(tmp_path, capsys):
    db = f"sqlite:///{tmp_path / 'l.db'}"
    tries = tmp_path / "tries.jsonl"
    assert main(_argv(db, "--tries-out", str(tries))) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    model_hash = QModel.load(MODEL).content_hash()
    assert summary["starts"] == 1 and summary["model_hash"] == model_hash
    with open_store(db) as store:
        (ex,) = store.training_executions(include_unfinished=True)
    assert ex.execution_id == "search-la2x5-main-train-0000" and ex.labeller == "search-la2x5"
    assert ex.metadata["labelled_by"] == {"policy": "la2x5", "model": model_hash}
    # the search knots this start: its choices are the labelled steps, ending in the knot
    assert ex.ended_in_knot and summary["labelled_states"] == len(ex.steps) >= 2
    assert [s.chosen_demo for s in ex.steps] == ex.metadata["search_chosen"]
    assert all(s.model_version == model_hash for s in ex.steps)
    got = read_tries(tries)  # one line per labelled state, for `knotlab train --tries`
    assert sorted(got) == [(ex.execution_id, i) for i in range(len(ex.steps))]
    assert all(not rec.advanced(t) for rec in got.values() for t in rec.tried)
    # the CPU kind that made the label and its tries (a near-tie can go the other way elsewhere)
    assert ex.metadata["numeric_kind"] == numeric_kind()
    assert {rec.numeric_kind for rec in got.values()} == {numeric_kind()}
    # resumable: a second run finds the start labelled and writes nothing more
    before = tries.read_text()
    assert main(_argv(db, "--tries-out", str(tries))) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["starts"] == 0
    assert tries.read_text() == before


def test_search_label_misuse_gets_one_line_and_writes_nothing(tmp_path, capsys):
    db = f"sqlite:///{tmp_path / 'l.db'}"
    foreign = tmp_path / "foreign.jsonl"
    line = {"execution_id": "oracle-x", "step_index": 0, "stage_before": 0, "tried": []}
    foreign.write_text(json.dumps(line) + "\n")
    cases = [
        (["label", "--search", "la2x5", "--db", db], "--search needs --model"),
        (
            _argv(db, "--policy-model", str(MODEL)),
            "--policy-model is used with --search and --from-policy only",
        ),
        (
            ["label", "--oracle", "--policy-model", str(MODEL), "--db", db],
            "--policy-model is used with --search and --from-policy only",
        ),
        (
            _argv(db, "--from-policy", "greedy", "--policy-model", str(tmp_path / "none.npz")),
            "--policy-model",
        ),
        (
            ["label", "--oracle", "--tries-out", str(tmp_path / "t.jsonl"), "--db", db],
            "--tries-out is used with --search only",
        ),
        (_argv(db, "--tries-out", str(foreign)), "holds tries of other executions"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (argv, err)
    assert foreign.read_text() == json.dumps(line) + "\n"
    assert not (tmp_path / "l.db").exists() or not open_store(db).training_executions(
        include_unfinished=True
    )


def test_the_search_labels_the_states_greedy_reaches_exactly_as_greedy_left_them(tmp_path, capsys):
    """DAgger with the search as the expert: each reached state is labelled from the simulator
    state greedy left (replayed here), and records what reached it."""
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    db = f"sqlite:///{tmp_path / 'l.db'}"
    tries = tmp_path / "tries.jsonl"
    argv = ["label", "--search", "la1x10", "--model", str(MODEL), "--from-policy", "greedy",
            "--round", "2", "--tasks", "1", "--db", db, "--workers", "1", "--no-progress",
            "--json", "--tries-out", str(tries)]  # fmt: skip
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    model_hash = QModel.load(MODEL).content_hash()
    assert summary["policy_model_hash"] == summary["model_hash"] == model_hash
    with open_store(db) as store:
        executions = store.training_executions(include_unfinished=True)
    task = get_task("overhand")
    start = task.files.load_task_set("main", "train")[0]
    greedy = Agent.default("greedy")
    with RopeWorld() as world:
        world.reset(start.start_nodes_k3)
        replay = []  # the rope before each of greedy's steps after the first
        for step in range(task.step_limit):
            if step:
                replay.append(world.rope_nodes())
            outcome = greedy.act(world, greedy.choose(world, step_index=step).action)
            if outcome.knot or outcome.exploded:
                break
    assert summary["reached_states"] == len(executions) == len(replay) >= 1
    for ex in sorted(executions, key=lambda e: e.execution_id):
        step = ex.metadata["reached_by"]["step"]
        assert ex.execution_id == f"search-la1x10-greedy-r2-{start.task_id}-t{step}"
        assert ex.metadata["reached_by"]["policy"] == "greedy"
        assert ex.metadata["reached_by"]["round"] == 2
        assert ex.metadata["labelled_by"] == {"policy": "la1x10", "model": model_hash}
        assert ex.task_id == f"{start.task_id}@greedy-r2-t{step}"
        if ex.steps:  # the search's label begins in the very state greedy reached
            assert ex.ended_in_knot and len(ex.steps) <= task.step_limit - step
            assert ex.steps[0].rope_nodes_k3 is not None
            assert abs(ex.steps[0].rope_nodes_k3 - replay[step - 1]).max() < 1e-4
    assert summary["labelled_states"] == sum(len(e.steps) for e in executions)
    # on this start the search knots from a state greedy reached, so the checks above ran
    assert any(ex.steps for ex in executions) and read_tries(tries)
    # resumable: the start is done
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["starts"] == 0
