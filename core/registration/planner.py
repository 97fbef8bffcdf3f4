"""Turn a chosen demo into an executable trajectory for the current scene (trajectory transfer).

The library scan ranks demos with the cheap ``SCAN`` schedule; the chosen demo is registered
again with the ``EXACT`` schedule and its gripper trajectory warped through that f (paper
section II; docs/reference/registration.md, 'Trajectory transfer').
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from knotlab.core.arrays import cloud_digest
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import KnotlabError
from knotlab.core.failures import FailureKind
from knotlab.core.registration import EXACT, Registration, RegistrationParams
from knotlab.core.registration.rpm import register_sides
from knotlab.core.registration.sides import CloudSide, one_demo_side, scene_side
from knotlab.core.registration.transfer import warp_trajectory
from knotlab.core.world.trajectory import GripperTrajectory

# Warped waypoints are clipped into the reachable box above the table: a warp that pushes a
# waypoint into the table (or absurdly high) is a transfer artefact, not an intention.
MIN_HEIGHT_M = 0.01
MAX_HEIGHT_M = 0.8
_SCENE_SIDES = 16  # scenes whose factorised side a transferer keeps (a search's states)


@dataclass(frozen=True, eq=False)
class TransferPlan:
    """A demo transferred onto a scene: the warped trajectory, or why there is none."""

    demo_index: int
    trajectory: GripperTrajectory | None
    registration: Registration | None
    failure: str | None = None
    timings: dict = field(default_factory=dict)

    @property
    def failure_kind(self) -> FailureKind | None:
        """REGISTRATION when registration or warping failed, else None."""
        return None if self.failure is None else FailureKind.REGISTRATION

    @property
    def ok(self) -> bool:
        """True when there is a trajectory to execute."""
        return self.trajectory is not None


class DemoTransferer:
    """Registers one library demo onto a scene cloud and warps its gripper trajectory."""

    def __init__(self, library: DemoLibrary, params: RegistrationParams = EXACT) -> None:
        self.library = library
        self.params = params
        # Factorised sides (two TPS bases, ~30 ms a transfer): a demo's is fixed, and a search
        # transfers several demos onto the same scene. Pure functions of their clouds, so a
        # cached side gives the very same registration (bit for bit).
        self._demo_sides: dict[int, CloudSide] = {}
        self._scene_sides: OrderedDict[str, CloudSide] = OrderedDict()
        self._lock = threading.Lock()

    def _sides(self, cloud_n3: np.ndarray, demo_index: int) -> tuple[CloudSide, CloudSide]:
        """The demo's and the scene's factorised sides (cached; a failure raises each time)."""
        with self._lock:
            demo = self._demo_sides.get(demo_index)
        if demo is None:
            demo = one_demo_side(self.library[demo_index].pre_cloud_n3, self.params)
            with self._lock:
                self._demo_sides[demo_index] = demo
        key = cloud_digest(cloud_n3)
        with self._lock:
            scene = self._scene_sides.get(key)
            if scene is not None:
                self._scene_sides.move_to_end(key)
        if scene is None:
            scene = scene_side(cloud_n3, self.params)
            with self._lock:
                self._scene_sides[key] = scene
                while len(self._scene_sides) > _SCENE_SIDES:
                    self._scene_sides.popitem(last=False)
        return demo, scene

    def plan(self, cloud_n3: np.ndarray, demo_index: int) -> TransferPlan:
        """Exact registration of demo ``demo_index`` onto the cloud, then warp; never raises."""
        seg = self.library[demo_index]
        t0 = time.perf_counter()
        try:
            reg = register_sides(*self._sides(cloud_n3, demo_index), self.params)
        except (KnotlabError, np.linalg.LinAlgError, FloatingPointError) as exc:
            return TransferPlan(demo_index, None, None, f"registration: {exc}")
        t1 = time.perf_counter()
        timings = {"register_s": t1 - t0}
        if not reg.ok:
            return TransferPlan(demo_index, None, reg, f"registration: {reg.reason}", timings)
        try:
            warped = warp_trajectory(seg.trajectory, reg.f)
        except (KnotlabError, np.linalg.LinAlgError, FloatingPointError) as exc:
            return TransferPlan(demo_index, None, reg, f"warp: {exc}", timings)
        pos = warped.positions_gt3.copy()
        pos[..., 2] = np.clip(pos[..., 2], MIN_HEIGHT_M, MAX_HEIGHT_M)
        traj = warped.with_positions(pos, warped.rotations_gt33)
        timings["warp_s"] = time.perf_counter() - t1
        return TransferPlan(demo_index, traj, reg, None, timings)
