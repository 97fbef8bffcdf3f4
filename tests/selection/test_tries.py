"""Tried candidates: simulated on real states, read back, applied to the QP (see
docs/reference/learning.md, "Tried candidates")."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from knotlab.app import cli
from knotlab.core.errors import InvalidInputError
from knotlab.core.experiments.tries import try_candidates, try_jobs
from knotlab.core.selection.learner import LabelledState, MaxMarginQLearner, TrainingData
from knotlab.core.selection.tries import StateTries, TriedDemo, apply_tries, read_tries
from tests.minilib import mini_executions, mini_library, mini_train_args


def _state(margins: list[float], expert: int = 0, step: int = 0) -> LabelledState:
    rng = np.random.default_rng(step)
    return LabelledState(rng.normal(size=(len(margins), 3)), expert, np.array(margins), 0, step)


def test_apply_tries_drops_rows_against_demos_that_advanced_and_floors_the_others() -> None:
    keys = ("a", "b", "c", "d")
    data = TrainingData((_state([0.0, 0.1, 0.02, 0.3]),))
    rec = StateTries(
        "ex", 0, 1,
        (TriedDemo("a", 2, False, None), TriedDemo("b", 2, False, None),
         TriedDemo("c", 1, False, None), TriedDemo("d", 3, True, None)),
    )  # fmt: skip
    out = apply_tries(data, "ex", {("ex", 0): rec}, keys).states[0]
    assert out.also_good_a.tolist() == [False, True, False, True]  # b advanced, d tied the knot
    # c kept the stage: its margin rises to the median positive margin (0.1); the rest as before
    assert np.allclose(out.margins_a, [0.0, 0.1, 0.1, 0.3])
    untouched = apply_tries(data, "other", {("ex", 0): rec}, keys).states[0]
    assert untouched.also_good_a is None


def test_a_failure_or_misgrasp_never_counts_as_advancing() -> None:
    rec = StateTries("ex", 0, 0, ())
    assert not rec.advanced(TriedDemo("a", 2, False, "misgrasp:left"))
    assert not rec.advanced(TriedDemo("a", 0, False, None))
    assert rec.advanced(TriedDemo("a", 3, True, None))


def test_the_learner_asks_nothing_against_an_also_good_demo() -> None:
    # Two demos whose features make "b" look better: without tries the label forces a above b
    phi = np.array([[0.0, 1.0], [1.0, 0.0]])
    plain = LabelledState(phi, 0, np.array([0.0, 0.2]))
    tried = dataclasses.replace(plain, also_good_a=np.array([False, True]))
    fit = MaxMarginQLearner(C=10.0, D=1.0, standardize=False)
    assert fit.fit(TrainingData((plain,))).metrics["n_margin_rows"] == 1
    assert fit.fit(TrainingData((tried,))).metrics["n_margin_rows"] == 0


def test_read_tries_names_a_bad_line(tmp_path) -> None:
    path = tmp_path / "tries.jsonl"
    good = StateTries("ex", 1, 0, (TriedDemo("a", 1, False, None),))
    path.write_text(json.dumps(good.to_dict()) + "\n{not json\n")
    with pytest.raises(InvalidInputError, match=r"tries.jsonl:2"):
        read_tries(path)
    path.write_text(json.dumps(good.to_dict()) + "\n")
    assert read_tries(path) == {("ex", 1): good}
    with pytest.raises(InvalidInputError, match="no such tries file"):
        read_tries(tmp_path / "missing.jsonl")


def test_a_tries_line_keeps_its_cpu_kind_and_an_older_line_reads_as_unrecorded(tmp_path) -> None:
    path = tmp_path / "tries.jsonl"
    made = StateTries("ex", 1, 0, (TriedDemo("a", 1, False, None),), "avx2")
    older = {k: v for k, v in StateTries("ex", 2, 0, ()).to_dict().items() if k != "numeric_kind"}
    path.write_text(json.dumps(made.to_dict()) + "\n" + json.dumps(older) + "\n")
    read = read_tries(path)
    assert read[("ex", 1)] == made and read[("ex", 2)].numeric_kind == "unrecorded"
    path.write_text(json.dumps({**made.to_dict(), "numeric_kind": 5}) + "\n")
    with pytest.raises(InvalidInputError, match=r"tries.jsonl:1: .*'numeric_kind' is 5"):
        read_tries(path)


@pytest.mark.slow
def test_tries_are_simulated_from_the_labelled_rope_and_repeat_exactly() -> None:
    lib = mini_library(2)
    ex = mini_executions(2)[0]
    steps = tuple(
        dataclasses.replace(s, candidates=(lib.keys[0], lib.keys[1], s.chosen_demo))
        for s in ex.steps
    )
    ex = dataclasses.replace(ex, steps=steps)
    jobs = try_jobs([ex], top=2, done={(ex.execution_id, 2)})
    assert [j.step_index for j in jobs] == [0, 1] and all(len(j.candidates) == 2 for j in jobs)
    first = sorted(try_candidates(jobs, lib, workers=1, progress=False), key=lambda r: r.step_index)
    again = sorted(try_candidates(jobs, lib, workers=1, progress=False), key=lambda r: r.step_index)
    assert first == again
    assert [t.demo for t in first[0].tried] == [lib.keys[0], lib.keys[1]]
    # the first demo's own first step, from its own start, makes the loop
    assert first[0].stage_before == 0 and first[0].advanced(first[0].tried[0])


def test_train_with_tries_records_them_and_refuses_a_foreign_demo(tmp_path, capsys) -> None:
    args, out = mini_train_args(tmp_path)
    lib = mini_library(2)
    ex = mini_executions(2)[0]
    rec = StateTries(ex.execution_id, 0, 0, (TriedDemo(lib.keys[3], 0, False, None),))
    tries = tmp_path / "tries.jsonl"
    tries.write_text(json.dumps(rec.to_dict()) + "\n")
    assert cli.main([*args, "--tries", str(tries)]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert info["tries"] == str(tries) and info["tried_states"] == 1
    bad = StateTries(ex.execution_id, 0, 0, (TriedDemo("s999-t0", 0, False, None),))
    tries.write_text(json.dumps(bad.to_dict()) + "\n")
    out.unlink()
    assert cli.main([*args, "--tries", str(tries)]) == 2
    assert "s999-t0" in capsys.readouterr().err


def test_merging_training_parts_keeps_what_the_tries_set() -> None:
    from knotlab.core.selection.model_selection import merge_training_data

    tried = dataclasses.replace(_state([0.0, 0.1, 0.2]), also_good_a=np.array([0, 1, 0], bool))
    merged = merge_training_data([TrainingData((_state([0.0, 0.3, 0.1]),)), TrainingData((tried,))])
    assert merged.states[0].also_good_a is None
    assert merged.states[1].also_good_a.tolist() == [False, True, False]
    assert [s.execution for s in merged.states] == [0, 1]
