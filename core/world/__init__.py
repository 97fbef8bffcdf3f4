"""The rope world: simulation, rope geometry, knot test, stages, trajectories, observation."""
