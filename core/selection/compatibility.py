"""Does a Q-model belong with a demo library and a task? One check, one clear error.

A model's features are defined per library (one column per demo, the demo's costs), per
observation model (the clouds it was trained on) and per task (its labels judged that task's
goal). Mixing any of them gives numbers that look fine and mean nothing, so every place that
pairs a model with a library asks here.
"""

from __future__ import annotations

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.qmodel import QModel
from knotlab.core.tasks import Task, check_task_of
from knotlab.core.world.observation import ObservationModel


def check_compatible(library: DemoLibrary, model: QModel | None, task: Task) -> None:
    """Raise InvalidInputError (one line) unless library, model and task belong together."""
    check_task_of("demo library", library.metadata.get("task"), task)
    if model is None:
        return
    spec = model.feature_spec
    check_task_of("model", spec.task, task)
    lib_hash = library.content_hash()
    if spec.library_hash != lib_hash:
        raise InvalidInputError(
            f"the model was trained on library {spec.library_hash}, "
            f"this library is {lib_hash}: retrain it with `knotlab train`"
        )
    check_observation(model, ObservationModel.of_library_metadata(library.metadata))


def check_observation(model: QModel, observation: ObservationModel) -> None:
    """Raise unless the model was trained on clouds of the library's observation model."""
    model_obs = ObservationModel.parse(model.feature_spec.observation_model)
    if model_obs is not observation:
        raise InvalidInputError(
            f"the model was trained on '{model_obs.value}' observations but this library's "
            f"clouds are '{observation.value}': use a library and model made with the same "
            "observation model"
        )


def check_feature_names(model: QModel, names: tuple[str, ...]) -> None:
    """Raise unless the model's feature columns are the ones this code computes."""
    theirs = model.feature_spec.names
    if list(theirs) != list(names):
        raise InvalidInputError(
            "the model's features do not match this library and code "
            f"({len(theirs)} model columns, {len(names)} here): retrain it with `knotlab train`"
        )
