"""Animation frames update the rope and grippers in place, and late frames are skipped."""

from __future__ import annotations

import numpy as np
import pytest
import viser

from knotlab.app.web.frame_painter import FramePainter, GripperLook, next_frame_index


def test_the_next_frame_is_the_newest_due_one_else_the_following() -> None:
    times = [k / 30 for k in range(100)]  # recorded at 30 Hz, played at 2x: one due every 1/60 s

    def at(i: int, now: float, n: int = 100) -> int:
        return next_frame_index(times.__getitem__, i, n, 0.0, 2.0, now)

    assert at(0, 0.0) == 1  # on time: the next one (it waits for its due time)
    assert at(0, 10 / 60) == 10  # ten frames late: the newest due one; 1-9 are skipped
    assert at(0, 1e6, n=40) == 39  # never past the last recorded frame
    assert at(5, 5 / 60 + 1e-9) == 6


@pytest.fixture
def server():
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


def _frame(shift: float, held: bool):
    nodes = np.stack([np.linspace(0, 0.5, 40), np.full(40, shift), np.zeros(40)], axis=1)
    grippers = np.array([[0.0, shift, 0.05], [0.5, shift, 0.05]])
    return nodes, grippers, np.array([held, False])


def test_frames_reuse_the_rope_and_gripper_nodes_and_show_the_grip(server) -> None:
    painter = FramePainter(
        server, "/label", rope_radius=0.01, rope_colour=(196, 120, 60), look=GripperLook((0, 1, 2))
    )
    painter.paint(*_frame(0.0, held=False))
    rope, left = painter._rope, painter._grippers[0]
    assert rope is not None
    painter.paint(*_frame(0.1, held=True))
    assert painter._rope is rope and painter._grippers[0] is left  # updated, not added anew
    assert np.isclose(np.asarray(rope.vertices)[:, 1].mean(), 0.1, atol=1e-3)
    assert np.allclose(left.frame.position, (0.0, 0.1, 0.05))
    assert left.held_sphere.visible and not left.open_sphere.visible
    painter.paint(*_frame(0.2, held=False))
    assert left.open_sphere.visible and not left.held_sphere.visible


def test_a_painter_whose_nodes_were_removed_adds_them_again(server) -> None:
    painter = FramePainter(
        server,
        "/playback",
        rope_radius=0.01,
        rope_colour=(196, 120, 60),
        look=GripperLook((0, 1, 2)),
    )
    painter.paint(*_frame(0.0, held=False))
    old = painter._rope
    server.scene.remove_by_name("/playback")  # the user left the view mid-play
    painter.paint(*_frame(0.1, held=False))
    assert painter._rope is not None and painter._rope is not old
    assert np.allclose(painter._grippers[1].frame.position, (0.5, 0.1, 0.05))
