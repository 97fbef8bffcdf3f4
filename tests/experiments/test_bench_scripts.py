"""The bookkeeping of the bench scripts: comparisons, ledgers, reports and pairings."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tests.bench_modules import load_bench_module


def test_scan_ab_reports_identical_arrays_and_the_largest_relative_difference(
    project_root, tmp_path
) -> None:
    scan_ab = load_bench_module(project_root, "scan_ab")
    before, after = tmp_path / "a.npz", tmp_path / "b.npz"
    costs = np.array([[1.0, 2.0], [np.inf, 4.0]])
    moved = costs.copy()
    moved[0, 1] = 2.0 * (1 + 3e-15)
    np.savez(before, same=np.arange(3.0), costs=costs)
    np.savez(after, same=np.arange(3.0), costs=moved)
    lines = scan_ab._compare(before, after)
    assert lines[0] == "same: identical"
    assert lines[1].startswith("costs: 1 of 4 differ, largest relative 3.1e-15")
    assert "finite/infinite" not in lines[1]


def _world(state: float):
    """A stand-in world whose snapshot digest depends on ``state`` only."""
    snap = SimpleNamespace(
        sim_time=state,
        positions_l3=np.full((2, 3), state),
        quaternions_l4=np.zeros((2, 4)),
        linear_velocities_l3=np.zeros((2, 3)),
        angular_velocities_l3=np.zeros((2, 3)),
    )
    return SimpleNamespace(snapshot=lambda: snap)


def test_sharing_ledger_books_first_own_and_shared_simulations(project_root) -> None:
    sharing = load_bench_module(project_root, "sharing")
    ledger = sharing.SharingLedger()
    apply = ledger.wrap(lambda world, transferer, cloud, action: action)
    cloud = np.zeros((4, 3))
    ledger.start("t0", "la2x5")
    assert apply(_world(0.0), None, cloud, 3) == 3  # first
    apply(_world(0.0), None, cloud, 3)  # the same policy again: own
    apply(_world(1.0), None, cloud, 3)  # another state: first
    ledger.start("t0", "oracle")
    apply(_world(0.0), None, cloud, 3)  # la2x5 had it: shared
    apply(_world(0.0), None, cloud + 1, 3)  # another cloud: first
    ledger.start("t1", "oracle")
    apply(_world(0.0), None, cloud, 3)  # a new task forgets: first
    assert ledger.calls["la2x5"] == {"first": 2, "own": 1, "shared": 0}
    assert ledger.calls["oracle"] == {"first": 2, "own": 0, "shared": 1}


def test_policy_states_label_files_read_back_and_append_without_a_second_header(
    project_root, tmp_path
) -> None:
    from knotlab.labeling_db.interchange import read_labels

    policy_states = load_bench_module(project_root, "policy_states")
    executions = [
        item.execution for item in read_labels(project_root / "results/labels_oracle_main.jsonl")
    ][:3]
    path = tmp_path / "round1.jsonl"
    policy_states._append(path, executions[:2])  # a new file: header, then the executions
    policy_states._append(path, executions[2:])  # resumed: appended, no second header
    back = policy_states._read(path)  # the labels format's reader accepts what was written
    assert [e.execution_id for e in back] == [e.execution_id for e in executions]
    assert sum('"format"' in line for line in path.read_text().splitlines()) == 1


def _line(policy: str, task: int, success: bool, **extra) -> str:
    import json

    return json.dumps(
        {"policy": policy, "task_id": f"t{task}", "success": success, "failure_kind": None, **extra}
    )


def test_robustness_report_pairs_settings_controls_and_robust_runs(project_root, tmp_path, capsys):
    robustness = load_bench_module(project_root, "robustness")
    matched, out, robust = tmp_path / "matched", tmp_path / "study", tmp_path / "robust"
    for folder in (matched, out / "combined25", out / "combined25_known", robust / "combined25"):
        folder.mkdir(parents=True)
    (matched / "outcomes.jsonl").write_text(
        "\n".join(_line("la2x5", i, True) for i in range(4)) + "\n"
    )
    (out / "combined25" / "outcomes.jsonl").write_text(
        "\n".join(_line("la2x5", i, i < 2) for i in range(4)) + "\n"
    )
    (out / "combined25_known" / "outcomes.jsonl").write_text(
        "\n".join(_line("la2x5", i, i < 3) for i in range(4)) + "\n"
    )
    (robust / "combined25" / "outcomes.jsonl").write_text(
        "\n".join(_line("rla2x5k2", i, i != 1, estimate_error_mm=[4.0, 8.0]) for i in range(4))
        + "\n"
        + "\n".join(_line("ala2x5k4", i, i != 3, planned_in=[0, i % 2]) for i in range(4))
        + "\n"
    )
    args = SimpleNamespace(out_dir=str(out), matched=str(matched), robust_dir=str(robust))
    assert robustness.report(args) == 0
    text = capsys.readouterr().out
    assert "| combined25 | la2x5 | 4 | 50.0 %" in text  # against the matched world: -50 points
    assert "| combined25 | la2x5 | 4 | 50.0 % | 75.0 % | -25.0 |" in text  # against its control
    assert "| combined25 | rla2x5k2 | 4 | 75.0 % | 50.0 % | +25.0 |" in text  # robust vs plain
    assert "| combined25 | ala2x5k4 | 4 | 75.0 % | 50.0 % | +25.0 |" in text  # adaptive vs plain
    assert "combined25/ala2x5k4: 2 of 8 decisions planned in a member other" in text
    assert "(step 1: 0 %, step 2: 50 %)" in text
    summary = (out / "summary.json").read_text()
    assert '"model_error"' in summary and '"robust_vs_plain"' in summary
    assert (out / "robustness.png").stat().st_size > 1000
    # A folder of robust runs alone (what its own run reports at its end): its policy is none
    # of the usual five, and is plotted all the same.
    alone = SimpleNamespace(out_dir=str(robust), matched=str(matched), robust_dir=None)
    assert robustness.report(alone) == 0
    assert (robust / "robustness.png").stat().st_size > 1000


def test_robustness_report_pairs_each_setting_with_the_matched_world_of_its_cpu_kind(
    project_root, tmp_path, capsys
):
    import json

    robustness = load_bench_module(project_root, "robustness")
    study = tmp_path / "study"
    wide, narrow = tmp_path / "matched512", study / "nominal"  # the AVX2 baseline inside the study
    for folder in (wide, narrow, study / "damping+10", study / "mass+10", study / "length+10"):
        folder.mkdir(parents=True)

    def write(folder, successes, kind=None, machine=None):
        extra = {"numeric_kind": kind} if kind else {}
        lines = [_line("la2x5", i, ok, **extra) for i, ok in enumerate(successes)]
        (folder / "outcomes.jsonl").write_text("\n".join(lines) + "\n")
        if machine:
            (folder / "results.json").write_text(json.dumps({"machine": machine}))

    # An old matched world whose lines name no kind: its results.json's BLAS kernels do.
    write(wide, [True] * 4, machine={"blas": ["openblas 0.3.30 SkylakeX (libscipy_openblas.so)"]})
    write(narrow, [True, True, False, False], kind="avx2")
    write(study / "damping+10", [True, False, False, False], kind="avx2")
    write(study / "mass+10", [True, True, True, False], kind="avx512")
    write(study / "length+10", [False] * 4, kind="avx9000")
    args = SimpleNamespace(out_dir=str(study), matched=f"{wide},{narrow}", robust_dir=None)
    assert robustness.report(args) == 0
    text = capsys.readouterr().out
    assert "| damping+10 | la2x5 | 4 | 25.0 % | [4.6, 69.9] | 50.0 % | -25.0 |" in text  # AVX2's
    assert "| mass+10 | la2x5 | 4 | 75.0 % | [30.1, 95.4] | 100.0 % | -25.0 |" in text  # AVX-512's
    assert "| length+10 | la2x5 | 4 | 0.0 % | [0.0, 49.0] | 100.0 % | -100.0 |" in text
    notes = [line for line in text.splitlines() if line.startswith("note:")]
    assert notes == [
        f"note: length+10 is paired with {wide} (avx9000 against avx512: not one CPU kind)"
    ]
    assert "| nominal |" not in text  # a matched world is not a setting
    pairing = json.loads((study / "summary.json").read_text())["matched_by_setting"]
    assert pairing["damping+10"] == f"{narrow} (avx2)"


def _scores(main: float, hard: float, top1: float = 0.5) -> dict:
    return {
        lv: {"greedy_success": s, "starts": 60, "top1": top1, "value_auc": 0.9, "n_states": 175}
        for lv, s in (("main", main), ("hard", hard))
    }


def test_level_models_choose_per_level_by_held_out_greedy_then_top1(
    project_root, tmp_path, capsys
) -> None:
    level_models = load_bench_module(project_root, "level_models")
    models = {
        "main": {"scores": _scores(0.75, 0.40), "train_states": 695},
        "hard": {"scores": _scores(0.60, 0.55), "train_states": 800},
        "both": {
            "scores": _scores(0.75, 0.55, top1=0.6),
            "train_states": 1495,
            "machine": {"vector_width": "avx2"},  # a model added on another machine says so
        },
    }
    assert level_models.choose(models, "main") == "both"  # a tie on success: top-1 decides
    assert level_models.choose(models, "hard") == "both"
    models["hard"]["scores"]["hard"]["greedy_success"] = 0.6
    assert level_models.choose(models, "hard") == "hard"
    report = {"models": models, "chosen": {"main": "both", "hard": "hard"}}
    level_models._table(report)
    text = capsys.readouterr().out
    assert "| both | 1495 | 45/60 = 0.750 | 0.600 | 0.900 | 33/60 = 0.550 |" in text
    assert "| 0.900 | avx2 |" in text and "| ? |" in text
    level_models._plot(report, tmp_path / "levels.png")
    assert (tmp_path / "levels.png").stat().st_size > 1000
    # Each task's labels where scripts/table1.sh writes them.
    assert level_models.results_dir("overhand") == project_root / "results"
    assert level_models.results_dir("figure8") == project_root / "results" / "figure8"
    assert level_models.policy_states_dir("overhand") == project_root / "results/policy_states_main"
    assert (
        level_models.policy_states_dir("figure8") == project_root / "results/figure8/policy_states"
    )


def test_level_models_drop_policy_states_reached_from_a_held_out_start(project_root) -> None:
    level_models = load_bench_module(project_root, "level_models")

    def reached(start: str) -> SimpleNamespace:
        return SimpleNamespace(metadata={"reached_by": {"start_task_id": start}})

    states = [reached("main-train-0001"), reached("main-train-0002"), reached("main-train-0001")]
    kept = level_models.reached_from_training(states, {"main-train-0001"})
    assert [s.metadata["reached_by"]["start_task_id"] for s in kept] == ["main-train-0002"]


def test_policy_states_plot_and_table_show_rounds_refitted_with_their_tries(
    project_root, tmp_path, capsys
) -> None:
    policy_states = load_bench_module(project_root, "policy_states")
    point = {
        "train_states": 700,
        "validation_greedy_success": 0.75,
        "validation_starts": 60,
        "validation_top1": 0.49,
        "validation_value_auc": 0.96,
    }
    curve = {
        "points": {
            "round0": point,
            "round1": {**point, "train_states": 1357},
            "round1+tries": {**point, "train_states": 1357, "validation_greedy_success": 0.8},
        }
    }
    policy_states._plot(curve, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 1000
    policy_states._table(curve)
    assert "| round1+tries | 1357 | 0.800 (60 starts) |" in capsys.readouterr().out


def test_greedy_validation_pairs_models_on_the_same_starts(project_root, tmp_path) -> None:
    import pytest

    gv = load_bench_module(project_root, "greedy_validation")
    lines = [
        {"model": m, "task_id": f"v{i}", "success": ok}
        for m, pattern in (("ref", "1100"), ("new", "1011"))
        for i, ok in enumerate(c == "1" for c in pattern)
    ]
    res = gv.summarise(lines, ["ref", "new"])
    assert res["ref"]["successes"] == 2 and res["new"]["successes"] == 3
    assert (res["new"]["wins_vs_first"], res["new"]["losses_vs_first"]) == (2, 1)
    assert res["ref"]["sign_test_p"] == 1.0  # against itself: no discordant pairs
    assert gv.sign_test(10, 0) < 0.01
    model = tmp_path / "m.npz"
    model.write_bytes(b"")
    assert gv.parse_models(f"a={model},b={model}") == {"a": model, "b": model}
    for bad in ("a", f"a={model},a={model}", "a=/no/such.npz"):
        with pytest.raises(SystemExit):
            gv.parse_models(bad)


def test_greedy_validation_plays_the_policy_asked_and_keeps_a_folder_to_it(
    project_root, tmp_path
) -> None:
    import json
    import subprocess
    import sys

    from knotlab.app import defaults

    out = tmp_path / "val"
    argv = [sys.executable, str(project_root / "bench" / "greedy_validation.py")]
    argv += ["--starts", "2", "--workers", "1", "--out-dir", str(out)]
    argv += ["--models", f"shipped={defaults.MODEL_PATH}"]
    subprocess.run([*argv, "--policy", "nn"], check=True, capture_output=True, cwd=project_root)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["policy"] == "nn" and summary["results"]["shipped"]["starts"] == 2
    again = subprocess.run([*argv], capture_output=True, text=True, cwd=project_root)
    assert again.returncode != 0 and "made with nn" in again.stderr  # greedy is the default


def test_task_transfer_pairs_arms_with_the_per_task_model_and_refuses_errored_runs(
    project_root, tmp_path
) -> None:
    import json

    tt = load_bench_module(project_root, "task_transfer")

    def folder(name: str, policy: str, wins: list[bool], error: str | None = None) -> Path:
        path = tmp_path / name
        path.mkdir()
        lines = [
            {"task_id": f"t{i:03d}", "policy": policy, "success": ok, "error": None}
            for i, ok in enumerate(wins)
        ]
        if error:
            lines[-1]["error"] = error
        (path / "outcomes.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
        return path

    ref = [True, True, False, False, True, False]
    arm = [True, False, True, True, True, False]
    per_task = tt._greedy_outcomes(folder("per", "greedy", ref), 6)
    moved = tt._greedy_outcomes(folder("moved", "greedy", arm), 5)  # the first 5 tasks only
    nn = tt._policy_outcomes(folder("nn", "nn", [False] * 6), "nn", 6)
    rows = tt._summarise({"per-task": per_task, "moved": moved}, nn)
    assert rows["moved"]["successes"] == 4 and rows["moved"]["n"] == 5
    vs = rows["moved"]["vs_per_task"]  # on the 5 common tasks: per-task 3, moved 4
    assert (vs["n"], vs["wins"], vs["losses"]) == (5, 2, 1) and vs["points"] == 20.0
    assert rows["nn"]["vs_nn"]["points"] == 0.0 and rows["per-task"]["vs_nn"]["wins"] == 3
    with pytest.raises(SystemExit, match="1 greedy episodes errored"):
        tt._greedy_outcomes(folder("bad", "greedy", ref, error="boom"), 6)


def test_robust_tuning_chooses_the_best_configuration_within_the_time_budget(
    project_root, tmp_path, capsys
):
    import json

    tuning = load_bench_module(project_root, "robust_tuning")
    folder = tmp_path / "combined25"
    folder.mkdir()

    def line(policy: str, task: int, success: bool, decide: float) -> str:
        return json.dumps(
            {"policy": policy, "task_id": f"t{task}", "success": success, "decision_s": [decide]}
        )

    wins = {"la2x5": {0, 1}, "ala2x5k2": {0, 1, 2}, "ala2x5k4": {0, 1, 2}, "rla2x5k8": {0, 1, 2, 3}}
    times = {"la2x5": 1.0, "ala2x5k2": 1.5, "ala2x5k4": 1.8, "rla2x5k8": 8.0}
    lines = [line(p, t, t in won, times[p]) for p, won in wins.items() for t in range(4)]
    (folder / "outcomes.jsonl").write_text("\n".join(lines) + "\n")
    configs = ["ala2x5k4", "ala2x5k2", "rla2x5k8"]
    chosen = tuning.report(folder, configs, 2.0)
    # rla2x5k8 knots most but takes 8x the time; of the two within 2x, fewer members wins the tie
    assert chosen.policy == "ala2x5k2" and (chosen.wins, chosen.losses) == (1, 0)
    assert json.loads((folder / "choice.json").read_text())["chosen"] == "ala2x5k2"
    text = capsys.readouterr().out
    assert "| rla2x5k8 | 8 | 25 % | 4 | 4/4 = 100.0 % |" in text and "| 8.00 |" in text
    assert tuning.baseline_of("ala2x5k4s50") == "la2x5"
    assert tuning.report(folder, ["rla2x5k8"], 2.0) is None  # nothing within the budget


def test_search_labels_read_knotted_rollouts_and_floor_only_the_candidates_that_did_not_advance(
    project_root, tmp_path
) -> None:
    import json
    from datetime import UTC, datetime

    from knotlab.core.tasks import get_task
    from knotlab.labeling_db.interchange import execution_to_dict, read_labels
    from knotlab.labeling_db.records import StoredExecution

    search_labels = load_bench_module(project_root, "search_labels")
    oracle = [
        item.execution for item in read_labels(project_root / "results/labels_oracle_main.jsonl")
    ]
    knotted = next(e for e in oracle if e.ended_in_knot and len(e.steps) == 3)
    now = datetime.now(UTC)
    tried = [
        [  # step 0 from stage 0: one candidate advanced, one kept the stage, one failed
            {"demo": "s000-t0", "stage": 1, "knot": False, "failure": None},
            {"demo": "s001-t0", "stage": 0, "knot": False, "failure": None},
            {"demo": "s002-t0", "stage": 1, "knot": False, "failure": "misgrasp"},
        ],
        [{"demo": "s000-t1", "stage": 1, "knot": False, "failure": None}],  # from stage 1: stayed
        [{"demo": "s000-t2", "stage": 3, "knot": True, "failure": None}],
    ]
    lines = [
        {
            "task_id": "main-train-0009",
            "knot": True,
            "stages": [1, 2, 3],
            "root_tries": tried,
            "execution": execution_to_dict(
                StoredExecution(knotted, started_at=now, finished_at=now)
            ),
        },
        {
            "task_id": "main-train-0003",
            "knot": False,
            "stages": [0],
            "root_tries": [[]],
            "execution": None,
        },  # a start the search did not knot
    ]
    (tmp_path / "rollouts_main.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    back = search_labels.search_executions(tmp_path, "main")
    assert [e.execution_id for e in back] == [knotted.execution_id]  # the failed one is no label
    assert [s.chosen_demo for s in back[0].steps] == [s.chosen_demo for s in knotted.steps]
    tries = search_labels.search_floor_tries(tmp_path, "main", get_task("overhand"))
    eid = knotted.execution_id
    assert [t.demo for t in tries[(eid, 0)].tried] == ["s001-t0", "s002-t0"]
    assert [t.demo for t in tries[(eid, 1)].tried] == ["s000-t1"]  # stage 1 -> 1 did not advance
    assert tries[(eid, 1)].stage_before == 1 and tries[(eid, 2)].tried == ()


def test_search_labels_writes_the_starts_outside_the_held_out_fifth_and_reads_policy_states(
    project_root, tmp_path
) -> None:
    """The starts the second step labels from leave out the held-out starts the fit scores on;
    its labels file gives the executions the search knotted from, in id order."""
    import argparse
    from datetime import UTC, datetime

    from knotlab.core.demos.tasks import TaskSet
    from knotlab.core.selection.labels import LabelledExecution
    from knotlab.core.tasks import get_task
    from knotlab.labeling_db.interchange import read_labels, write_labels
    from knotlab.labeling_db.records import StoredExecution

    search_labels = load_bench_module(project_root, "search_labels")
    args = argparse.Namespace(out_dir=tmp_path, task="overhand")
    assert search_labels.cmd_starts(args) == 0
    task = get_task("overhand")
    for level in ("main", "hard"):
        kept = TaskSet.load(tmp_path / f"starts_{level}.npz")
        split = search_labels.level_split(
            task, level, project_root / f"results/labels_oracle_{level}.jsonl"
        )
        held = {s.task_id for s in split.held_out_starts}
        full = {s.task_id for s in task.files.load_task_set(level, "train")}
        assert {s.task_id for s in kept} == full - held and len(held) == 60
        assert kept.split == "train" and kept.metadata["level"] == level
    written = (tmp_path / "starts_main.npz").stat().st_mtime_ns
    assert search_labels.cmd_starts(args) == 0  # the same starts: left as they are
    assert (tmp_path / "starts_main.npz").stat().st_mtime_ns == written

    assert search_labels.dagger_executions(tmp_path, "main") == []  # none yet
    assert search_labels.dagger_part("dagger-hard") == ("hard", 1)
    assert search_labels.dagger_part("dagger2-main") == ("main", 2)
    assert search_labels.dagger_files(tmp_path, "main", 2)[0].name == "labels_dagger_main_r2.jsonl"
    oracle = [
        item.execution for item in read_labels(project_root / "results/labels_oracle_main.jsonl")
    ]
    knotted = next(e for e in oracle if e.ended_in_knot)
    later = LabelledExecution("search-la2x5-greedy-r1-z-t1", "oracle", "search-la2x5",
                              knotted.steps, True, task_id="z@greedy-r1-t1")  # fmt: skip
    earlier = LabelledExecution("search-la2x5-greedy-r1-a-t1", "oracle", "search-la2x5",
                                knotted.steps, True, task_id="a@greedy-r1-t1")  # fmt: skip
    empty = LabelledExecution("search-la2x5-greedy-r1-a-t2", "oracle", "search-la2x5", (),
                              False, task_id="a@greedy-r1-t2")  # fmt: skip
    labels, _ = search_labels.dagger_files(tmp_path, "main")
    now = datetime.now(UTC)
    with labels.open("w") as fh:
        stored = [
            StoredExecution(e, started_at=now, finished_at=now) for e in (later, empty, earlier)
        ]
        write_labels(stored, fh, "jsonl")
    back = search_labels.dagger_executions(tmp_path, "main")
    assert [e.execution_id for e in back] == [earlier.execution_id, later.execution_id]


def test_stage_mask_allows_only_the_demos_of_the_true_ropes_stage(project_root) -> None:
    from knotlab.core.selection.decision import Decision

    sm = load_bench_module(project_root, "stage_mask")
    steps_a = np.array([0, 1, 2, 2, 3])

    class Inner:
        name = "greedy"

        def __init__(self, scores) -> None:
            self.scores = np.array(scores, dtype=float)

        def choose(self, ctx) -> Decision:
            return Decision(int(np.argmax(self.scores)), self.scores)

    class Stage:  # the task: the stage is the rope's first node's x, for the test
        def stage(self, nodes):
            return SimpleNamespace(stage=int(nodes[0][0]))

    def ctx(stage: int):
        return SimpleNamespace(world=SimpleNamespace(rope_nodes=lambda: np.array([[stage, 0, 0]])))

    # The inner choice is demo 4 (step 3); at stage 2 the best step-2 demo is taken instead.
    policy = sm.StageMaskedPolicy(Inner([0.1, 0.2, 0.3, 0.5, 0.9]), Stage(), steps_a)
    got = policy.choose(ctx(2))
    assert got.action == 3 and np.isneginf(got.scores_a[[0, 1, 4]]).all()
    assert policy.choose(ctx(3)).action == 4 and policy.name == "greedy+stage"
    # No demo of the stage's step registered: the inner choice stands.
    policy = sm.StageMaskedPolicy(Inner([0.1, 0.2, -np.inf, -np.inf, 0.9]), Stage(), steps_a)
    assert policy.choose(ctx(2)).action == 4
    table = sm.transition_table(
        [{"transitions": [[0, 0, 1], [1, 2, 1], [1, 1, 2]]}, {"transitions": [[1, 2, 0]]}]
    )
    assert table == {(0, 0): (1, 1), (1, 1): (1, 1), (1, 2): (2, 0)}


def test_demo_prior_rates_count_advances_and_shift_greedys_choice(project_root) -> None:
    from knotlab.core.selection.decision import Decision

    dp = load_bench_module(project_root, "demo_prior")
    lines = [
        {"stage_before": 2, "tried": [{"demo": "a", "stage": 3, "knot": False}] * 3},
        {"stage_before": 2, "tried": [{"demo": "b", "stage": 2, "knot": False}] * 3},
        {"stage_before": 3, "tried": [{"demo": "b", "stage": 0, "knot": True}]},
    ]
    rate = dp.advance_rates(lines, ["a", "b", "never"])
    # (advanced + 1) / (tried + 2); a demo never tried gets the pooled rate (4 + 1) / (7 + 2).
    assert np.allclose(rate, [4 / 5, 2 / 6, 5 / 9])

    class Inner:
        name = "greedy"

        def choose(self, ctx) -> Decision:
            return Decision(1, np.array([1.0, 1.5, -np.inf]))

    assert dp.PriorPolicy(Inner(), rate, 0.1).choose(None).action == 1  # a small prior: Q decides
    shifted = dp.PriorPolicy(Inner(), rate, 1.0).choose(None)
    assert shifted.action == 0 and np.isneginf(shifted.scores_a[2])  # unusable stays unusable


def test_tried_neighbours_prior_counts_the_nearest_tried_states_and_shifts_greedy(
    project_root, tmp_path
) -> None:
    from knotlab.core.selection.decision import Decision

    tn = load_bench_module(project_root, "tried_neighbours")
    # a state's description: log cost ratios to the nearest demo, capped; failed demos capped
    desc = tn.describe(np.array([2.0, 1.0, np.inf, 1e9]))
    assert np.allclose(desc, [np.log(2.0), 0.0, tn.DESCRIPTOR_CAP, tn.DESCRIPTOR_CAP])
    # four tried states of two executions over a library of three demos: demo "a" advanced in the
    # two states near cost profile A and failed in the two near profile B
    near_a, near_b = [1.0, 2.0, 4.0], [4.0, 2.0, 1.0]
    ids = ["e1", "e1", "e2", "e2"]
    np.savez(
        tmp_path / "scans.npz",
        execution_id=np.array(ids),
        step_index=np.array([0, 1, 0, 1]),
        nn_cost_sa=np.array([near_a, near_b, near_a, near_b]),
    )
    lines = [
        {"execution_id": e, "step_index": s, "stage_before": 0,
         "tried": [{"demo": "a", "stage": int(s == 0), "knot": False}]}
        for e, s in zip(ids, [0, 1, 0, 1], strict=True)
    ]  # fmt: skip
    tries = tmp_path / "tries.jsonl"
    tries.write_text("".join(json.dumps(x) + "\n" for x in lines))
    ts = tn.load_tried_states(tmp_path / "scans.npz", str(tries), ("a", "b", "c"))
    assert np.isclose(ts.rate_a[0], 3 / 6)  # (2 advanced + 1) / (4 tried + 2)
    demos = np.array([0, 1])
    # k = 2 nearest tried states of "a" from profile A: both advanced, shrunk by SHRINK to 1/2
    p_a = ts.prior(tn.describe(np.array(near_a)), demos, 2)
    assert np.isclose(p_a[0], (2 + tn.SHRINK * 0.5) / (2 + tn.SHRINK))
    p_b = ts.prior(tn.describe(np.array(near_b)), demos, 2)
    assert np.isclose(p_b[0], (0 + tn.SHRINK * 0.5) / (2 + tn.SHRINK))
    assert p_a[1] == p_b[1] == ts.rate_a[1]  # never tried: its (pooled) rate, whatever the state
    # leaving execution e1 out, state 0's neighbours are e2's only
    held = np.array([e == "e1" for e in ids])
    assert np.isclose(tn._prior_without(ts, 0, demos, 1, held)[0], (1 + tn.SHRINK * 2 / 4) / 3)

    class Inner:
        name = "greedy"

        def choose(self, ctx) -> Decision:
            return Decision(1, np.array([1.0, 1.2, -np.inf]))

    ctx = SimpleNamespace(scan=SimpleNamespace(nn_cost_a=np.array(near_a)))
    assert tn.NeighbourPriorPolicy(Inner(), ts, 2, 0.0).choose(ctx).action == 1
    shifted = tn.NeighbourPriorPolicy(Inner(), ts, 2, 1.0).choose(ctx)
    assert shifted.action == 0 and np.isneginf(shifted.scores_a[2])
    ctx_b = SimpleNamespace(scan=SimpleNamespace(nn_cost_a=np.array(near_b)))
    assert tn.NeighbourPriorPolicy(Inner(), ts, 2, 1.0).choose(ctx_b).action == 1


def test_prior_weight_arms_play_resumably_and_refuse_a_folder_made_with_other_tries(
    project_root, tmp_path, monkeypatch, capsys
) -> None:
    dp = load_bench_module(project_root, "demo_prior")
    model = project_root / "results/search_labels/model_search-both+dagger-both+floor.npz"
    tries = project_root / "results/tries_main.jsonl"
    out = tmp_path / "arms"
    argv = ["demo_prior.py", "--starts", "1", "--lams", "0", "--workers", "1"]
    argv += ["--model", str(model), "--out-dir", str(out)]
    monkeypatch.setattr(sys, "argv", [*argv, "--tries", str(tries)])
    assert dp.main() == 0  # one real greedy episode on the first validation start
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tries"] == str(tries) and summary["errored_episodes"] == 0
    assert summary["results"]["0"]["starts"] == 1 and summary["split"] == "validation"
    line = json.loads((out / "outcomes.jsonl").read_text())
    assert line["task_id"] == "main-val-0000" and line["lam"] == 0.0
    assert dp.main() == 0  # resumed: nothing played again
    assert len((out / "outcomes.jsonl").read_text().splitlines()) == 1
    other = project_root / "results/tries_hard.jsonl"
    monkeypatch.setattr(sys, "argv", [*argv, "--tries", str(other)])
    with pytest.raises(SystemExit, match="made with other starts, model, tries; use another dir"):
        dp.main()


def test_greedy_committee_counts_members_equally_and_keeps_unusable_demos_out(
    project_root, tmp_path
) -> None:
    gc = load_bench_module(project_root, "greedy_committee")
    inf = np.inf
    # Member 1 prefers demo 0 by a hair on a large Q scale, member 2 demo 1 by far on a small
    # one: standardised, member 2's clear preference wins; demo 3 is unusable for everyone.
    scores_ma = np.array([[100.0, 99.9, 0.0, -inf], [0.0, 1.0, 0.0, -inf]])
    z = gc.combine_scores(scores_ma, "z")
    assert int(np.argmax(z)) == 1 and np.isneginf(z[3])
    borda = gc.combine_scores(scores_ma, "borda")
    # ranks: member 1 -> 0, 1, 2; member 2 -> 1, then the tie 0, 2 in index order
    assert borda.tolist()[:3] == [-1.0, -1.0, -4.0] and np.isneginf(borda[3])
    # a demo one member cannot score is unusable for the committee
    assert np.isneginf(gc.combine_scores(np.array([[1.0, 2.0], [1.0, -inf]]), "z")[1])
    model = tmp_path / "m.npz"
    model.write_bytes(b"")
    arm = gc.parse_arm(f"z2=z:{model},{model}")
    assert arm.combine == "z" and len(arm.model_paths) == 2
    for bad in ("nameonly", f"x=mean:{model}", "x=z:/no/such/model.npz"):
        with pytest.raises(SystemExit):
            gc.parse_arm(bad)


def test_another_slack_weight_names_its_own_models_and_sorts_after_the_fixed_ones(
    project_root,
) -> None:
    lm = load_bench_module(project_root, "level_models")
    assert lm.slack_weight({"C": 1000.0}, None) == (1000.0, "")
    assert lm.slack_weight({"C": 1000.0}, 1000) == (1000.0, "")
    assert lm.slack_weight({"C": 1000.0}, 3000.0) == (3000.0, "-C3000")
    assert lm._ordered({"both-C3000": 0, "hard": 0, "main": 0}) == ["main", "hard", "both-C3000"]


def test_another_margin_scale_names_its_own_models(project_root) -> None:
    lm = load_bench_module(project_root, "level_models")
    assert lm.margin_weight({"margin_scale": 1.0}, None) == (1.0, "")
    assert lm.margin_weight({}, 1.0) == (1.0, "")  # a model from before the scale was recorded
    assert lm.margin_weight({"margin_scale": 1.0}, 3) == (3.0, "-m3")
    assert lm.margin_weight({"margin_scale": 1.0}, 0.3) == (0.3, "-m0.3")


def test_greedy_fragility_slides_a_chain_along_itself_and_finds_the_first_other_choice(
    project_root,
) -> None:
    gf = load_bench_module(project_root, "greedy_fragility")
    bent = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.2, 0.1, 0]])
    forward = gf.slide_along(bent, 0.05)  # every node 5 cm further along the chain
    assert np.allclose(forward[:3], [[0.05, 0, 0], [0.15, 0, 0], [0.2, 0.05, 0]])
    assert np.allclose(forward[3], [0.2, 0.15, 0])  # past the end: along the end's direction
    back = gf.slide_along(bent, -0.05)
    assert np.allclose(back[0], [-0.05, 0, 0]) and np.allclose(back[3], [0.2, 0.05, 0])
    assert np.allclose(gf.slide_along(bent, 0.0), bent)
    assert gf.first_other_choice(["a", "b", "c"], ["a", "x", "c"]) == 1
    assert gf.first_other_choice(["a", "b"], ["a", "b", "c"]) is None


def test_greedy_fragility_puts_a_chain_on_another_chains_curve(project_root) -> None:
    gf = load_bench_module(project_root, "greedy_fragility")
    bent = np.array([[0.0, 0, 0], [0.2, 0, 0], [0.2, 0.2, 0]])
    points = np.array([[0.05, 0.01, 0], [0.25, 0.1, 0.02], [-0.1, 0.05, 0], [0.2, 0.3, 0]])
    on = gf.on_curve(points, bent)
    # Each point goes to its nearest place on the curve, which runs on past its ends.
    assert np.allclose(on, [[0.05, 0, 0], [0.2, 0.1, 0], [-0.1, 0, 0], [0.2, 0.3, 0]])
    # A chain on its own curve stays where it is; the true nodes on a slid estimate's curve
    # (same shape) are the true nodes: no shape error is left, only the slide.
    assert np.allclose(gf.on_curve(bent, bent), bent)
    line = np.column_stack([np.linspace(0, 0.4, 9), np.zeros(9), np.zeros(9)])
    slid = gf.slide_along(line, 0.03)  # runs 3 cm past the line's end, along it
    assert np.allclose(gf.on_curve(line, slid), line)
    assert np.allclose(gf.on_curve(slid, line), slid)
