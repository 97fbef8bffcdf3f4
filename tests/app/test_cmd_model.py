"""`knotlab model info`: a saved model's features, hashes, settings and training metrics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from knotlab.app import cli, defaults
from knotlab.core.selection.qmodel import QModel


def _model(path: Path) -> QModel:
    model = QModel(
        weights_d=np.array([1.0, -2.0, 0.5]),
        bias=0.25,
        feature_mean_d=np.zeros(3),
        feature_scale_d=np.ones(3),
        spec_dict={
            "feature_set": "knotlab-features-v1",
            "library_hash": "feedc0ffee123456",
            "action_keys": ["s000-t0", "s000-t1"],
            "names": ["c1_map", "c2_bend_f", "grasp_dist_m"],
            "indicator_mask": [False, False, False],
            "phase_steps": [0, 1, 2],
            "phase_temperature": 0.25,
            "observation_model": "tracked",
            "landmark_hash": None,
        },
        hyperparameters={"C": 10.0, "D": 1.0},
        metrics={
            "train_top1": 0.75,
            "status": "optimal",
            "training_run": {"labels": "l.jsonl", "validation": None},
        },
    )
    model.save(path)
    return model


def test_model_info_prints_what_the_model_is(tmp_path: Path, capsys) -> None:
    model = _model(tmp_path / "m.npz")
    assert cli.main(["model", "info", str(tmp_path / "m.npz")]) == 0
    out = capsys.readouterr().out
    assert f"hash {model.content_hash()}" in out
    assert "feedc0ffee123456 (2 demos)" in out
    assert "observation:   tracked" in out
    assert "3 (knotlab-features-v1): c1_map, c2_bend_f, grasp_dist_m" in out
    assert "C=10.0, D=1.0" in out and "train_top1=0.75" in out


def test_model_info_json_holds_every_field(tmp_path: Path, capsys) -> None:
    model = _model(tmp_path / "m.npz")
    assert cli.main(["model", "info", str(tmp_path / "m.npz"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["hash"] == model.content_hash()
    assert info["library_hash"] == "feedc0ffee123456"
    assert info["observation_model"] == "tracked"
    assert info["feature_names"] == ["c1_map", "c2_bend_f", "grasp_dist_m"]
    assert info["n_features"] == 3 and info["n_actions"] == 2
    assert info["hyperparameters"] == {"C": 10.0, "D": 1.0}
    assert info["metrics"] == {"train_top1": 0.75, "status": "optimal"}
    assert info["training_run"]["labels"] == "l.jsonl"


@pytest.mark.skipif(not defaults.MODEL_PATH.exists(), reason="no shipped model")
def test_model_info_reads_the_shipped_model(capsys) -> None:
    assert cli.main(["model", "info", str(defaults.MODEL_PATH), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["hash"] == QModel.load(defaults.MODEL_PATH).content_hash()
    assert info["training_run"]["validation"]["n_states"] > 0
