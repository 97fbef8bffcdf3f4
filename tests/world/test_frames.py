"""Recording an execution's frames for animation reads poses only: the physics is unchanged."""

from __future__ import annotations

import numpy as np

from knotlab.core.tasks.overhand.knot_sequence import overhand_sequence
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.rope import straight_rope
from knotlab.core.world.sim import RopeWorld


def test_frames_do_not_change_the_outcome_and_end_at_the_final_rope():
    traj = overhand_sequence()[0]
    with RopeWorld() as world:
        world.reset(straight_rope())
        start = world.snapshot()
        plain = world.execute(traj)
        after_plain = world.rope_nodes()
        world.restore(start)
        rec = FrameRecorder(1 / 30)
        recorded = world.execute(traj, frames=rec)
        after_recorded = world.rope_nodes()
    assert np.array_equal(after_plain, after_recorded)
    assert plain.sim_steps == recorded.sim_steps and rec.finished
    frames = recorded.frames
    assert frames is not None and len(frames) == len(rec) > 10
    assert np.all(np.diff(frames.times_f) >= 0)
    assert np.allclose(frames.nodes_fk3[-1], after_recorded, atol=1e-6)  # float32 frames
    assert frames.closed_fg.any()  # the grasp shows in the frames
