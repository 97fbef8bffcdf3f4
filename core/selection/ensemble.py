"""The ensemble of model worlds the robust and adaptive lookaheads search in.

Member 0 is the agent's own model world (the step context's); members 1..k-1 are copies of its
physics with every factor scaled by a seeded draw within +-``spread``
(`mismatch.perturb_params`, seeds ``seed + 1`` .. ``seed + k - 1``): the same draws for a given
seed, spread and model physics, whichever policy asks.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the simulator imports pybullet: only for the checker
    from knotlab.core.world.protocol import World
    from knotlab.core.world.sim import RopeWorld


class EnsembleWorlds:
    """The perturbed members' simulators per model physics, made on first use and kept."""

    def __init__(self, members: int, spread: float, seed: int) -> None:
        self.members, self.spread, self.seed = members, spread, seed
        self._worlds: dict[tuple, list[RopeWorld]] = {}

    def perturbed(self, model_world: World) -> list[RopeWorld]:
        """The worlds of members 1..k-1 around ``model_world``'s physics."""
        from knotlab.core.world.mismatch import PhysicsParams, perturb_params
        from knotlab.core.world.sim import GripperParams, RopeWorld

        gripper = getattr(model_world, "gripper", GripperParams())
        base = PhysicsParams(model_world.params, gripper)
        key = (base.rope, base.gripper)
        if key not in self._worlds:
            worlds = []
            for m in range(1, self.members):
                member = perturb_params(base, self.spread, self.seed + m)
                worlds.append(RopeWorld(member.rope, member.gripper))
            self._worlds[key] = worlds
        return self._worlds[key]

    def close(self) -> None:
        """Release the members' simulators."""
        for worlds in self._worlds.values():
            for world in worlds:
                world.close()
        self._worlds.clear()
