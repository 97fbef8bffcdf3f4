"""Draws one tab's session in its 3D scene: table, rope tube, cloud, ranked candidates, animation.

Scene paths: /table, and under /label (hidden while Inspect draws its own view): rope, cloud,
grippers/{left,right}, candidates/{rank}/{path_g,grasp_i,release_i,label}, warped.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import viser

from knotlab.app.web.geometry import pick_candidate, tube_faces, tube_vertices
from knotlab.app.web.session import Candidate, SessionView
from knotlab.core.world.frames import FrameRecorder

ROPE_RADIUS = 0.01  # m, as the simulator's rope
ROPE_COLOUR = (196, 120, 60)
CLOUD_COLOUR = (40, 90, 200)
GREY = (170, 170, 170)
# Rank colours (1 = best): distinct, colour-blind-safe (Okabe-Ito).
RANK_COLOURS = (
    (0, 158, 115),
    (230, 159, 0),
    (86, 180, 233),
    (204, 121, 167),
    (213, 94, 0),
    (0, 114, 178),
    (240, 228, 66),
    (120, 120, 120),
    (0, 0, 0),
)
PLAYBACK_SPEED = 2.0  # animation runs at twice simulated time: a 6 s execution plays in 3 s


def rank_colour(rank: int) -> tuple[int, int, int]:
    """The colour of a candidate rank (1-based), cycling after nine."""
    return RANK_COLOURS[(rank - 1) % len(RANK_COLOURS)]


def candidate_label(c: Candidate) -> str:
    """The 3D label and list text of a candidate: rank, demo, its step, Q, cost."""
    score = f"Q {c.ranked.q:.2f}" if c.ranked.q is not None else "NN"
    return f"#{c.ranked.rank} {c.ranked.demo_key} · step {c.demo_step + 1} · {score}"


def _xyz(p: np.ndarray) -> tuple[float, float, float]:
    return (float(p[0]), float(p[1]), float(p[2]))


_Method = TypeVar("_Method", bound=Callable[..., Any])


def _serialised(method: _Method) -> _Method:
    """Run a drawing method under the drawer's lock.

    Viser runs every callback on its own thread: a click's redraw can meet another click's, or a
    try's, and two redraws at once remove each other's nodes half-way ("Cannot assign to
    'position' on a removed handle"), seen under load.
    """

    @functools.wraps(method)
    def locked(self: SceneDrawer, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return locked  # type: ignore[return-value]


class SceneDrawer:
    """One client's scene: draws a SessionView and plays try animations."""

    def __init__(self, client: viser.ClientHandle, on_pick: Callable[[int], None]) -> None:
        self.client = client
        self.scene = client.scene
        self._on_pick = on_pick
        self._polylines: dict[int, list[np.ndarray]] = {}
        self._markers: dict[int, list[tuple[np.ndarray, float]]] = {}
        self._drawn_ranks: list[int] = []
        self._lock = threading.RLock()  # one redraw at a time (see _serialised)
        self._anim_stop = threading.Event()
        self._anim_thread: threading.Thread | None = None
        self.first_frame_at: float | None = None  # perf_counter of the last try's first frame
        self.scene.add_box(
            "/table", color=(225, 222, 212), dimensions=(1.6, 1.2, 0.02), position=(0, 0, -0.011)
        )
        self.scene.add_grid("/grid", width=1.6, height=1.2, cell_size=0.1, position=(0, 0, 0.0005))
        self.label_root = self.scene.add_frame("/label", show_axes=False)
        self.scene.on_click()(self._scene_click)

    def set_label_visible(self, visible: bool) -> None:
        """Show or hide everything the labelling view draws (Inspect draws its own)."""
        self.label_root.visible = visible

    # ------------------------------------------------------------------ state
    @_serialised
    def draw(self, view: SessionView, *, look: bool = False, show_warped: bool = False) -> None:
        """Draw the rope, cloud and candidates of ``view`` (``look`` points the camera at it)."""
        with self.client.atomic():
            if view.rope_nodes_k3 is not None:
                self.draw_rope(view.rope_nodes_k3)
            else:
                self.scene.remove_by_name("/label/rope")
            if view.cloud_n3 is not None:
                self.scene.add_point_cloud(
                    "/label/cloud",
                    np.asarray(view.cloud_n3, dtype=np.float32),
                    CLOUD_COLOUR,
                    point_size=0.008,
                    point_shape="circle",
                    precision="float32",
                )
            else:
                self.scene.remove_by_name("/label/cloud")
            self.scene.remove_by_name("/label/grippers")
            self.draw_candidates(view)
        if look and view.rope_nodes_k3 is not None:
            self.look_at(view.rope_nodes_k3)

    def draw_rope(self, nodes_k3: np.ndarray) -> None:
        """The rope as a closed tube mesh."""
        nodes = np.asarray(nodes_k3)
        self.scene.add_mesh_simple(
            "/label/rope",
            tube_vertices(nodes, ROPE_RADIUS),
            tube_faces(len(nodes), 12),
            color=ROPE_COLOUR,
            flat_shading=False,
        )

    def look_at(self, nodes_k3: np.ndarray) -> None:
        """Point the camera at the rope from the front, above the table."""
        centre = np.asarray(nodes_k3).mean(axis=0)
        cam = self.client.camera
        cam.look_at = (float(centre[0]), float(centre[1]), 0.0)
        cam.position = (float(centre[0]), float(centre[1]) - 0.75, 0.65)

    @_serialised
    def draw_candidates(self, view: SessionView) -> None:
        """Every candidate's warped trajectories, markers and 3D label; selected one thicker."""
        self.scene.remove_by_name("/label/candidates")
        self._polylines = {}
        self._markers = {}
        for c in view.candidates:
            rank = c.ranked.rank
            rejected = rank in view.rejected
            colour = GREY if rejected else rank_colour(rank)
            selected = rank == view.selected
            base = f"/label/candidates/{rank}"
            lines = []
            for g in range(2):
                pts = c.positions_gt3[g]
                if not c.closed_gt[g].any():
                    continue  # this gripper stays idle in the demo
                lines.append(pts)
                segs = np.stack([pts[:-1], pts[1:]], axis=1).astype(np.float32)
                self.scene.add_line_segments(
                    f"{base}/path_{g}",
                    segs,
                    colour,
                    thickness=7.0 if selected else 3.0,
                    thickness_units="screen",
                )
            self._polylines[rank] = lines
            markers: list[tuple[np.ndarray, float]] = []
            self._markers[rank] = markers
            radius = 0.016 if selected else 0.011
            for i, p in enumerate(c.grasp_points):
                self.scene.add_icosphere(
                    f"{base}/grasp_{i}", radius=radius, color=colour, position=_xyz(p)
                )
                markers.append((np.asarray(p, dtype=np.float64), radius))
            for i, p in enumerate(c.release_points):
                self.scene.add_box(
                    f"{base}/release_{i}",
                    color=colour,
                    dimensions=(radius * 1.6,) * 3,
                    position=_xyz(p),
                )
                # The box picked as its circumscribed sphere (half-diagonal 1.39 x radius).
                markers.append((np.asarray(p, dtype=np.float64), radius * 0.8 * np.sqrt(3)))
            # Labels half-way along each path, stacked by rank: candidates often grasp the same
            # rope end, where their labels would overlap.
            active = [g for g in range(2) if c.closed_gt[g].any()] or [0]
            path = c.positions_gt3[active[0]]
            anchor = path[len(path) // 2]
            self.scene.add_label(
                f"{base}/label",
                candidate_label(c)
                + (" (dead end)" if rank in view.dead_ends else " (rejected)" if rejected else ""),
                position=(float(anchor[0]), float(anchor[1]), float(anchor[2]) + 0.035 * rank),
                font_screen_scale=1.2 if selected else 0.9,
            )
        self._drawn_ranks = [c.ranked.rank for c in view.candidates]

    @_serialised
    def show_warped(self, rank: int | None, cloud_n3: np.ndarray | None) -> None:
        """Show one candidate's demo cloud warped onto the scene (None hides it)."""
        self.scene.remove_by_name("/label/warped")
        if rank is None or cloud_n3 is None:
            return
        self.scene.add_point_cloud(
            "/label/warped",
            np.asarray(cloud_n3, dtype=np.float32),
            rank_colour(rank),
            point_size=0.008,
            point_shape="diamond",
            precision="float32",
        )

    # ------------------------------------------------------------------ picking
    def paths(self, rank: int) -> list[np.ndarray]:
        """The drawn path polylines of one candidate (one per gripper it uses)."""
        with self._lock:
            return list(self._polylines.get(rank, []))

    def pick(self, ray_origin_3: np.ndarray, ray_direction_3: np.ndarray) -> int | None:
        """The candidate rank a click along this ray selects (None: nothing within reach)."""
        with self._lock:  # a redraw replaces both dicts
            markers, polylines = self._markers, self._polylines
        return pick_candidate(
            np.asarray(ray_origin_3), np.asarray(ray_direction_3), markers, polylines
        )

    def _scene_click(self, event: viser.SceneClickEvent) -> None:
        # The only click handler: markers have none of their own (see pick_candidate).
        if event.client_id != self.client.client_id:
            return
        rank = self.pick(np.asarray(event.ray_origin), np.asarray(event.ray_direction))
        if rank is not None:
            self._on_pick(rank)

    # ------------------------------------------------------------------ animation
    def animate(
        self, recorder: FrameRecorder, rank: int, active_g: tuple[bool, bool] = (True, True)
    ) -> threading.Thread:
        """Play the recorder's frames as they arrive (PLAYBACK_SPEED x simulated time).

        Only the grippers the trajectory uses (``active_g``) are drawn; the cloud of the state
        before the try is hidden (it no longer describes the rope).
        """
        self.stop_animation()
        self.scene.remove_by_name("/label/cloud")
        self._anim_stop = threading.Event()
        stop = self._anim_stop
        self.first_frame_at = None
        colour = rank_colour(rank)

        def play() -> None:
            i, t_wall0 = 0, None
            while not stop.is_set():
                if i >= len(recorder):
                    if recorder.finished:
                        break
                    time.sleep(0.005)
                    continue
                t_sim, nodes, grippers, closed = recorder.frame(i)
                if t_wall0 is None:
                    t_wall0 = time.perf_counter() - t_sim / PLAYBACK_SPEED
                due = t_wall0 + t_sim / PLAYBACK_SPEED
                wait = due - time.perf_counter()
                if wait > 0:
                    stop.wait(wait)
                with self.client.atomic():
                    self.draw_rope(nodes)
                    for g, name in enumerate(("left", "right")):
                        if not active_g[g]:
                            continue
                        self.scene.add_icosphere(
                            f"/label/grippers/{name}",
                            radius=0.018 if closed[g] else 0.012,
                            color=colour if closed[g] else (60, 60, 60),
                            position=_xyz(grippers[g]),
                        )
                self.client.flush()
                if self.first_frame_at is None:
                    self.first_frame_at = time.perf_counter()
                i += 1

        thread = threading.Thread(target=play, name=f"animate-{self.client.client_id}", daemon=True)
        self._anim_thread = thread
        thread.start()
        return thread

    def stop_animation(self) -> None:
        """Stop a running animation (the next draw replaces its last frame)."""
        self._anim_stop.set()
        if self._anim_thread is not None and self._anim_thread is not threading.current_thread():
            self._anim_thread.join(timeout=2.0)
        self._anim_thread = None
