"""`knotlab bench` end to end on the tiny real library: results, resuming, refusals, engines."""

from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from knotlab.app import cli
from knotlab.core.demos.tasks import RopeTask
from knotlab.core.errors import InvalidInputError
from knotlab.core.experiments.bench import (
    BenchMismatchError,
    BenchWorker,
    EpisodeJob,
    OutcomeLog,
    RunIdentity,
    WorkerSpec,
    check_task_limits,
    plan_jobs,
    wanted_pairs,
    wilson_interval,
)
from knotlab.core.machine import numeric_kind
from tests.minilib import mini_library, write_mini_files, write_mini_labels

pytestmark = pytest.mark.xdist_group("bench")

N_TASKS = 2
POLICIES = "nn,greedy,oracle"


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Mini library, 3 test tasks, labels and a model trained on them via `knotlab train`."""
    d = tmp_path_factory.mktemp("bench_files")
    lib, tasks = write_mini_files(d, n_tasks=3)
    labels = write_mini_labels(d / "labels.jsonl")
    model = d / "model.npz"
    rc = cli.main(
        [
            *("train", "--labels", str(labels), "--library", str(lib), "--out", str(model)),
            *("--workers", "1", "--no-progress", "--validation-fraction", "0"),
        ]
    )
    assert rc == 0
    return {"dir": d, "library": lib, "tasks": tasks, "labels": labels, "model": model}


def _bench_args(files, out: Path, *extra: str, policies: str = POLICIES) -> list[str]:
    return [
        "bench",
        "--policies",
        policies,
        "--tasks",
        str(N_TASKS),
        "--out",
        str(out),
        "--library",
        str(files["library"]),
        "--task-set",
        str(files["tasks"]),
        "--model",
        str(files["model"]),
        "--max-steps",
        "1",
        "--workers",
        "1",
        "--no-progress",
        "--json",
        *extra,
    ]


def _last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def first_run(files, tmp_path_factory) -> dict:
    """One bench run of nn, greedy and oracle on 2 tasks (1 step each), kept for the tests."""
    out = tmp_path_factory.mktemp("bench_run") / "out"
    mp = pytest.MonkeyPatch()
    try:
        import io
        import sys

        buf = io.StringIO()
        mp.setattr(sys, "stdout", buf)
        rc = cli.main(_bench_args(files, out))
    finally:
        mp.undo()
    text = buf.getvalue()
    return {"rc": rc, "out": out, "stdout": text, "summary": json.loads(text.splitlines()[-1])}


# ---------------------------------------------------------------------------- pure functions


@pytest.mark.parametrize(
    ("k", "n", "low", "high"),
    [
        (0, 10, 0.0, 0.27753),  # upper = z^2 / (n + z^2)
        (5, 10, 0.23659, 0.76341),
        (10, 10, 0.72247, 1.0),
        (86, 100, 0.77863, 0.91474),  # scipy.stats.binomtest(...).proportion_ci("wilson")
        (107, 125, 0.78384, 0.90693),  # the paper's greedy count: 85.6 % of 125
        (1, 1, 0.20655, 1.0),
    ],
)
def test_wilson_interval_matches_known_values(k, n, low, high):
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(low, abs=1e-5)
    assert hi == pytest.approx(high, abs=1e-5)


def test_first_per_policy_limits_only_the_named_policies():
    tasks = [RopeTask(f"t{i}", np.zeros((5, 3)), 0, i) for i in range(3)]
    first = {"oracle": 1, "la1x10": 2}
    policies = ["la2x5", "oracle", "la1x10"]
    pairs = [(p, t.task_id) for _, t, p in wanted_pairs(tasks, policies, first)]
    assert pairs == [
        ("la2x5", "t0"),
        ("oracle", "t0"),
        ("la1x10", "t0"),
        ("la2x5", "t1"),
        ("la1x10", "t1"),
        ("la2x5", "t2"),
    ]
    check_task_limits(first, policies)
    with pytest.raises(InvalidInputError, match="not among the policies run"):
        check_task_limits({"la2x10": 5}, ["la2x5"])
    with pytest.raises(InvalidInputError, match=">= 1"):
        check_task_limits(0, ["la2x5"])


def test_first_flag_parses_one_k_or_per_policy_limits():
    from knotlab.app.cmd_bench import task_limits

    assert task_limits("125") == 125
    assert task_limits("la1x10=125, oracle=100") == {"la1x10": 125, "oracle": 100}
    for bad in ("0", "la2x5=0", "=3", "la2x5=1,la2x5=2", "oracle=many"):
        with pytest.raises(argparse.ArgumentTypeError):
            task_limits(bad)


def test_wilson_interval_of_nothing_is_nan_and_bad_counts_raise():
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


def test_first_limits_only_the_search_policies():
    tasks = [RopeTask(f"t{i}", np.zeros((5, 3)), 0, i) for i in range(3)]
    jobs = plan_jobs(
        tasks, ["nn", "la1x10", "oracle"], {("nn", "t0")}, seed=0, max_steps=5, noise=0, first=1
    )
    assert [(j.policy, j.task_id) for j in jobs] == [
        ("la1x10", "t0"),
        ("oracle", "t0"),
        ("nn", "t1"),
        ("nn", "t2"),
    ]
    assert len({j.seed for j in jobs if j.task_id == "t0"}) == 1  # same noise for every policy


def test_run_identity_pins_the_model_only_once_a_learned_policy_ran():
    base = RunIdentity("lib", "tasks", 0, 0.0, 5, None)
    pinned = RunIdentity("lib", "tasks", 0, 0.0, 5, "m1").merged(base)
    assert pinned.model_hash == "m1"
    assert base.merged(pinned).model_hash == "m1"  # an nn-only rerun keeps the pin
    with pytest.raises(BenchMismatchError, match="model_hash"):
        RunIdentity("lib", "tasks", 0, 0.0, 5, "m2").merged(pinned)
    with pytest.raises(BenchMismatchError, match="noise"):
        RunIdentity("lib", "tasks", 0, 0.01, 5, None).merged(pinned)


def test_outcome_log_drops_a_torn_last_line_and_appends_cleanly(tmp_path):
    path = tmp_path / "o.jsonl"
    path.write_text('{"policy": "nn", "task_id": "a", "x": 1}\n{"policy": "nn", "task_')
    log = OutcomeLog(path)
    assert list(log.load()) == [("nn", "a")]
    with log.open() as fh:
        OutcomeLog.append(fh, {"policy": "nn", "task_id": "b"})
    assert list(log.load()) == [("nn", "a"), ("nn", "b")]


def test_worker_turns_an_unexpected_exception_into_an_error_outcome():
    worker = BenchWorker(WorkerSpec(mini_library(2)))
    try:
        bad = np.full((41, 3), np.nan)  # world.reset rejects it before the episode starts
        rec = worker.run(EpisodeJob("nn", 0, "bad-task", bad, 1, 1, 0.0))
        assert rec["success"] is False
        assert rec["failure_kind"] == "error"
        assert "bad-task" in rec["task_id"] and rec["error"]
        good = mini_library(2)[0].pre_nodes_k3
        assert worker.run(EpisodeJob("nn", 1, "ok", good, 1, 1, 0.0))["failure_kind"] != "error"
    finally:
        worker.close()


def test_a_measuring_model_simulates_the_world_s_radius_and_the_matched_world_itself():
    from knotlab.core.world.mismatch import parse_setting

    start = mini_library(2)[0].pre_nodes_k3
    job = EpisodeJob("nn", 0, "t", start, 1, 1, 0.0)
    measured = parse_setting("measured")
    thicker = parse_setting("radius+25")
    thick = BenchWorker(WorkerSpec(mini_library(2), None, None, thicker, measured))
    matched = BenchWorker(WorkerSpec(mini_library(2), None, None, agent_model=measured))
    blind = BenchWorker(WorkerSpec(mini_library(2), None, None, parse_setting("radius+25")))
    try:
        world, model_world, _ = thick._worlds_for(job)
        assert world.params.radius == pytest.approx(0.0125)
        assert model_world is not None
        assert model_world.params.radius == pytest.approx(0.0125, rel=3e-3)
        assert matched._worlds_for(job)[1] is None  # the world itself: today's episodes
        assert blind._worlds_for(job)[1].params.radius == pytest.approx(0.01)  # not measured
    finally:
        for w in (thick, matched, blind):
            w.close()


# ---------------------------------------------------------------------------- the command


def test_bench_writes_results_table_and_chart(first_run, files):
    assert first_run["rc"] == 0
    out = first_run["out"]
    res = json.loads((out / "results.json").read_text())
    assert res["format"] == "knotlab-bench-results"
    assert res["policies"] == ["nn", "greedy", "oracle"]
    assert res["library_hash"] == mini_library(2).content_hash()
    assert res["model_hash"] and res["task_set_hash"]
    assert set(res["packages"]) >= {"numpy", "scipy", "pybullet", "cvxpy", "knotlab"}
    assert res["machine"]["cpu_count"] >= 1
    assert isinstance(res["machine"]["blas"], list)  # which BLAS kernels made these numbers
    assert res["arguments"]["tasks"] == N_TASKS and res["arguments"]["max_steps"] == 1
    assert set(res["seeds"]["episode_seeds"]) == {"mini-test-0000", "mini-test-0001"}
    for policy in ("nn", "greedy", "oracle"):
        recs = res["outcomes"][policy]
        assert [r["task_id"] for r in recs] == ["mini-test-0000", "mini-test-0001"]
        for r in recs:
            assert r["policy"] == policy and r["n_steps"] <= 1
            assert isinstance(r["success"], bool) and len(r["decision_s"]) == r["n_steps"]
    row = {r["policy"]: r for r in res["table"]}
    assert row["nn"]["n"] == N_TASKS and row["nn"]["paper_rate"] == pytest.approx(0.688)
    assert row["oracle"]["paper_rate"] is None
    assert 0 <= row["greedy"]["wilson_low"] <= row["greedy"]["wilson_high"] <= 1
    assert (out / "table1.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len((out / "outcomes.jsonl").read_text().splitlines()) == 3 * N_TASKS
    text = first_run["stdout"]
    assert "Table I" in text and "68.8%" in text and "oracle" in text
    assert first_run["summary"]["ran"] == 3 * N_TASKS
    assert res["numeric_kinds"] == {numeric_kind(): 3 * N_TASKS}  # the CPU kind of every episode


def test_rerun_runs_nothing_and_reports_the_same_outcomes(first_run, files, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    before = json.loads((out / "results.json").read_text())["outcomes"]
    assert cli.main(_bench_args(files, out)) == 0
    summary = _last_json(capsys)
    assert summary["ran"] == 0 and summary["resumed"] == 3 * N_TASKS
    assert json.loads((out / "results.json").read_text())["outcomes"] == before


def test_interrupted_run_resumes_only_the_missing_episodes(first_run, files, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    lines = (out / "outcomes.jsonl").read_text().splitlines(keepends=True)
    lost = json.loads(lines[-1])
    # Killed while writing the last line: five whole lines and half of the sixth.
    (out / "outcomes.jsonl").write_text("".join(lines[:-1]) + lines[-1][:25])
    assert cli.main(_bench_args(files, out)) == 0
    summary = _last_json(capsys)
    assert summary["ran"] == 1 and summary["resumed"] == 3 * N_TASKS - 1
    after = (out / "outcomes.jsonl").read_text().splitlines()
    assert len(after) == 3 * N_TASKS and all(json.loads(line) for line in after)
    redone = json.loads(after[-1])
    assert (redone["policy"], redone["task_id"]) == (lost["policy"], lost["task_id"])


def test_more_tasks_and_other_policies_extend_an_existing_run(first_run, files, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    args = _bench_args(files, out, policies="nn")
    args[args.index("--tasks") + 1] = "3"
    args.remove("--model")  # nn needs no model; the pinned model hash stays
    args.remove(str(files["model"]))
    assert cli.main(args) == 0
    summary = _last_json(capsys)
    assert summary["ran"] == 1 and summary["resumed"] == N_TASKS
    identity = json.loads((out / "run.json").read_text())["identity"]
    assert identity["model_hash"] is not None


@pytest.mark.parametrize(
    ("flag", "value", "field"),
    [("--seed", "1", "seed"), ("--noise", "0.01", "noise"), ("--max-steps", "2", "max_steps")],
)
def test_rerun_with_different_defining_arguments_is_refused(
    first_run, files, tmp_path, capsys, flag, value, field
):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    before = (out / "outcomes.jsonl").read_bytes()
    args = _bench_args(files, out)
    if flag in args:
        args[args.index(flag) + 1] = value
    else:
        args += [flag, value]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "different arguments" in err and field in err
    assert (out / "outcomes.jsonl").read_bytes() == before


@pytest.mark.slow
def test_rerun_with_another_model_or_library_is_refused(first_run, files, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    other = tmp_path / "other_model.npz"
    assert (
        cli.main(
            [
                *("train", "--labels", str(files["labels"]), "--library", str(files["library"])),
                *("--out", str(other), "--C", "7", "--workers", "1", "--no-progress"),
                *("--validation-fraction", "0"),
            ]
        )
        == 0
    )
    capsys.readouterr()
    args = _bench_args(files, out)
    args[args.index("--model") + 1] = str(other)
    assert cli.main(args) == 2
    assert "model_hash" in capsys.readouterr().err
    other_lib = mini_library(3).save(tmp_path / "lib3.npz")
    args = _bench_args(files, out, policies="nn")
    args[args.index("--library") + 1] = str(other_lib)
    assert cli.main(args) == 2
    assert "library_hash" in capsys.readouterr().err


def test_learned_policy_without_a_model_says_to_train_first(files, tmp_path, capsys, monkeypatch):
    from knotlab.app import defaults

    monkeypatch.setattr(defaults, "model_path", lambda task="overhand": tmp_path / "no_model.npz")
    args = _bench_args(files, tmp_path / "out", policies="nn,greedy")
    i = args.index("--model")
    del args[i : i + 2]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "knotlab train" in err and "greedy" in err
    assert not (tmp_path / "out" / "outcomes.jsonl").exists()


def test_unknown_policy_is_refused_before_any_work(files, tmp_path, capsys):
    assert cli.main(_bench_args(files, tmp_path / "out", policies="nn,best")) == 2
    assert "unknown policy" in capsys.readouterr().err


@pytest.mark.slow
def test_local_process_pool_runs_the_same_jobs(files, tmp_path, capsys):
    out = tmp_path / "out"
    args = _bench_args(files, out, policies="nn")
    args[args.index("--workers") + 1] = "2"
    assert cli.main(args) == 0
    assert _last_json(capsys)["ran"] == N_TASKS
    res = json.loads((out / "results.json").read_text())
    pids = {r["pid"] for r in res["outcomes"]["nn"]}
    assert len(res["outcomes"]["nn"]) == N_TASKS and pids.isdisjoint({__import__("os").getpid()})


@pytest.mark.slow
def test_ray_engine_runs_the_same_jobs_on_actors(files, tmp_path, capsys):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'ray[default]')")
    out = tmp_path / "out"
    args = _bench_args(files, out, "--engine", "ray", policies="nn")
    args[args.index("--workers") + 1] = "2"
    assert cli.main(args) == 0
    assert _last_json(capsys)["ran"] == N_TASKS
    res = json.loads((out / "results.json").read_text())
    assert res["engine"] == "ray"
    assert [r["task_id"] for r in res["outcomes"]["nn"]] == ["mini-test-0000", "mini-test-0001"]
    assert all(r["failure_kind"] != "error" for r in res["outcomes"]["nn"])


@pytest.mark.slow
def test_ray_actors_sharing_simulations_give_the_local_unshared_outcomes(files, tmp_path, capsys):
    """--share-simulations on Ray: a task's policies go to one actor (`run_group`) together."""
    pytest.importorskip("ray", reason="ray is not installed (pip install 'ray[default]')")
    runs = {}
    for name, extra in (("local", ()), ("ray", ("--engine", "ray", "--share-simulations"))):
        out = tmp_path / name
        # the oracle first: nn's executions are then restored from the oracle's simulations
        args = _bench_args(files, out, *extra, policies="oracle,nn")
        args[args.index("--workers") + 1] = "2"
        assert cli.main(args) == 0
        lines = (out / "outcomes.jsonl").read_text().splitlines()
        if name == "ray":  # each task's episodes ran on one actor, one after the other
            pids: dict[str, set] = {}
            for r in map(json.loads, lines):
                pids.setdefault(r["task_id"], set()).add(r["pid"])
            assert all(len(p) == 1 for p in pids.values()), pids
        untimed = ("wall_s", "decision_s", "pid", "node")
        runs[name] = {
            (r["policy"], r["task_id"]): {k: v for k, v in r.items() if k not in untimed}
            for r in map(json.loads, lines)
        }
    assert len(runs["local"]) == 2 * N_TASKS
    assert runs["ray"] == runs["local"]


@pytest.mark.parametrize(
    "extra, message",
    [
        (("--tasks", "0"), "argument --tasks: expected an integer >= 1, got '0'"),
        (("--max-steps", "0"), "argument --max-steps: expected an integer >= 1"),
        (("--first", "0"), "argument --first: expected an integer >= 1"),
        (("--noise", "nan"), "argument --noise: expected a finite number >= 0"),
    ],
)
def test_bench_refuses_counts_that_would_not_be_a_table(files, tmp_path, capsys, extra, message):
    args = _bench_args(files, tmp_path / "out")
    for flag, value in zip(extra[::2], extra[1::2], strict=True):
        if flag in args:
            args[args.index(flag) + 1] = value
        else:
            args += [flag, value]
    assert cli.main(args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_a_run_whose_episodes_errored_is_not_a_result(files, tmp_path, capsys, monkeypatch):
    from knotlab.core.demos.tasks import RopeTask, TaskSet

    good = TaskSet.load(files["tasks"])
    # Ropes scaled 100x: the world refuses the reset, so every episode records an error.
    scaled = TaskSet(
        [RopeTask(t.task_id, t.start_nodes_k3 * 100.0, t.source_start, t.seed) for t in good],
        good.metadata,
    )
    path = scaled.save(tmp_path / "scaled.npz")
    args = _bench_args(files, tmp_path / "out", policies="nn")
    args[args.index("--task-set") + 1] = str(path)
    # The task-set loader refuses such a file before anything runs ...
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "rope arc length" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()
    # ... so let it through to check what the episodes themselves do with it.
    monkeypatch.setattr(TaskSet, "load", classmethod(lambda cls, p: scaled))
    rc = cli.main(args)
    captured = capsys.readouterr()
    recs = [
        json.loads(line) for line in (tmp_path / "out" / "outcomes.jsonl").read_text().splitlines()
    ]
    assert recs and all(r["failure_kind"] == "error" for r in recs)
    assert "wrong scale or units" in recs[0]["error"]
    assert rc == 1 and "not a result" in captured.err


# ---------------------------------------------------------------------------- run identity on disk


def _rewrite_lines(path: Path, edit) -> None:
    """Apply ``edit`` to every outcome record of ``path`` and write them back, one per line."""
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    path.write_text("".join(json.dumps(edit(r)) + "\n" for r in recs))


def _other_model(files, tmp_path) -> Path:
    """The test model with another bias: the same features, another content hash."""
    import dataclasses

    from knotlab.core.selection.qmodel import QModel

    model = QModel.load(files["model"])
    return dataclasses.replace(model, bias=model.bias + 1.0).save(tmp_path / "other.npz")


def test_every_outcome_line_records_the_run_that_made_it(first_run):
    out = first_run["out"]
    identity = json.loads((out / "run.json").read_text())["identity"]
    for line in (out / "outcomes.jsonl").read_text().splitlines():
        rec = json.loads(line)
        model = identity["model_hash"] if rec["policy"] == "greedy" else None
        assert rec["run"] == {**identity, "model_hash": model}
    res = json.loads((out / "results.json").read_text())
    assert all("run" not in r for recs in res["outcomes"].values() for r in recs)


def test_without_run_json_the_lines_identify_the_run(first_run, files, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    identity = json.loads((out / "run.json").read_text())
    (out / "run.json").unlink()
    assert cli.main(_bench_args(files, out)) == 0
    assert _last_json(capsys)["resumed"] == 3 * N_TASKS
    assert json.loads((out / "run.json").read_text()) == identity
    before = (out / "outcomes.jsonl").read_bytes()
    for flag, value, field in [("--seed", "1", "seed"), ("--model", None, "model_hash")]:
        (out / "run.json").unlink(missing_ok=True)  # a refusal writes no run.json
        args = _bench_args(files, out)
        if flag == "--model":
            args[args.index("--model") + 1] = str(_other_model(files, tmp_path))
        else:
            args += [flag, value]
        assert cli.main(args) == 2
        err = capsys.readouterr().err
        assert "different arguments" in err and field in err and len(err.splitlines()) == 1
        assert (out / "outcomes.jsonl").read_bytes() == before


def test_lines_without_identity_resume_only_beside_a_run_json(first_run, files, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    _rewrite_lines(out / "outcomes.jsonl", lambda r: {k: v for k, v in r.items() if k != "run"})
    before = (out / "outcomes.jsonl").read_bytes()
    run_json = (out / "run.json").read_bytes()
    (out / "run.json").unlink()
    assert cli.main(_bench_args(files, out)) == 2
    err = capsys.readouterr().err
    assert "does not record the run that made it" in err and len(err.splitlines()) == 1
    assert (out / "outcomes.jsonl").read_bytes() == before and not (out / "run.json").exists()
    (out / "run.json").write_bytes(run_json)  # lines from before they carried it: run.json vouches
    assert cli.main(_bench_args(files, out)) == 0
    assert _last_json(capsys)["ran"] == 0


def test_a_line_from_another_run_than_run_json_is_refused(first_run, files, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)

    def other_seed(rec: dict) -> dict:
        if rec["policy"] == "nn" and rec["task_id"].endswith("1"):
            rec["run"]["seed"] = 5
        return rec

    _rewrite_lines(out / "outcomes.jsonl", other_seed)
    before = (out / "outcomes.jsonl").read_bytes()
    assert cli.main(_bench_args(files, out)) == 2
    err = capsys.readouterr().err
    assert "made by another run" in err and "seed" in err and len(err.splitlines()) == 1
    assert (out / "outcomes.jsonl").read_bytes() == before
    (out / "run.json").unlink()  # without run.json: the lines disagree among themselves
    assert cli.main(_bench_args(files, out)) == 2
    assert "outcomes of 2 different runs" in capsys.readouterr().err


def test_a_model_whose_features_do_not_fit_the_library_is_refused_before_any_episode(
    files, tmp_path, capsys
):
    import dataclasses

    from knotlab.core.selection.qmodel import QModel

    model = QModel.load(files["model"])
    names = [*model.feature_spec.names[:-1], "demo[s099-t9]"]  # a demo this library lacks
    bad = dataclasses.replace(model, spec_dict={**model.spec_dict, "names": names})
    args = _bench_args(files, tmp_path / "out", policies="nn,greedy")
    args[args.index("--model") + 1] = str(bad.save(tmp_path / "bad.npz"))
    args[args.index("--workers") + 1] = "2"  # a mismatch found in a worker would break the pool
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "features do not match this library" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_a_folder_resumed_on_another_kind_of_cpu_says_so_and_counts_each_kind(
    first_run, files, tmp_path, capsys, caplog
):
    out = tmp_path / "out"
    shutil.copytree(first_run["out"], out)
    lines = (out / "outcomes.jsonl").read_text().splitlines(keepends=True)
    assert all(json.loads(line)["numeric_kind"] == numeric_kind() for line in lines)
    # Four episodes from another kind of machine, one from before lines named their kind, and
    # the last episode still to run here.
    recs = [json.loads(line) for line in lines[:-1]]
    for r in recs[:4]:
        r["numeric_kind"] = "avx9000"
    del recs[4]["numeric_kind"]
    (out / "outcomes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    with caplog.at_level("WARNING"):
        assert cli.main(_bench_args(files, out)) == 0
    assert _last_json(capsys)["ran"] == 1
    warned = [r.getMessage() for r in caplog.records if "episodes made on" in r.getMessage()]
    assert len(warned) == 1 and "avx9000" in warned[0] and "unrecorded" not in warned[0]
    res = json.loads((out / "results.json").read_text())
    assert res["numeric_kinds"] == {"avx9000": 4, numeric_kind(): 1, "unrecorded": 1}
    caplog.clear()
    with caplog.at_level("WARNING"):  # nothing left to run: nothing is mixed, nothing said
        assert cli.main(_bench_args(files, out)) == 0
    assert not [r for r in caplog.records if "episodes made on" in r.getMessage()]
