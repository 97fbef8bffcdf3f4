"""Paints the frames of a moving rope and its grippers by updating scene nodes in place.

An animation frame used to add the rope's tube mesh and both gripper spheres anew: the browser
then built a fresh geometry, material and scene node 60 times a second per tab. Here the nodes
are added once; a frame sends only the tube's vertices (viser writes them into the same GL
buffer) and the spheres' positions, and a gripper closing shows its other sphere. Frames that
fall due while the previous one is still being sent are skipped, so a loaded machine shows a
lower frame rate at the right simulated time instead of a slower and slower film.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import viser

from knotlab.app.web.geometry import tube_faces, tube_vertices

GRIPPER_NAMES = ("left", "right")
MAX_PAINT_HZ = 30.0  # frames sent per second at most: smooth to the eye, half the old load
OPEN_COLOUR = (60, 60, 60)


@dataclass(frozen=True)
class GripperLook:
    """How a gripper sphere is drawn open and closed (radii in m)."""

    closed_colour: tuple[int, int, int]
    open_radius: float = 0.012
    closed_radius: float = 0.018


class FramePainter:
    """Draws rope + gripper frames under ``root`` (``root``/rope, ``root``/grippers/...)."""

    def __init__(
        self,
        client: viser.ClientHandle | viser.ViserServer,
        root: str,
        *,
        rope_radius: float,
        rope_colour: tuple[int, int, int],
        look: GripperLook,
        active_g: tuple[bool, bool] = (True, True),
        grippers_path: str | None = None,
    ) -> None:
        self.client = client
        self.rope_path = f"{root}/rope"
        self.grippers_path = grippers_path or f"{root}/grippers"
        self.rope_radius = rope_radius
        self.rope_colour = rope_colour
        self.look = look
        self.active_g = active_g
        self._rope: viser.MeshHandle | None = None
        self._rope_nodes = -1
        self._grippers: list[_Gripper] = []

    def paint(self, nodes_k3: np.ndarray, grippers_g3: np.ndarray, closed_g: np.ndarray) -> None:
        """Draw one frame: the rope's centreline and each active gripper's position and grip."""
        with self.client.atomic():
            try:
                self._paint(np.asarray(nodes_k3), grippers_g3, closed_g)
            except RuntimeError:  # viser refuses writes to a node removed meanwhile: add anew
                self.reset()
                self._paint(np.asarray(nodes_k3), grippers_g3, closed_g)

    def reset(self) -> None:
        """Forget the nodes (they were removed): the next frame adds them again."""
        self._rope, self._rope_nodes, self._grippers = None, -1, []

    def _paint(self, nodes: np.ndarray, grippers_g3: np.ndarray, closed_g: np.ndarray) -> None:
        verts = tube_vertices(nodes, self.rope_radius)
        if self._rope is None or self._rope_nodes != len(nodes):
            self._rope = self.client.scene.add_mesh_simple(
                self.rope_path,
                verts,
                tube_faces(len(nodes), 12),
                color=self.rope_colour,
                flat_shading=False,
            )
            self._rope_nodes = len(nodes)
        else:
            self._rope.vertices = verts
        if not self._grippers:
            self._grippers = [
                self._add_gripper(name, on)
                for name, on in zip(GRIPPER_NAMES, self.active_g, strict=True)
            ]
        for g, gripper in enumerate(self._grippers):
            if self.active_g[g]:
                gripper.move(grippers_g3[g], bool(closed_g[g]))

    def _add_gripper(self, name: str, active: bool) -> _Gripper:
        scene, look = self.client.scene, self.look
        base = f"{self.grippers_path}/{name}"
        frame = scene.add_frame(base, show_axes=False, visible=active)
        return _Gripper(
            frame,
            scene.add_icosphere(f"{base}/open", radius=look.open_radius, color=OPEN_COLOUR),
            scene.add_icosphere(
                f"{base}/held", radius=look.closed_radius, color=look.closed_colour, visible=False
            ),
        )


@dataclass
class _Gripper:
    """A gripper's moving frame and its two spheres (open, held), one shown at a time."""

    frame: viser.FrameHandle
    open_sphere: viser.IcosphereHandle
    held_sphere: viser.IcosphereHandle
    held: bool = False

    def move(self, position_3: np.ndarray, held: bool) -> None:
        """Put the gripper at ``position_3``, its grip shown by which sphere is visible."""
        self.frame.position = tuple(float(v) for v in position_3)  # type: ignore[assignment]
        if held is not self.held:
            self.held_sphere.visible = held
            self.open_sphere.visible = not held
            self.held = held


def next_frame_index(
    time_of: Callable[[int], float], i: int, n: int, t_wall0: float, speed: float, now: float
) -> int:
    """The frame to paint after frame ``i`` of ``n`` recorded, at wall time ``now``: the newest
    one already due (those between are skipped), else ``i + 1``. Frame k is due at
    ``t_wall0 + time_of(k) / speed``."""
    j = i + 1
    while j + 1 < n and t_wall0 + time_of(j + 1) / speed <= now:
        j += 1
    return j
