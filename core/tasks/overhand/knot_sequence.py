"""The fixed 3-step gripper sequence that ties an overhand knot in a straight rope.

Start: the straight rope along x, end A at x = -0.5, end B at x = +0.5, resting on the table
(`core.world.rope.straight_rope`). Only the right gripper works; the left one stays open and parked.
1. Make the loop: pick end B, lift it high (~0.55 m, so the rope hangs straight down) and lay it
   down along a counter-clockwise loop like a pen, crossing over the standing part, ending with
   the tail just below the loop's first side.
2. Lay the loop's first side over the tail: pick it next to the tail, lift only a little (a high
   lift drags the tail along) and pull it past the tail. Equivalent to the tail passing under,
   which a point gripper on a table cannot do directly.
3. Pull the tail out through the loop.
Rationale and measurements: docs/reference/rope_world.md, "The fixed 3-step sequence". Open
loop: it works on the straight rope only; the scripted expert generalises it.
"""

from __future__ import annotations

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.tasks.expert_moves import pick_place, single_gripper_trajectory
from knotlab.core.world.trajectory import GripperTrajectory


def overhand_sequence(
    rope_length: float = 1.0, rope_height: float = 0.01
) -> tuple[GripperTrajectory, GripperTrajectory, GripperTrajectory]:
    """The 3 trajectories that tie an overhand knot in the default straight rope."""
    if not np.isclose(rope_length, 1.0):
        raise InvalidInputError(
            f"the fixed knot sequence is laid out for a 1.0 m rope, got {rope_length} m"
        )
    z0 = rope_height
    # Step 1: end B's link centre, up, high above the loop start, then the pen-like laying path.
    link_b = np.array([0.4875, 0.0, z0])
    centre = np.array([-0.05, 0.08])
    radius = 0.08
    ang = np.linspace(-0.5 * np.pi, np.pi, 19)  # counter-clockwise, 270 degrees
    loop_xy = centre + radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    tail_xy = np.array([[-0.13, -0.06], [-0.01, -0.06]])
    path_xy = np.vstack([[-0.03, 0.0], loop_xy, tail_xy])
    legs = np.linalg.norm(np.diff(path_xy, axis=0), axis=1)
    frac = np.concatenate([[0.0], np.cumsum(legs)]) / legs.sum()
    top, bottom = 0.55, 0.02
    path_z = top + (bottom - top) * frac  # descend in proportion to the distance travelled
    laying = np.column_stack([path_xy, path_z])
    points1 = np.vstack([link_b, [0.45, 0.0, 0.10], laying, laying[-1:]])
    n1 = points1.shape[0]
    closed1 = np.ones(n1, dtype=bool)
    closed1[-1] = False
    speeds1 = np.full(n1, 0.3)
    step1 = single_gripper_trajectory(points1, closed1, speeds1)
    # Steps 2 and 3 pick where step 1 (resp. 2) leaves the rope in simulation: fixed numbers,
    # valid for the straight start only. Measured neighbours (pick link 20 or 21, place 7-11 cm
    # below the tail, lift 3-4 cm, pull 15-20 cm) all tie the knot, so this sits in a robust spot.
    step2 = pick_place(  # link 21, on the loop's first side, just above the tail end
        pick_3=np.array([0.002, 0.038, z0]),
        lift=0.04,
        place_xy=np.array([0.002, -0.136]),  # 9 cm below the tail end at y = -0.046
        place_z=0.02,
        speed=0.2,
    )
    tail_end = np.array([-0.053, -0.072, z0])  # link 39 after step 2
    step3 = pick_place(
        pick_3=tail_end,
        lift=0.05,
        place_xy=tail_end[:2] + np.array([0.20, -0.05]),
        place_z=0.02,
        speed=0.2,
    )
    return step1, step2, step3
