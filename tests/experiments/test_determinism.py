"""Same seed, same machine: bit-identical outcomes, whatever the rerun or the worker count.

What may differ across machines (BLAS kernels, near-ties) is in docs/determinism.md; these tests
pin what must not differ on one machine. Times and process ids are the only fields left out.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from knotlab.app import cli
from tests.minilib import mini_library, mini_tasks, write_mini_files, write_mini_labels

pytestmark = [pytest.mark.xdist_group("bench"), pytest.mark.slow]  # ~1 CPU-min each

_UNTIMED = ("wall_s", "decision_s", "pid")  # how long and where, not what happened


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Mini library, 2 test tasks and a model trained on the mini labels."""
    d = tmp_path_factory.mktemp("determinism")
    lib, tasks = write_mini_files(d, n_tasks=2)
    labels = write_mini_labels(d / "labels.jsonl")
    model = d / "model.npz"
    args = ["train", "--labels", str(labels), "--library", str(lib), "--out", str(model)]
    assert cli.main([*args, "--workers", "1", "--no-progress", "--validation-fraction", "0"]) == 0
    return {"library": lib, "tasks": tasks, "model": model, "dir": d}


def _bench(
    files, out: Path, workers: int, *extra: str, policies: str = "nn,greedy"
) -> dict[tuple[str, str], dict]:
    """One small noisy bench (nn and greedy); its outcome records without times, by episode."""
    args = ["bench", "--policies", policies, "--tasks", "2", "--max-steps", "2", *extra]
    args += ["--noise", "0.002", "--seed", "3", "--workers", str(workers), "--no-progress"]
    args += ["--library", str(files["library"]), "--task-set", str(files["tasks"])]
    assert cli.main([*args, "--model", str(files["model"]), "--out", str(out)]) == 0
    recs = [json.loads(line) for line in (out / "outcomes.jsonl").read_text().splitlines()]
    return {
        (r["policy"], r["task_id"]): {k: v for k, v in r.items() if k not in _UNTIMED} for r in recs
    }


def test_a_bench_rerun_and_another_worker_count_give_identical_outcomes(files, tmp_path, capsys):
    first = _bench(files, tmp_path / "a", workers=1)
    again = _bench(files, tmp_path / "b", workers=1)
    parallel = _bench(files, tmp_path / "c", workers=2)
    assert len(first) == 4 and all(r["n_steps"] >= 1 for r in first.values())
    for key, rec in first.items():
        for other in (again, parallel):
            assert set(other[key]) == set(rec)
            for field, value in rec.items():  # field by field, so a failure names the field
                assert other[key][field] == value, (key, field)


def test_sharing_simulations_across_policies_changes_no_outcome(files, tmp_path):
    """--share-simulations: every policy of a task on one worker with one outcome memo. The
    episodes are the same to the last bit; only how long they took may differ."""
    # the searches first: nn and greedy then find their executions simulated already, and must
    # continue from the restored after-state exactly as if they had executed them
    policies = "oracle,la1x2,greedy,nn"
    alone = _bench(files, tmp_path / "alone", 2, policies=policies)
    shared = _bench(files, tmp_path / "shared", 2, "--share-simulations", policies=policies)
    assert len(alone) == 8
    for key, rec in alone.items():
        assert set(shared[key]) == set(rec)
        for field, value in rec.items():
            assert shared[key][field] == value, (key, field)


def test_a_shared_memo_simulates_an_execution_once_for_every_policy(monkeypatch):
    from knotlab.core.execution import memo
    from knotlab.core.experiments.bench import BenchWorker, EpisodeJob, WorkerSpec

    calls: list[int] = []
    original = memo.apply_demo

    def counted(world, transferer, cloud, action, *args, **kwargs):
        calls.append(int(action))
        return original(world, transferer, cloud, action, *args, **kwargs)

    monkeypatch.setattr(memo, "apply_demo", counted)
    task = mini_tasks(1, "test")[0]
    jobs = [
        EpisodeJob(name, 0, task.task_id, task.start_nodes_k3, 5, 2, 0.0)
        for name in ("oracle", "nn")
    ]
    worker = BenchWorker(WorkerSpec(mini_library(2)))
    try:
        alone = [worker.run(job) for job in jobs]
        n_alone = len(calls)
        calls.clear()
        shared = worker.run_group(jobs)
    finally:
        worker.close()
    drop = ("wall_s", "decision_s", "pid")
    assert [{k: v for k, v in r.items() if k not in drop} for r in shared] == [
        {k: v for k, v in r.items() if k not in drop} for r in alone
    ]
    # nn's executions are among the oracle's candidates: restored, not simulated again
    assert 0 < len(calls) < n_alone, (len(calls), n_alone)


def _oracle_runs(library_path: Path, workers: int) -> list:
    from knotlab.core.experiments.labeller import OracleParams, oracle_label_tasks

    params = OracleParams(candidates=2, max_steps=2, sim_budget=4)
    tasks = mini_tasks(2, "train")
    results = oracle_label_tasks(
        str(library_path), tasks, params=params, workers=workers, progress=False
    )
    return sorted((r.execution for r in results), key=lambda e: e.execution_id)


def test_oracle_labels_are_bit_identical_in_process_and_over_two_workers(files):
    alone = _oracle_runs(files["library"], workers=1)
    pooled = _oracle_runs(files["library"], workers=2)
    assert [e.execution_id for e in alone] == [e.execution_id for e in pooled]
    assert sum(len(e.steps) + len(e.dead_ends) for e in alone) >= 1  # something to compare
    for a, b in zip(alone, pooled, strict=True):
        assert (a.ended_in_knot, a.metadata) == (b.ended_in_knot, b.metadata)
        assert len(a.steps) == len(b.steps) and len(a.dead_ends) == len(b.dead_ends)
        for sa, sb in zip(a.steps, b.steps, strict=True):
            assert (sa.chosen_demo, sa.outcome, sa.candidates) == (
                sb.chosen_demo,
                sb.outcome,
                sb.candidates,
            )
            # Registration costs and observed clouds to the last bit, not approximately.
            np.testing.assert_array_equal(sa.candidate_scores_c, sb.candidate_scores_c)
            np.testing.assert_array_equal(sa.cloud_n3, sb.cloud_n3)
            np.testing.assert_array_equal(sa.rope_nodes_k3, sb.rope_nodes_k3)
        for da, db in zip(a.dead_ends, b.dead_ends, strict=True):
            np.testing.assert_array_equal(da.cloud_n3, db.cloud_n3)
