"""Portable columns and transplanted models: one task's weights ranking another library's demos."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.feature_spec import FeatureSpec
from knotlab.core.selection.learner import LabelledState, MaxMarginQLearner, TrainingData
from knotlab.core.selection.transfer import (
    is_portable,
    pool_portable,
    portable_names,
    project_training_data,
    transplant,
)

PORTABLE = ("c1_map", "c2_bend_f", "c3_bend_g", "c1_map*c1_map", "grasp_dist_m", "phase_match")


def spec_of(demos: int, phases: int, *, landmarks: int = 0, temperature: float = 0.25,
            rank: bool = False) -> FeatureSpec:  # fmt: skip
    """A library's spec laid out as the featurizer lays it out (portable, phase, landmark, demo)."""
    names = (
        list(PORTABLE[:5])
        + [f"phase_{k}" for k in range(phases)]
        + ["phase_match"]
        + (["nn_rel"] if rank else [])
        + [f"landmark[{i}:labelled]" for i in range(landmarks)]
        + [f"demo[s{a:03d}-t{a % phases}]" for a in range(demos)]
    )
    n_onehot = landmarks + demos
    indicator = [False] * (len(names) - n_onehot) + [True] * n_onehot
    return FeatureSpec(
        "knotlab-features-v1",
        f"lib{demos}",
        tuple(f"s{a:03d}-t{a % phases}" for a in range(demos)),
        tuple(names),
        tuple(indicator),
        tuple(range(phases)),
        temperature,
        "lm" if landmarks else None,
        "centreline",
        rank,
        "overhand" if phases == 3 else "figure8",
    )


def random_data(spec: FeatureSpec, n_states: int, seed: int) -> TrainingData:
    """Labelled states whose expert action is the lowest c1 (a rule the portable columns see)."""
    rng = np.random.default_rng(seed)
    d, a = len(spec.names), len(spec.action_keys)
    states = []
    for s in range(n_states):
        phi = rng.normal(size=(a, d))
        best = int(np.argmin(phi[:, 0]))
        margins = np.abs(phi[:, 0] - phi[best, 0])
        states.append(LabelledState(phi, best, margins, execution=s // 3, step=s % 3))
    pairs = tuple((i, i + 1) for i in range(n_states - 1) if i % 3 != 2)
    return TrainingData(
        tuple(states), pairs, tuple(range(2, n_states, 3)), (rng.normal(size=(a, d)),)
    )


def test_per_library_columns_are_told_apart_from_portable_ones() -> None:
    spec = spec_of(demos=4, phases=3, landmarks=2)
    assert portable_names(spec) == PORTABLE
    assert not any(is_portable(n) for n in ("demo[s001-t1]", "landmark[3:dead_end]", "phase_2"))
    assert is_portable("phase_match") and is_portable("nn_rel")


def test_a_portable_fit_transplanted_ranks_another_library_exactly_as_it_ranks_itself() -> None:
    source, target = spec_of(demos=6, phases=3), spec_of(demos=8, phases=4)
    data, columns = pool_portable([(random_data(source, 12, 0), source)])
    model = MaxMarginQLearner(C=10.0).fit(data, columns)
    moved = transplant(model, target)
    assert moved.feature_spec.names == target.names and moved.landmarks is None
    assert moved.metrics["transplanted_from"]["columns"] == list(PORTABLE)
    phi = np.random.default_rng(5).normal(size=(8, len(target.names)))
    keep = [target.names.index(n) for n in PORTABLE]
    np.testing.assert_allclose(moved.q(phi), model.q(phi[:, keep]), rtol=0, atol=1e-12)
    # The per-library columns carry nothing: changing them leaves every Q as it was.
    other = phi.copy()
    other[:, [i for i in range(len(target.names)) if i not in keep]] = 7.0
    np.testing.assert_allclose(moved.q(other), moved.q(phi), rtol=0, atol=1e-12)
    assert moved.content_hash() != transplant(model, spec_of(demos=8, phases=2)).content_hash()


def test_a_full_models_portable_weights_move_and_its_per_library_ones_stay() -> None:
    source = spec_of(demos=5, phases=3)
    data = random_data(source, 9, 1)
    full = MaxMarginQLearner(C=10.0).fit(data, _SpecOnly(source))
    moved = transplant(full, spec_of(demos=3, phases=4))
    src = {n: i for i, n in enumerate(source.names)}
    for j, name in enumerate(moved.feature_spec.names):
        if is_portable(name):
            assert moved.weights_d[j] == full.weights_d[src[name]]
            assert moved.feature_scale_d[j] == full.feature_scale_d[src[name]]
        else:
            assert moved.weights_d[j] == 0.0
    assert moved.bias == full.bias


def test_pooling_keeps_each_parts_bellman_links_and_executions_apart() -> None:
    a, b = spec_of(demos=4, phases=3), spec_of(demos=6, phases=4)
    da, db = random_data(a, 6, 2), random_data(b, 9, 3)
    pooled, columns = pool_portable([(da, a), (db, b)])
    assert columns.names == PORTABLE
    assert len(pooled.states) == 15 and pooled.n_features == len(PORTABLE)
    assert pooled.bellman_pairs == da.bellman_pairs + tuple(
        (i + 6, j + 6) for i, j in db.bellman_pairs
    )
    assert pooled.goal_states == da.goal_states + tuple(g + 6 for g in db.goal_states)
    executions_a = {s.execution for s in pooled.states[:6]}
    executions_b = {s.execution for s in pooled.states[6:]}
    assert executions_a.isdisjoint(executions_b)
    assert [s.phi_ad.shape[0] for s in pooled.states] == [4] * 6 + [6] * 9
    # One part pooled is that part's portable columns, bit for bit (what `train --portable` fits).
    alone, _ = pool_portable([(db, b)])
    projected = project_training_data(db, b.names, PORTABLE)
    for x, y in zip(alone.states, projected.states, strict=True):
        assert np.array_equal(x.phi_ad, y.phi_ad)
    pairs = zip(alone.dead_ends_phi, projected.dead_ends_phi, strict=True)
    assert all(np.array_equal(x, y) for x, y in pairs)


@pytest.mark.parametrize(
    ("other", "problem"),
    [
        (spec_of(demos=4, phases=4, temperature=0.5), "portable columns differ"),
        (spec_of(demos=4, phases=4, rank=True), "portable columns differ"),
    ],
)
def test_libraries_whose_portable_columns_mean_other_things_are_not_pooled(other, problem) -> None:
    a = spec_of(demos=4, phases=3)
    with pytest.raises(InvalidInputError, match=problem):
        pool_portable([(random_data(a, 3, 0), a), (random_data(other, 3, 1), other)])


def test_transplant_refuses_targets_it_cannot_mean_the_same_on() -> None:
    source = spec_of(demos=4, phases=3)
    data, columns = pool_portable([(random_data(source, 6, 0), source)])
    model = MaxMarginQLearner(C=1.0).fit(data, columns)
    with pytest.raises(InvalidInputError, match="without landmarks"):
        transplant(model, spec_of(demos=4, phases=4, landmarks=2))
    with pytest.raises(InvalidInputError, match="phase temperatures differ"):
        transplant(model, spec_of(demos=4, phases=4, temperature=0.5))
    with pytest.raises(InvalidInputError, match="lacks the model's portable column 'nn_rel'"):
        ranked = spec_of(demos=4, phases=3, rank=True)
        data_r, cols_r = pool_portable([(random_data(ranked, 6, 0), ranked)])
        transplant(MaxMarginQLearner(C=1.0).fit(data_r, cols_r), spec_of(demos=4, phases=4))


def test_the_shipped_overhand_model_ranks_the_figure_eights_demos(project_root) -> None:
    """End to end on the shipped files: the transplanted model is one an Agent accepts."""
    from knotlab.core.agent import Agent
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.selection.features import LibraryFeaturizer
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.tasks import get_task

    overhand, figure8 = get_task("overhand"), get_task("figure8")
    library = DemoLibrary.load(figure8.files.library_path)
    moved = transplant(
        QModel.load(overhand.files.model_path), LibraryFeaturizer(library).feature_spec
    )
    agent = Agent(library, moved, policy="greedy")
    cloud = library.clouds()[4]  # a demo's own rope: that demo registers at ~zero cost
    scores = agent.scores(cloud)
    assert np.isfinite(scores).sum() > len(library) // 2
    assert np.all(np.isfinite(scores[[4]]))


class _SpecOnly:
    """What the learner reads from a featurizer when it is given data, not executions."""

    def __init__(self, spec: FeatureSpec) -> None:
        self._spec = spec
        self.landmarks = None

    def spec(self) -> dict:
        return self._spec.to_dict()


def test_the_command_line_transfers_a_model_and_keeps_what_it_did_not_make(tmp_path, capsys):
    import json

    from knotlab.app import cli
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.tasks import get_task

    source = str(get_task("overhand").files.model_path)
    out = tmp_path / "moved.npz"
    argv = ["model", "transfer", source, "--task", "figure8", "--out", str(out)]
    assert cli.main([*argv, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])
    moved = QModel.load(out)
    assert summary["model_hash"] == moved.content_hash() and summary["task"] == "figure8"
    assert summary["from_task"] == "overhand" and "grasp_dist_m" in summary["columns"]
    assert all(n.startswith(("demo[", "phase_")) and n != "phase_match" for n in summary["zeroed"])
    assert moved.metrics["transplanted_from"]["model_hash"] == QModel.load(source).content_hash()
    before = out.read_bytes()
    assert cli.main(argv) == 2  # exists: never replaced without --force
    assert "--force" in capsys.readouterr().err and out.read_bytes() == before
    assert cli.main(["model", "info", str(out)]) == 0
    assert "transplanted: from the overhand model" in capsys.readouterr().out


def test_a_pooled_model_with_each_librarys_demo_priors_carries_its_own_onto_its_library():
    from knotlab.core.selection.transfer import pool_with_own_columns

    a, b = spec_of(demos=4, phases=3), spec_of(demos=5, phases=4)
    data, columns = pool_with_own_columns(
        [("knot_a", random_data(a, 6, 0), a), ("knot_b", random_data(b, 9, 1), b)]
    )
    assert columns.names[: len(PORTABLE)] == PORTABLE
    assert columns.names[len(PORTABLE) :] == tuple(
        [f"knot_a:{n}" for n in a.names if n.startswith("demo[")]
        + [f"knot_b:{n}" for n in b.names if n.startswith("demo[")]
    )
    assert not any(is_portable(n) for n in columns.names[len(PORTABLE) :])
    first_b = len(PORTABLE) + 4
    assert not data.states[0].phi_ad[:, first_b:].any()  # knot_a's states: no knot_b priors
    assert not data.states[6].phi_ad[:, len(PORTABLE) : first_b].any()
    model = MaxMarginQLearner(C=10.0).fit(data, columns)
    carry = {f"knot_b:{n}": n for n in b.names if n.startswith("demo[")}
    moved = transplant(model, b, also=carry)
    phi = np.random.default_rng(3).normal(size=(5, len(b.names)))
    pooled_phi = np.zeros((5, len(columns.names)))
    for j, name in enumerate(columns.names):
        own = name.removeprefix("knot_b:")
        if name in PORTABLE or name.startswith("knot_b:"):
            pooled_phi[:, j] = phi[:, b.names.index(own)]
    np.testing.assert_allclose(moved.q(phi), model.q(pooled_phi), rtol=0, atol=1e-12)
    with pytest.raises(InvalidInputError, match="cannot carry"):
        transplant(model, b, also={"knot_c:demo[x]": "demo[x]"})
