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


def test_a_reader_waiting_for_a_frame_is_woken_by_it_and_by_the_end() -> None:
    import pickle
    import threading
    import time

    rec = FrameRecorder(0.05)
    assert not rec.wait_for_frame(0, 0.01)  # nothing yet: the timeout
    adder = threading.Timer(0.2, rec.add, (0.0, np.zeros((3, 3)), np.zeros((2, 3)), [False] * 2))
    t0 = time.perf_counter()
    adder.start()
    assert rec.wait_for_frame(0, 5.0)
    assert 0.15 < time.perf_counter() - t0 < 2.0  # woken by the frame, not the timeout
    ender = threading.Timer(0.2, setattr, (rec, "finished", True))
    t0 = time.perf_counter()
    ender.start()
    assert not rec.wait_for_frame(1, 5.0) and rec.finished  # the end wakes it: no frame 1
    assert time.perf_counter() - t0 < 2.0
    copy = pickle.loads(pickle.dumps(rec))  # the lock stays behind; the frames travel
    assert len(copy) == 1 and copy.finished and copy.wait_for_frame(0, 0.01)
