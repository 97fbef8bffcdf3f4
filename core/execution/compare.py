"""One candidate executed twice from the same rope: in the agent's model and in another world.

What Inspect shows side by side, so a researcher sees what a model error does to one decision:
the same transferred trajectory, the same start rope (placed at rest in each), two physics.
Shape suffixes: n = cloud points, k = rope nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knotlab.core.execution.apply import ActionOutcome, apply_demo
from knotlab.core.registration.planner import DemoTransferer
from knotlab.core.tasks import Task
from knotlab.core.world.estimate import RopeEstimate, node_error_mm, place_estimate
from knotlab.core.world.protocol import World


@dataclass(frozen=True, eq=False)
class ModelAndWorld:
    """A candidate's outcome under the agent's model and under the other world."""

    model: ActionOutcome
    world: ActionOutcome

    @property
    def apart_mm(self) -> float:
        """Mean distance between the two ropes after the step (mm; inf if either broke)."""
        a, b = self.model.nodes_after_k3, self.world.nodes_after_k3
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return float("inf")
        return node_error_mm(a, b)

    @property
    def agree(self) -> bool:
        """Whether both reach the same stage (and the same goal)."""
        return (self.model.stage, self.model.knot) == (self.world.stage, self.world.knot)


def outcome_in_model_and_world(
    nodes_k3: np.ndarray,
    cloud_n3: np.ndarray,
    demo_index: int,
    transferer: DemoTransferer,
    model_world: World,
    world: World,
    *,
    task: Task | None = None,
) -> ModelAndWorld:
    """Place the rope at rest in both worlds, transfer demo ``demo_index`` onto ``cloud_n3`` and
    execute it in each; both worlds are left in their after-states."""
    estimate = RopeEstimate(np.asarray(nodes_k3, dtype=float))
    place_estimate(model_world, estimate)
    place_estimate(world, estimate)
    in_model = apply_demo(model_world, transferer, cloud_n3, demo_index, task=task)
    in_world = apply_demo(world, transferer, cloud_n3, demo_index, task=task)
    return ModelAndWorld(in_model, in_world)
