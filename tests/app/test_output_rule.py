"""One rule for outputs (app.options.check_output): a command writes into a path that exists only
with --force or when it is its own output to resume, and into a shipped or committed one only
with --force; results folders and tries files carry an identity; oracle labels are keyed by the
start rope, not only the task id.

Every test works on tmp copies: results/, static/ and a task's data folder are tmp folders here
(`shipped`), so no committed file is ever touched.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from knotlab.app import cli, defaults, options
from knotlab.core.selection.labels import LabelledExecution, LabelledStep
from knotlab.labeling_db.store import open_store
from tests.minilib import mini_executions, mini_library, mini_tasks, write_mini_files

pytestmark = pytest.mark.xdist_group("minilib")


@pytest.fixture
def shipped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """Tmp stand-ins for results/, static/ and a task's data folder."""
    root = tmp_path / "repo"
    places = {name: root / name for name in ("results", "static", "data")}
    for folder in places.values():
        folder.mkdir(parents=True)
    monkeypatch.setattr(defaults, "RESULTS_DIR", places["results"])
    monkeypatch.setattr(defaults, "STATIC_DIR", places["static"])
    monkeypatch.setattr(defaults, "shipped_dirs", lambda: (places["data"], places["results"]))
    return places


@pytest.fixture(scope="module")
def mini(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The mini library and one test task, and a bench run of nn on it (1 step)."""
    d = tmp_path_factory.mktemp("output_rule")
    library, tasks = write_mini_files(d, n_tasks=1)
    files = {"dir": d, "library": library, "tasks": tasks, "run": d / "run"}
    assert cli.main(_bench(files, files["run"])) == 0
    return files


def _bench(files: dict[str, Path], out: Path, *extra: str) -> list[str]:
    # `--out`: the spelling of the probe (a prefix of --out-dir)
    return [
        *("bench", "--policies", "nn", "--tasks", "1", "--out", str(out)),
        *("--library", str(files["library"]), "--task-set", str(files["tasks"])),
        *("--max-steps", "1", "--workers", "1", "--no-progress", "--json", *extra),
    ]


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def _one_line_error(capsys: pytest.CaptureFixture[str], *parts: str) -> str:
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and ": error: " in lines[0] and "Traceback" not in err, err
    for part in parts:
        assert part in lines[0], lines[0]
    return lines[0]


# ---------------------------------------------------------------- shipped and committed outputs


def test_bench_resumes_a_committed_results_folder_only_with_force(mini, shipped, capsys):
    out = shipped["results"] / "table1_mini"
    assert cli.main(_bench(mini, out)) == 0  # a new folder: nothing committed there yet
    before = _files(out)
    capsys.readouterr()
    # now it is committed: not resumed, results.json and the chart not redrawn
    assert cli.main(_bench(mini, out)) == 2
    _one_line_error(capsys, f"--out-dir {out}", "shipped or committed", "--force")
    assert _files(out) == before
    assert cli.main(_bench(mini, out, "--force")) == 0  # told to: resumed, nothing rerun
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["ran"] == 0 and summary["resumed"] == 1


def test_playback_does_not_replace_a_shipped_gif_without_force(mini, shipped, tmp_path, capsys):
    gif = shipped["static"] / "playback_knot.gif"
    gif.write_bytes(b"GIF89a the shipped one")
    episode = f"{mini['run']}:nn:mini-test-0000"
    args = ["playback", episode, "--library", str(mini["library"]), "--size", "64"]
    args += ["--task-set", str(mini["tasks"]), "--fps", "2"]
    assert cli.main([*args, "--out", str(gif)]) == 2
    _one_line_error(capsys, "shipped or committed animation", "--force")
    assert gif.read_bytes() == b"GIF89a the shipped one"
    mine = tmp_path / "mine.gif"
    mine.write_bytes(b"GIF89a mine")
    assert cli.main([*args, "--out", str(mine)]) == 2  # an existing file: not without --force
    _one_line_error(capsys, "exists", "--force")
    assert mine.read_bytes() == b"GIF89a mine"
    assert cli.main([*args, "--out", str(mine), "--force"]) == 0
    assert mine.read_bytes()[:6] == b"GIF89a" and mine.stat().st_size > 100


def _labels_db(tmp_path: Path, executions: list[LabelledExecution]) -> str:
    url = f"sqlite:///{tmp_path / 'labels.db'}"
    with open_store(url) as store:
        store.add_executions(executions)
    return url


def test_labels_export_does_not_replace_committed_labels_without_force(shipped, tmp_path, capsys):
    url = _labels_db(tmp_path, mini_executions(2))
    committed = shipped["results"] / "labels_oracle_main.jsonl"
    committed.write_text('{"format":"knotlab-labels","version":1}\n')
    before = committed.read_bytes()
    assert cli.main(["labels", "export", "--db", url, "--out", str(committed)]) == 2
    _one_line_error(capsys, "shipped or committed labels file", "--force")
    assert committed.read_bytes() == before
    assert cli.main(["labels", "export", "--db", url, "--out", str(committed), "--force"]) == 0
    assert len(committed.read_text().splitlines()) == 3  # the header and two executions
    mine = tmp_path / "mine.jsonl"
    assert cli.main(["labels", "export", "--db", url, "--out", str(mine)]) == 0
    capsys.readouterr()
    assert cli.main(["labels", "export", "--db", url, "--out", str(mine)]) == 2
    _one_line_error(capsys, "exists", "--force")


def _labels_with_candidates(path: Path) -> tuple[Path, list[LabelledExecution]]:
    """One mini execution whose first two steps show two candidates (a tries job each)."""
    from datetime import UTC, datetime

    from knotlab.labeling_db.interchange import write_labels
    from knotlab.labeling_db.store import StoredExecution

    when = datetime(2024, 1, 1, tzinfo=UTC)
    keys = mini_library(2).keys
    ex = mini_executions(2)[0]
    steps = tuple(
        dataclasses.replace(s, candidates=(s.chosen_demo, *(k for k in keys if k != s.chosen_demo)))
        for s in ex.steps[:2]
    )
    ex = dataclasses.replace(ex, steps=steps, ended_in_knot=False)
    with open(path, "w", encoding="utf-8") as fh:
        write_labels([StoredExecution(ex, started_at=when, finished_at=when)], fh, "jsonl")
    return path, [ex]


def _tries_line(execution_id: str, step: int, demos: tuple[str, ...]) -> str:
    tried = [{"demo": d, "stage": 1, "knot": False, "failure": None} for d in demos]
    line = {"execution_id": execution_id, "step_index": step, "stage_before": 0, "tried": tried}
    return json.dumps(line) + "\n"


def _tries_args(labels: Path, library: Path, out: Path, *extra: str) -> list[str]:
    return [
        *("labels", "tries", "--labels", str(labels), "--library", str(library)),
        *("--top", "1", "--out", str(out), "--workers", "1", "--no-progress", *extra),
    ]


def test_labels_tries_appends_to_a_committed_file_only_with_force(shipped, tmp_path, capsys):
    labels, (ex,) = _labels_with_candidates(tmp_path / "labels.jsonl")
    library = mini_library(2).save(tmp_path / "lib.npz")
    committed = shipped["results"] / "tries_main.jsonl"
    step = ex.steps[0]
    committed.write_text(_tries_line(ex.execution_id, 0, step.candidates[:1]))
    before = committed.read_bytes()
    assert cli.main(_tries_args(labels, library, committed)) == 2
    _one_line_error(capsys, "shipped or committed tries file", "--force")
    assert committed.read_bytes() == before
    assert cli.main(_tries_args(labels, library, committed, "--force")) == 0  # resumed: 1 state
    lines = committed.read_text().splitlines()
    assert len(lines) == 2 and lines[0] == before.decode().strip()
    assert json.loads(lines[1])["step_index"] == 1


def test_labels_tries_name_their_cpu_kind_and_a_resume_on_another_kind_warns(tmp_path, capsys):
    from knotlab.core.machine import numeric_kind

    labels, (ex,) = _labels_with_candidates(tmp_path / "labels.jsonl")
    library = mini_library(2).save(tmp_path / "lib.npz")
    out = tmp_path / "tries.jsonl"
    first = json.loads(_tries_line(ex.execution_id, 0, ex.steps[0].candidates[:1]))
    out.write_text(json.dumps({**first, "numeric_kind": "avx9000"}) + "\n")  # another machine's
    assert cli.main(_tries_args(labels, library, out)) == 0  # resumed: the second state
    err = capsys.readouterr().err
    assert f"holds tries made on avx9000; this machine is {numeric_kind()}" in err
    made_here = json.loads(out.read_text().splitlines()[1])
    assert made_here["step_index"] == 1 and made_here["numeric_kind"] == numeric_kind()
    assert cli.main(_tries_args(labels, library, out)) == 0  # nothing left to try: no warning
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"format":"knotlab-labels","version":1}\n', "not a tried-candidates line"),
        (_tries_line("oracle-other-0001", 0, ("s000-t0",)), "made from other labels"),
        (_tries_line("mini-exec-0", 0, ("s001-t0",)), "other labels or another --top"),
    ],
    ids=["not-tries", "other-labels", "other-top"],
)
def test_labels_tries_refuses_a_file_that_is_not_its_own(tmp_path, capsys, content, message):
    labels, (ex,) = _labels_with_candidates(tmp_path / "labels.jsonl")
    assert ex.execution_id == "mini-exec-0" and ex.steps[0].candidates[0] == "s000-t0"
    library = mini_library(2).save(tmp_path / "lib.npz")
    out = tmp_path / "tries.jsonl"
    out.write_text(content)
    for extra in ((), ("--force",)):  # never appended to, not even when told to
        assert cli.main(_tries_args(labels, library, out, *extra)) == 2
        _one_line_error(capsys, str(out), message)
        assert out.read_text() == content


# ------------------------------------------------------------------ bench's own results folder


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ("hello world\n", "not JSON"),
        ('{"a": 1}\n', "no 'policy' field"),
        ("[1, 2]\n", "not an object"),
        ('{"policy": "nn", "task_id": "mini-test-0000"}\n', "no 'success' field"),
    ],
    ids=["text", "other-object", "array", "no-outcome"],
)
def test_bench_refuses_a_folder_whose_outcomes_are_not_bench_lines(
    mini, tmp_path, capsys, content, problem
):
    out = tmp_path / "other"
    out.mkdir()
    (out / "outcomes.jsonl").write_text(content)
    for extra in ((), ("--force",)):  # never appended to, not even when told to
        assert cli.main(_bench(mini, out, *extra)) == 2
        _one_line_error(capsys, "outcomes.jsonl:1", "not a knotlab bench outcome line", problem)
        assert _files(out) == {"outcomes.jsonl": content.encode()}


def test_bench_replaces_another_folder_s_files_only_with_force(mini, tmp_path, capsys):
    out = tmp_path / "other"
    out.mkdir()
    (out / "results.json").write_text('{"mine": true}\n')
    (out / "notes.txt").write_text("kept\n")
    assert cli.main(_bench(mini, out)) == 2
    _one_line_error(capsys, "is not this command's own output to resume", "--force")
    assert _files(out) == {"notes.txt": b"kept\n", "results.json": b'{"mine": true}\n'}
    assert cli.main(_bench(mini, out, "--force")) == 0
    assert json.loads((out / "results.json").read_text())["format"] == "knotlab-bench-results"
    assert (out / "notes.txt").read_text() == "kept\n"
    # an existing folder holding none of bench's files (a log beside it) is written into
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "segments.log").write_text("start\n")
    assert cli.main(_bench(mini, fresh)) == 0


def test_bench_resumes_its_own_folder_without_force(mini, tmp_path, capsys):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(mini["run"], out)
    assert cli.main(_bench(mini, out)) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["resumed"] == 1


# ------------------------------------------------------------- every other command that writes


@pytest.mark.parametrize(
    ("argv", "name"),
    [
        (["tie"], "knot.png"),
        (["demos", "generate", "--starts", "1", "--workers", "1", "--no-progress"], "lib.npz"),
        (["train", "--labels", "none.jsonl", "--no-progress"], "model.npz"),
        (["playback", "r:nn:t-0"], "x.gif"),
        (["labels", "export", "--db", "sqlite:///none.db"], "x.jsonl"),
        (["tasks", "generate", "--seed", "0", "--no-progress"], "tasks_main_train.npz"),
    ],
    ids=["tie", "demos", "train", "playback", "export", "tasks"],
)
def test_no_command_replaces_an_existing_file_without_force(
    tmp_path, monkeypatch, capsys, argv, name
):
    monkeypatch.chdir(tmp_path)
    target = tmp_path / name
    target.write_bytes(b"someone else's")
    where = ["--out-dir", "."] if argv[0] == "tasks" else ["--out", name]
    assert cli.main([*argv, *where]) == 2
    _one_line_error(capsys, "exists; write elsewhere or pass --force")
    assert target.read_bytes() == b"someone else's"


def test_tasks_generate_writes_no_new_file_into_a_shipped_folder(shipped, capsys):
    argv = ["tasks", "generate", "--seed", "0", "--level", "new", "--no-progress"]
    assert cli.main([*argv, "--out-dir", str(shipped["data"])]) == 2
    _one_line_error(capsys, "shipped or committed folder", "--force")
    assert list(shipped["data"].iterdir()) == []


def test_committed_is_an_existing_path_under_results_static_or_a_task_s_data(shipped):
    (shipped["results"] / "run").mkdir()
    assert options.is_committed(shipped["results"] / "run")
    assert options.is_committed(shipped["static"])
    assert not options.is_committed(shipped["results"] / "new")  # not there yet
    assert not options.is_committed(shipped["results"].parent / "elsewhere")


# ------------------------------------------------------------- oracle labels keyed by the rope


def _oracle_execution(task_id: str, nodes: np.ndarray, metadata: dict | None = None):
    lib = mini_library(2)
    seg = lib[0]
    step = LabelledStep(0, seg.pre_cloud_n3, seg.key, "progressed", nodes)
    return LabelledExecution(
        f"oracle-{task_id}",
        "oracle",
        "oracle",
        (step,),
        ended_in_knot=False,
        task_id=task_id,
        library_hash=lib.content_hash(),
        metadata=metadata or {},
    )


def _label_args(tmp_path: Path, url: str) -> list[str]:
    lib_path, tasks_path = write_mini_files(tmp_path, n_tasks=1, split="train")
    return [
        *("label", "--oracle", "--task-set", str(tasks_path), "--library", str(lib_path)),
        *("--db", url, "--sim-budget", "3", "--workers", "1", "--no-progress", "--json"),
    ]


def test_oracle_labelling_refuses_a_labelled_task_id_whose_rope_differs(tmp_path, capsys):
    task = mini_tasks(1, "train")[0]
    other = task.start_nodes_k3 + np.array([0.0, 0.05, 0.0])  # the same id, another rope
    url = _labels_db(tmp_path, [_oracle_execution(task.task_id, other)])
    assert cli.main(_label_args(tmp_path, url)) == 2
    line = _one_line_error(capsys, task.task_id, "ropes differ")
    assert "50.0 mm" in line
    with open_store(url) as store:
        assert len(store.training_executions(include_unfinished=True)) == 1  # nothing relabelled


def test_oracle_labelling_skips_a_task_labelled_from_the_same_rope(tmp_path, capsys):
    task = mini_tasks(1, "train")[0]
    url = _labels_db(tmp_path, [_oracle_execution(task.task_id, task.start_nodes_k3)])
    assert cli.main(_label_args(tmp_path, url)) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["skipped_already_labelled"] == 1 and summary["tasks"] == 0


def test_oracle_labels_record_the_start_rope_and_a_differing_hash_is_refused(tmp_path, capsys):
    from knotlab.core.experiments.labeller import START_HASH_KEY, start_rope_hash

    task = mini_tasks(1, "train")[0]
    recorded = {START_HASH_KEY: start_rope_hash(task.start_nodes_k3 + 0.01)}
    # the hash decides even where the stored step's rope would pass
    url = _labels_db(tmp_path, [_oracle_execution(task.task_id, task.start_nodes_k3, recorded)])
    assert cli.main(_label_args(tmp_path, url)) == 2
    _one_line_error(capsys, task.task_id, "ropes differ", "start rope hash")
