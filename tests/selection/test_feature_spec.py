"""The typed seams: a model's FeatureSpec (stored dict and hash kept), StepOutcome's strings."""

from __future__ import annotations

import typing

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.outcomes import STEP_OUTCOMES, StepOutcome
from knotlab.core.selection.feature_spec import FeatureSpec
from knotlab.core.selection.labels import OUTCOMES, LabelledStep
from knotlab.core.selection.qmodel import QModel
from knotlab.core.tasks import get_task

_OLD_CLOUD_SPEC = {  # a spec as models saved before observation_model and tasks existed
    "feature_set": "knotlab-features-v1",
    "library_hash": "feedc0ffee123456",
    "action_keys": ["s000-t0"],
    "names": ["c1_map", "demo[s000-t0]"],
    "indicator_mask": [False, True],
    "phase_steps": [0],
    "phase_temperature": 0.25,
    "landmark_hash": None,
}


def _model(spec: dict) -> QModel:
    return QModel(np.array([1.0, 2.0]), 0.5, np.zeros(2), np.ones(2), spec, {})


def test_an_old_spec_reads_with_its_defaults_and_keeps_its_dict_and_hash() -> None:
    model = _model(dict(_OLD_CLOUD_SPEC))
    spec = model.feature_spec
    assert (spec.observation_model, spec.rank_features, spec.task) == ("cloud", False, "overhand")
    assert spec.names == ("c1_map", "demo[s000-t0]") and spec.indicator_mask == (False, True)
    assert spec.to_dict() != _OLD_CLOUD_SPEC  # to_dict would add observation_model ...
    assert model.spec_dict == _OLD_CLOUD_SPEC  # ... so the model keeps the dict it was given
    assert model.content_hash() == _model(dict(_OLD_CLOUD_SPEC)).content_hash()
    assert model.content_hash() != _model(spec.to_dict()).content_hash()


def test_to_dict_round_trips_and_writes_task_and_rank_features_only_when_set() -> None:
    spec = FeatureSpec.from_dict({**_OLD_CLOUD_SPEC, "observation_model": "centreline"})
    assert "task" not in spec.to_dict() and "rank_features" not in spec.to_dict()
    assert FeatureSpec.from_dict(spec.to_dict()) == spec
    other = FeatureSpec.from_dict({**spec.to_dict(), "task": "figure8", "rank_features": True})
    assert other.to_dict()["task"] == "figure8" and other.to_dict()["rank_features"] is True
    assert FeatureSpec.from_dict(other.to_dict()) == other


def test_a_spec_lacking_a_key_names_it() -> None:
    spec = {k: v for k, v in _OLD_CLOUD_SPEC.items() if k != "phase_steps"}
    with pytest.raises(InvalidInputError, match="'phase_steps'"):
        FeatureSpec.from_dict(spec)
    model = _model(spec)  # a partial spec still makes a model; only its typed form is refused
    with pytest.raises(InvalidInputError, match="'phase_steps'"):
        assert model.feature_spec is None  # (never reached)


def test_the_shipped_model_keeps_its_hash() -> None:
    model = QModel.load(get_task("overhand").files.model_path)
    assert model.content_hash() == "731a88753755aab6"
    assert model.feature_spec.observation_model == model.spec_dict["observation_model"]
    assert "task" not in model.spec_dict


def test_step_outcomes_are_the_stored_strings() -> None:
    assert STEP_OUTCOMES == OUTCOMES == ("progressed", "knot", "dead_end", "misgrasp", "skipped")
    assert StepOutcome.KNOT == "knot" and f"{StepOutcome.DEAD_END}" == "dead_end"
    step = LabelledStep(0, np.zeros((3, 3)), "s000-t0", "knot")  # a stored string reads back
    assert step.outcome is StepOutcome.KNOT
    with pytest.raises(InvalidInputError, match="outcome must be one of"):
        LabelledStep(0, np.zeros((3, 3)), "s000-t0", "tied")


def test_bench_engines_come_from_the_engine_literal() -> None:
    from knotlab.app import cmd_bench
    from knotlab.core.experiments.bench import ENGINES, Engine

    assert ENGINES == typing.get_args(Engine) == cmd_bench._ENGINE_CHOICES == ("local", "ray")
