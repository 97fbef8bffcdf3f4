"""The Inspect tab's explainer: its simulator costs a new tab nothing until Inspect is used."""

from __future__ import annotations

import numpy as np

from knotlab.app.web.inspect import Inspector


def test_the_inspectors_simulator_is_made_on_first_use_and_explains_the_state(resources) -> None:
    inspector = Inspector(resources)
    try:
        assert inspector._world is None  # building a tab builds no simulator for Inspect
        start = next(iter(resources.tasks))
        view = inspector.load(np.asarray(start.start_nodes_k3), start.task_id)
        assert inspector._world is not None and inspector.world is inspector._world
        assert np.allclose(view.nodes_k3, inspector.world.rope_nodes())
    finally:
        inspector.close()
    Inspector(resources).close()  # never used: closing has no simulator to free
