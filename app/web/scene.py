"""Draws one tab's session in its 3D scene: table, rope tube, cloud, ranked candidates, animation.

Scene paths: /table, and under /label (hidden while Inspect draws its own view): rope, cloud,
grippers/{left,right}, candidates/{rank}/{path_g,grasp_i,release_i,label}, warped.
"""

from __future__ import annotations

import contextlib
import functools
import json
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any, Literal, TypeVar

import numpy as np
import viser

from knotlab.app.web.frame_painter import (
    MAX_PAINT_HZ,
    FramePainter,
    GripperLook,
    next_frame_index,
)
from knotlab.app.web.geometry import frame_points, pick_candidate, tube_faces, tube_vertices
from knotlab.app.web.session_records import Candidate, Phase, SessionView
from knotlab.core.world.frames import FrameRecorder

ROPE_RADIUS = 0.01  # m, as the simulator's rope
ROPE_COLOUR = (196, 120, 60)
CLOUD_COLOUR = (40, 90, 200)
GREY = (170, 170, 170)
# Rank colours (1 = best): far from the rope's orange, the cloud's blue, the table and the
# rejected grey, and from each other (CIELAB distance; tests/app/web/test_scene.py). Orange and
# vermillion are left out: next to the rope they read as part of it.
RANK_COLOURS = (
    (0, 158, 115),  # bluish green
    (170, 51, 119),  # purple
    (86, 180, 233),  # sky blue
    (40, 40, 40),  # near black
    (240, 228, 66),  # yellow
    (204, 121, 167),  # pink
    (17, 119, 51),  # dark green
    (51, 34, 136),  # indigo
    (136, 34, 85),  # wine
)
# The labelling view looks from the front, 41 degrees above the table (x right, y away, z up).
VIEW_FORWARD = (0.0, 0.75, -0.65)
FRAME_MARGIN_PX = 24  # what framing keeps clear at the canvas's edges
TEXT_PX_PER_CHAR = 9.0  # about, for a 3D caption at the scales drawn (measured on screenshots)
TEXT_PX_HIGH = 24.0  # a caption's height
# viser's "large" control panel floats over the canvas's right side: 24 em of 16 px, 16 px from
# the window's edge. Framing keeps the content left of it (on a canvas wide enough for both).
PANEL_PX = 24 * 16 + 16
WARPED_POINT_SIZE = 1.4 * ROPE_RADIUS  # m: the warped demo cloud's points, wider than the rope
WARPED_LIFT = ROPE_RADIUS  # m: and drawn on the rope's top, not inside it
PLAYBACK_SPEED = 2.0  # animation runs at twice simulated time: a 6 s execution plays in 3 s
MODEL_SPEED = 6.0  # the model's own steps are fast-forwarded: a 6 s execution plays in 1 s


CAPTION_LIFT_M = 0.045  # the selected caption over the highest path; badges sit 0.015 over theirs
SceneView = Literal["label", "inspect", "playback"]  # what a tab's 3D view shows


def rank_colour(rank: int) -> tuple[int, int, int]:
    """The colour of a candidate rank (1-based), cycling after nine."""
    return RANK_COLOURS[(rank - 1) % len(RANK_COLOURS)]


def candidate_label(c: Candidate) -> str:
    """The 3D label and list text of a candidate: rank, demo, its step, Q, cost."""
    score = f"Q {c.ranked.q:.2f}" if c.ranked.q is not None else "NN"
    return f"#{c.ranked.rank} {c.ranked.demo_key} · step {c.demo_step + 1} · {score}"


def badge_text(c: Candidate, view: SessionView) -> str:
    """The 3D text of a candidate: the full caption for the selected one, a rank badge for the
    rest (five full captions overlap one another), with how it was judged."""
    rank = c.ranked.rank
    verdict = (
        " (dead end)"
        if rank in view.dead_ends
        else " (the model's, failed)"
        if rank == view.model_failed
        else " (rejected)"
        if rank in view.rejected
        else ""
    )
    return (candidate_label(c) if rank == view.selected else f"#{rank}") + verdict


def drawn_candidates(view: SessionView) -> list[Candidate]:
    """The candidates the scene shows: all while choosing; during and after a try only the
    tried one (the others' paths would hide what it did)."""
    if view.phase in (Phase.TRYING, Phase.JUDGING):
        tried = view.last_try.rank if view.last_try is not None else view.selected
        return [c for c in view.candidates if c.ranked.rank == tried]
    return list(view.candidates)


def label_anchor(c: Candidate, view: SessionView) -> np.ndarray:
    """Where a candidate's 3D text sits: the selected caption above its path's highest point,
    the badges spread along their paths by rank so that they do not stack up."""
    path = _labelled_path(c)
    if c.ranked.rank == view.selected:
        # Over its own path's highest point, but above every candidate's path: the badges sit
        # on theirs, and one under the caption would be written over it.
        top = path[int(np.argmax(path[:, 2]))]
        highest = max(float(_labelled_path(o)[:, 2].max()) for o in view.candidates)
        return np.array([top[0], top[1], max(float(top[2]), highest) + CAPTION_LIFT_M])
    n = max(len(view.candidates) - 1, 1)
    at = 0.25 + 0.5 * (c.ranked.rank - 1) / n
    return path[min(int(at * len(path)), len(path) - 1)] + (0.0, 0.0, 0.015)


def _labelled_path(c: Candidate) -> np.ndarray:
    """The path a candidate's text goes with: its first moving gripper's."""
    active = [g for g in range(2) if c.closed_gt[g].any()] or [0]
    return np.asarray(c.positions_gt3[active[0]], dtype=np.float64)


def framed_points(view: SessionView) -> tuple[np.ndarray, np.ndarray]:
    """What a new state's camera must show: the rope, every candidate's paths, markers and
    3D text (as a badge and as the selected caption); and per point the width (px) of the text
    that starts at it (0: none)."""
    parts: list[np.ndarray] = []
    text_px: list[float] = []
    if view.rope_nodes_k3 is not None:
        parts.append(np.asarray(view.rope_nodes_k3, dtype=np.float64))
    for c in view.candidates:
        for g in range(2):
            if c.closed_gt[g].any():
                parts.append(np.asarray(c.positions_gt3[g], dtype=np.float64)[::2])
        parts += [np.asarray(p, dtype=np.float64)[None] for p in c.grasp_points]
        parts += [np.asarray(p, dtype=np.float64)[None] for p in c.release_points]
        text_px += [0.0] * (sum(len(x) for x in parts) - len(text_px))
        # Its text both as a badge and as the selected caption: a click selects another
        # candidate without moving the camera, and its caption must still be in view.
        for as_shown in (replace(view, selected=c.ranked.rank), replace(view, selected=None)):
            parts.append(label_anchor(c, as_shown)[None])
            text_px.append(TEXT_PX_PER_CHAR * len(badge_text(c, as_shown)))
    if not parts:
        return np.zeros((0, 3)), np.zeros(0)
    text_px += [0.0] * (sum(len(x) for x in parts) - len(text_px))
    return np.concatenate(parts), np.asarray(text_px)


def free_box(
    width: int, height: int, pixel_ratio: float = 1.0
) -> tuple[float, float, float, float]:
    """The canvas pixels (left, top, right, bottom) the side panel leaves free, less a margin.

    The browser reports its canvas in device pixels (CSS pixels x ``pixel_ratio``, 2 on a
    high-density screen) while the panel and the margin are sized in CSS pixels."""
    panel, m = PANEL_PX * pixel_ratio, FRAME_MARGIN_PX * pixel_ratio
    right = width - panel if width >= 2 * panel else width
    return (m, m, right - m, height - m)


@dataclass(frozen=True)
class BrowserScale:
    """What a page says of its window: device pixels per CSS pixel, and its CSS size."""

    device_ratio: float = 1.0
    css_width: float = 0.0  # 0: not known
    css_height: float = 0.0

    def ratio_for(self, width: int, height: int) -> float:
        """Image pixels per CSS pixel of a canvas the browser reports as ``width`` x ``height``.

        viser renders at a lower resolution while frames are slow (down to 0.75 of the
        device's: software WebGL, a busy machine) and reports the canvas it renders, so the
        reported size, not the device's ratio, says how many of its pixels the CSS-sized panel
        and text take. A window resized since it was measured falls back to the device's.
        """
        if self.css_width > 0 and self.css_height > 0:
            rx, ry = width / self.css_width, height / self.css_height
            if abs(rx - ry) <= 0.02 * max(rx, ry):
                return rx
        return self.device_ratio


def camera_pose(
    points_p3: np.ndarray,
    text_px: np.ndarray | None,
    size: tuple[int, int],
    ratio: float,
    up: np.ndarray,
    fov: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(position, look_at) of the front camera that shows ``points_p3`` as close as they fit,
    left of the panel, on a canvas of ``size`` rendered pixels at ``ratio`` of them per CSS
    pixel (each point's text, ``text_px`` CSS pixels wide, clear of the panel too)."""
    width, height = size
    box = np.tile(np.asarray(free_box(width, height, ratio), dtype=np.float64), (len(points_p3), 1))
    if text_px is not None:
        box[:, 2] -= text_px * ratio
        box[:, 1] += np.where(text_px > 0, TEXT_PX_HIGH * ratio, 0.0)
    return frame_points(points_p3, np.asarray(VIEW_FORWARD), up, fov, (width, height), box)


def browser_scale_of(client: viser.ClientHandle, timeout: float = 3.0) -> BrowserScale:
    """The browser's device pixel ratio and window size in CSS pixels (1.0 and unknown if it
    does not say within ``timeout`` s).

    viser reports the canvas size in rendered pixels but has no call for the ratio, so the page
    is asked to put it in its local storage (viser's message for running a script: the one it
    loads plotly with), which is then read back as any stored item; messages arrive in order."""
    from viser import _messages  # private: viser has no public call for this message

    # viser keeps a server's items under the "viser-user:" prefix in the page's local storage.
    script = (
        "localStorage.setItem('viser-user:knotlab.pixel_ratio', JSON.stringify("
        "[window.devicePixelRatio || 1, window.innerWidth, window.innerHeight]))"
    )
    try:
        client._websock_connection.queue_message(_messages.RunJavascriptMessage(source=script))
        value = client.local_storage.get_item("knotlab.pixel_ratio", timeout=timeout)
        ratio, css_w, css_h = (float(x) for x in json.loads(value or "null"))
    except (RuntimeError, TimeoutError, ValueError, TypeError, AttributeError):
        return BrowserScale()
    if not 0.5 <= ratio <= 8.0:
        return BrowserScale()
    if not (css_w > 0 and css_h > 0):
        css_w = css_h = 0.0
    return BrowserScale(ratio, css_w, css_h)


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


TABLE_SIZE = (1.6, 1.2)  # metres, centred on the origin
GRID_CELL = 0.1  # metres between grid lines


def grid_segments(width: float, height: float, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """A grid's lines on z = 0 as (n, 2, 3) segments: (cell lines, the two centre lines)."""
    half_w, half_h = width / 2, height / 2
    nx, ny = int(np.floor(half_w / cell + 1e-9)), int(np.floor(half_h / cell + 1e-9))
    xs = [k * cell for k in range(-nx, nx + 1) if k != 0]
    ys = [k * cell for k in range(-ny, ny + 1) if k != 0]
    cells = [((x, -half_h, 0.0), (x, half_h, 0.0)) for x in xs]
    cells += [((-half_w, y, 0.0), (half_w, y, 0.0)) for y in ys]
    centre = [((0.0, -half_h, 0.0), (0.0, half_h, 0.0)), ((-half_w, 0.0, 0.0), (half_w, 0.0, 0.0))]
    return np.asarray(cells, dtype=np.float32), np.asarray(centre, dtype=np.float32)


def add_table(scene: viser.SceneApi, *, lite: bool) -> list[Any]:
    """The table and its 10 cm grid (``lite``: drawn cheaply for software WebGL); their handles.

    The table and the grid fill most of the view. In software WebGL (a headless browser, a
    machine without a GPU) the table's physically based material and the grid's per-pixel shader
    cost about a third of every frame, so a lite scene draws the table in a toon material and the
    grid as plain line segments (the same lines, the same colours).
    """
    width, height = TABLE_SIZE
    table = scene.add_box(
        "/table",
        color=(225, 222, 212),
        dimensions=(width, height, 0.02),
        position=(0, 0, -0.011),
        material="toon3" if lite else "standard",
        receive_shadow=not lite,
    )
    if not lite:
        grid = scene.add_grid(
            "/grid", width=width, height=height, cell_size=GRID_CELL, position=(0, 0, 0.0005)
        )
        return [table, grid]
    cells, centre = grid_segments(width, height, GRID_CELL)
    return [
        table,
        scene.add_frame("/grid", show_axes=False, position=(0, 0, 0.0005)),
        scene.add_line_segments(
            "/grid/cells", cells, (200, 200, 200), thickness=1.0, thickness_units="screen"
        ),
        scene.add_line_segments(
            "/grid/centre", centre, (140, 140, 140), thickness=1.0, thickness_units="screen"
        ),
    ]


class SceneDrawer:
    """One client's scene: draws a SessionView and plays try animations."""

    def __init__(
        self, client: viser.ClientHandle, on_pick: Callable[[int], None], *, lite: bool = False
    ) -> None:
        """``lite``: drawn for software WebGL (cheaper table material, grid as plain lines)."""
        self.client = client
        self.scene = client.scene
        self._on_pick = on_pick
        self._polylines: dict[int, list[np.ndarray]] = {}
        self._markers: dict[int, list[tuple[np.ndarray, float]]] = {}
        self._drawn_ranks: list[int] = []
        self._framed_nodes: np.ndarray | None = None  # the rope the camera last framed
        self._lock = threading.RLock()  # one redraw at a time (see _serialised)
        self._anim_stop = threading.Event()
        self._anim_thread: threading.Thread | None = None
        self.first_frame_at: float | None = None  # perf_counter of the last try's first frame
        add_table(self.scene, lite=lite)
        self.label_root = self.scene.add_frame("/label", show_axes=False)
        self.browser = BrowserScale()  # the page's pixel ratio and size (see free_box)
        self.showing: SceneView = "label"
        self.scene.on_click()(self._scene_click)

    @contextlib.contextmanager
    def drawing(self, view: SceneView, *, enter: bool = False) -> Iterator[bool]:
        """Hold the scene to draw into ``view`` (shown first if ``enter``); yields whether it is
        on screen. A slow drawer (a loading Inspect) checks it here, under the lock that
        ``show_only`` takes, so it never draws into a view the user has left."""
        with self._lock:
            if enter:
                self.show_only(view)
            yield self.showing == view

    @_serialised
    def show_only(self, view: SceneView) -> None:
        """Show one of the tab's 3D views: the labelling one (hidden, kept, while another
        shows), Inspect's state (/inspect) or a playback (/playback); the other two go."""
        self.showing = view
        self.label_root.visible = view == "label"
        if view != "inspect":
            self.scene.remove_by_name("/inspect")
        if view != "playback":
            self.scene.remove_by_name("/playback")

    # ------------------------------------------------------------------ state
    @_serialised
    def draw(self, view: SessionView, *, look: bool = False, show_warped: bool = False) -> None:
        """Draw the rope, cloud and candidates of ``view``; a new state (another rope) is framed,
        and ``look`` frames it again."""
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
        nodes = view.rope_nodes_k3
        if nodes is not None and (
            look or self._framed_nodes is None or not np.array_equal(nodes, self._framed_nodes)
        ):
            self.frame(view)

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

    def frame(self, view: SessionView) -> None:
        """Point the camera from the front, above the table, as close as it can be while the
        rope and every candidate's paths, markers and text are in view, left of the panel."""
        points, text_px = framed_points(view)
        if not len(points):
            return
        self._framed_nodes = view.rope_nodes_k3
        self.frame_points(points, text_px)

    def frame_points(self, points_p3: np.ndarray, text_px: np.ndarray | None = None) -> None:
        """Point the camera from the front, above the table, at these points (left of the
        panel, as close as they all fit); a point where text starts keeps the text's width
        (px, per point) clear of the panel too (viser draws a label rightwards from its
        anchor)."""
        cam = self.client.camera
        width, height = cam.image_width, cam.image_height
        if width <= 0 or height <= 0:
            return  # the browser has not reported its canvas yet
        up = np.asarray(cam.up_direction, dtype=np.float64)
        if not np.linalg.norm(up):
            up = np.array([0.0, 0.0, 1.0])
        ratio = self.browser.ratio_for(width, height)
        position, look_at = camera_pose(points_p3, text_px, (width, height), ratio, up, cam.fov)
        # Position first: viser moves the look-at point along with the position, so the
        # look-at point set second is the one that stays (the other order depends on where
        # the camera was, and a new tab's camera starts elsewhere).
        cam.position = position
        cam.look_at = look_at

    @_serialised
    def draw_candidates(self, view: SessionView) -> None:
        """The candidates' warped paths, markers and 3D text (the selected one thicker, with
        its full caption; the others with rank badges); during and after a try, the tried one."""
        self.scene.remove_by_name("/label/candidates")
        self._polylines = {}
        self._markers = {}
        shown = drawn_candidates(view)
        for c in shown:
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
            self.scene.add_label(
                f"{base}/label",
                badge_text(c, view),
                position=_xyz(label_anchor(c, view)),
                font_screen_scale=1.1 if selected else 0.9,
            )
        self._drawn_ranks = [c.ranked.rank for c in shown]

    @_serialised
    def show_warped(self, rank: int | None, cloud_n3: np.ndarray | None) -> None:
        """Show one candidate's demo cloud warped onto the scene (None hides it)."""
        self.scene.remove_by_name("/label/warped")
        if rank is None or cloud_n3 is None:
            return
        # Its points lie on the rope's surface: drawn wider than the rope (and above it) so
        # the tube does not hide them.
        self.scene.add_point_cloud(
            "/label/warped",
            np.asarray(cloud_n3, dtype=np.float32) + np.array([0.0, 0.0, WARPED_LIFT], np.float32),
            rank_colour(rank),
            point_size=WARPED_POINT_SIZE,
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
        self,
        recorder: FrameRecorder,
        cand: Candidate,
        rope_nodes_k3: np.ndarray | None,
        speed: float = PLAYBACK_SPEED,
    ) -> threading.Thread:
        """Play the recorder's frames of ``cand``'s execution as they arrive (``speed`` x
        simulated time).

        Only the grippers the trajectory uses are drawn; the cloud of the state before the try
        is hidden (it no longer describes the rope). The rope as shown (``rope_nodes_k3``) with
        the used grippers open at the path's first point is drawn at once: the moment before
        the first grasp, shown while the simulation waits for a free worker.
        """
        active_g = (bool(cand.closed_gt[0].any()), bool(cand.closed_gt[1].any()))
        self.stop_animation()
        self.scene.remove_by_name("/label/cloud")
        self._anim_stop = threading.Event()
        stop = self._anim_stop
        self.first_frame_at = None
        colour = rank_colour(cand.ranked.rank)

        painter = FramePainter(
            self.client,
            "/label",
            rope_radius=ROPE_RADIUS,
            rope_colour=ROPE_COLOUR,
            look=GripperLook(colour),
            active_g=active_g,
        )

        last_start = 0.0
        if rope_nodes_k3 is not None:
            painter.paint(rope_nodes_k3, cand.positions_gt3[:, 0], np.zeros(2, dtype=bool))
            self.client.flush()
            last_start = time.perf_counter()

        def play() -> None:
            i, t_wall0, last_paint = -1, 0.0, last_start  # i: the frame last painted
            while not stop.is_set():
                n = len(recorder)
                if i + 1 >= n:
                    if recorder.finished:
                        break
                    recorder.wait_for_frame(i + 1, 0.1)  # woken by the frame (or the end)
                    continue
                if i < 0:
                    t_wall0 = time.perf_counter() - recorder.frame(0)[0] / speed
                i = next_frame_index(
                    lambda k: recorder.frame(k)[0], i, n, t_wall0, speed, time.perf_counter()
                )
                t_sim, nodes, grippers, closed = recorder.frame(i)
                due = max(t_wall0 + t_sim / speed, last_paint + 1.0 / MAX_PAINT_HZ)
                wait = due - time.perf_counter()
                if wait > 0:
                    stop.wait(wait)
                painter.paint(nodes, grippers, closed)
                self.client.flush()
                last_paint = time.perf_counter()
                if self.first_frame_at is None:
                    self.first_frame_at = last_paint

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
