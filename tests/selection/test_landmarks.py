"""Landmark states: sampling, storage in the model file, and the value features they give."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from knotlab.app import cli
from knotlab.core.errors import CorruptFileError, InvalidInputError
from knotlab.core.selection.features import LibraryFeaturizer
from knotlab.core.selection.labels import DeadEndState
from knotlab.core.selection.landmarks import Landmarks, sample_landmarks
from knotlab.core.selection.learner import MaxMarginQLearner
from knotlab.core.selection.qmodel import QModel
from tests.minilib import mini_executions, mini_library, mini_train_args

pytestmark = pytest.mark.xdist_group("minilib")


def _executions_with_dead_ends():
    """Mini executions, each with one dead end: its start cloud squashed to a straight line."""
    out = []
    for ex in mini_executions(2):
        cloud = ex.steps[0].cloud_n3.copy()
        cloud[:, 1] = 0.0  # a straight rope: nothing like the looped states that follow
        out.append(dataclasses.replace(ex, dead_ends=(DeadEndState(cloud),)))
    return out


def test_sampling_is_seeded_and_takes_from_both_kinds():
    executions = _executions_with_dead_ends()
    a = sample_landmarks(executions, n_labelled=4, n_dead_ends=1, seed=3)
    b = sample_landmarks(executions, n_labelled=4, n_dead_ends=1, seed=3)
    assert a.kinds == ("labelled",) * 4 + ("dead_end",)
    assert a.content_hash() == b.content_hash()
    everything = sample_landmarks(executions, n_labelled=100, n_dead_ends=100)
    assert len(everything) == 6 + 2  # 2 executions x 3 steps, 2 dead ends: no more exist
    with pytest.raises(InvalidInputError):
        sample_landmarks(executions, n_labelled=-1)


def test_landmarks_round_trip_through_arrays_and_reject_inconsistent_ones():
    marks = sample_landmarks(_executions_with_dead_ends(), n_labelled=3, n_dead_ends=2)
    back = Landmarks.from_arrays(marks.to_arrays())
    assert back.content_hash() == marks.content_hash() and back.kinds == marks.kinds
    arrays = marks.to_arrays()
    arrays["landmark_sizes_l"] = arrays["landmark_sizes_l"] + 1
    with pytest.raises(InvalidInputError, match="sizes add up"):
        Landmarks.from_arrays(arrays)
    with pytest.raises(InvalidInputError, match="kinds"):
        Landmarks((np.zeros((3, 3)),), ("somewhere",))


def test_landmark_columns_are_a_state_softmax_that_peaks_at_the_matching_landmark():
    lib = mini_library(2)
    marks = sample_landmarks(_executions_with_dead_ends(), n_labelled=6, n_dead_ends=2)
    fz = LibraryFeaturizer(lib, landmarks=marks)
    names = list(fz.feature_spec.names)
    cols = [i for i, n in enumerate(names) if n.startswith("landmark[")]
    assert len(cols) == len(marks) and names[cols[-1]].endswith(":dead_end]")
    assert fz.feature_spec.landmark_hash == marks.content_hash()
    for target in (0, len(marks) - 1):
        phi, _ = fz.features(marks.clouds[target])
        near = phi[:, cols]
        assert np.all(near == near[0])  # the same for every action: a state feature
        assert near[0].sum() == pytest.approx(1.0)
        assert near[0, target] == pytest.approx(near[0].max())  # (both dead ends are alike)
        assert near[0, target] > 0.4
    plain, _ = LibraryFeaturizer(lib).features(marks.clouds[0])
    assert phi.shape[1] == plain.shape[1] + len(marks)


def test_a_model_keeps_its_landmarks_and_rebuilds_its_featurizer(tmp_path):
    lib = mini_library(2)
    executions = _executions_with_dead_ends()
    marks = sample_landmarks(executions, n_labelled=6, n_dead_ends=2)
    fz = LibraryFeaturizer(lib, landmarks=marks)
    model = MaxMarginQLearner(C=10.0, D=1.0).fit(executions, fz)
    assert model.landmarks is not None
    path = model.save(tmp_path / "m.npz")
    loaded = QModel.load(path)
    assert loaded.content_hash() == model.content_hash()
    assert loaded.landmarks.content_hash() == marks.content_hash()
    rebuilt = LibraryFeaturizer.for_model(lib, loaded)
    cloud = executions[0].steps[1].cloud_n3
    np.testing.assert_allclose(loaded.q(rebuilt.features(cloud)[0]), model.q(fz.features(cloud)[0]))
    # The dead end is valued below the states the expert went on from.
    v_dead = np.max(model.q(fz.features(executions[0].dead_ends[0].cloud_n3)[0]))
    v_start = np.max(model.q(fz.features(executions[0].steps[0].cloud_n3)[0]))
    assert v_dead < v_start
    # A model without landmarks cannot drive a featurizer that has them, and vice versa.
    plain = MaxMarginQLearner(C=10.0, D=1.0).fit(executions, LibraryFeaturizer(lib))
    assert plain.landmarks is None
    with pytest.raises(InvalidInputError, match="do not match"):
        QModel(
            plain.weights_d,
            plain.bias,
            plain.feature_mean_d,
            plain.feature_scale_d,
            plain.spec_dict,
            plain.hyperparameters,
            landmarks=marks,
        )
    # Tampering with the stored landmarks is caught by the content hash.
    with np.load(path) as data:
        arrays = {k: np.array(data[k]) for k in data.files}
    arrays["landmark_points_n3"][0, 0] += 0.01
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(CorruptFileError):
        QModel.load(tmp_path / "bad.npz")


def test_train_command_samples_landmarks_from_the_training_split(tmp_path, capsys):
    args, out = mini_train_args(tmp_path)
    assert cli.main([*args, "--landmarks", "2,5"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # One training execution of 3 states and no dead ends: 2 labelled landmarks, 0 dead ends.
    assert summary["landmarks"]["n"] == 2
    model = QModel.load(out)
    assert len(model.landmarks) == 2
    assert "value_auc" in summary["validation"]
    assert cli.main([*args, "--landmarks", "0,0", "--force"]) == 0  # replaces its own model
    assert QModel.load(out).landmarks is None
    assert cli.main([*args, "--landmarks", "5"]) == 2
