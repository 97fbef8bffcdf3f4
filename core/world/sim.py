"""RopeWorld: a PyBullet rope (capsule chain) on a table, moved by two kinematic point grippers.

Frames: metres and seconds, right-handed, z up, table top at z = 0.
Shape suffixes: l = rope links (capsules), k = rope nodes (l + 1 capsule end points),
g = grippers (left, right), n = cloud points, 3/4 = xyz/quaternion xyzw.

Model (docs/reference/rope_world.md, 'Rope model'): N separate rigid capsules joined end to end
by point-to-point constraints; neighbours do not collide, every other pair does. A gripper is a
point-to-point constraint from the grasped link to the world whose pivot follows the gripper.

Determinism: every stepping call (``execute``, ``settle``) first rebuilds the PyBullet world from a
plain state record (poses and velocities of every link). A snapshot is that record, so
restore-then-execute rebuilds from exactly the same numbers as the uninterrupted run and is
bit-identical to it; snapshots are also picklable and portable between worlds and processes.
"""

from __future__ import annotations

import itertools
import math
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import ModuleType

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.failures import FailureKind
from knotlab.core.world.frames import ExecutionFrames, FrameRecorder
from knotlab.core.world.observation import surface_cloud
from knotlab.core.world.rope import as_nodes, resample_by_arc_length, rope_length
from knotlab.core.world.trajectory import GRIPPERS, GripperTrajectory


def _import_pybullet_quietly() -> ModuleType:
    """Import pybullet with its C-level "build time" banner sent to /dev/null.

    The banner is printed by the extension's init straight to the process's stdout/stderr file
    descriptors, so Python-level redirection cannot catch it: descriptors 1 and 2 are swapped for
    the import, and C's stdio buffers are flushed (into /dev/null) before they are swapped back.
    An import error is raised after the swap back, so it is still seen.
    """
    import ctypes
    import os
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(devnull, fd)
        import pybullet

        ctypes.CDLL(None).fflush(None)
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
        os.close(devnull)
    return pybullet


p = _import_pybullet_quietly()


@dataclass(frozen=True)
class RopeParams:
    """Every physical and numerical setting of the rope and the solver."""

    n_links: int = 40
    length: float = 1.0  # m
    radius: float = 0.01  # m
    mass: float = 0.2  # kg, whole rope
    friction: float = 0.8  # lateral, of the rope (and of the table unless table_friction is set)
    # The table's own lateral friction; None: the rope's. PyBullet multiplies the two bodies'
    # coefficients, so rope-on-table friction is friction * table_friction and rope-on-rope is
    # friction ** 2: the two can be changed apart (core/world/mismatch.py does).
    table_friction: float | None = None
    linear_damping: float = 0.5
    angular_damping: float = 0.5
    joint_max_force: float = 1000.0  # N, link-to-link p2p constraints
    joint_erp: float = 0.8
    timestep: float = 1.0 / 240.0  # s
    solver_iterations: int = 20
    gravity: float = 9.81  # m/s^2
    # Accepted mismatch between the given rope's arc length and `length` (fraction).
    length_tolerance: float = 0.1
    # Blow-up detection: any link faster than this (m/s) or joints gaping more than
    # `stretch_limit` link lengths ends an execution (peaks in normal use: ~0.5 m/s, 13 %).
    explode_speed: float = 20.0
    stretch_limit: float = 0.5
    check_every: int = 4  # steps between blow-up / stretch checks

    def __post_init__(self) -> None:
        if int(self.n_links) != self.n_links or self.n_links < 2:
            raise InvalidInputError(
                f"RopeParams.n_links must be an integer >= 2, got {self.n_links}"
            )
        for name in ("length", "radius", "mass", "timestep", "joint_max_force", "explode_speed"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InvalidInputError(f"RopeParams.{name} must be positive, got {value}")
        if self.table_friction is not None and not (
            np.isfinite(self.table_friction) and self.table_friction >= 0
        ):
            raise InvalidInputError(
                f"RopeParams.table_friction must be >= 0 (or None), got {self.table_friction}"
            )
        if 2 * self.radius > self.link_length:
            raise InvalidInputError(
                f"RopeParams: diameter {2 * self.radius} exceeds link length {self.link_length}"
            )
        if self.solver_iterations < 1 or self.check_every < 1:
            raise InvalidInputError("RopeParams: solver_iterations and check_every must be >= 1")

    @property
    def link_length(self) -> float:
        """Length of one capsule link (m)."""
        return self.length / self.n_links


@dataclass(frozen=True)
class GripperParams:
    """Point-gripper settings: grasp reach, speed caps, grip force, settling after a trajectory."""

    grasp_radius: float = 0.03  # m, from gripper point to a link's axis
    max_speed: float = 0.5  # m/s, 3-D speed cap of each gripper point
    max_descent_speed: float = 0.25  # m/s, cap on downward speed (lowering is done gently)
    grip_force: float = 30.0  # N, max force of the gripper constraint
    settle_time: float = 1.0  # s after both grippers release at the end of `execute`
    rest_speed: float = 0.005  # m/s: settling stops early once every link is slower than this

    def __post_init__(self) -> None:
        for name in ("grasp_radius", "max_speed", "max_descent_speed", "grip_force"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InvalidInputError(f"GripperParams.{name} must be positive, got {value}")
        if self.settle_time < 0 or self.rest_speed < 0:
            raise InvalidInputError("GripperParams: settle_time and rest_speed must be >= 0")


# Where an execution's time goes: building the PyBullet world from the state record, moving
# with no rope held (approach, lowering, lifting away), dragging with at least one gripper
# holding a link, and settling after the release.
EXECUTION_PHASES = ("rebuild", "approach", "drag", "settle")


@dataclass(frozen=True)
class ExecutionResult:
    """Outcome of one `RopeWorld.execute` call."""

    ok: bool
    failure: str | None  # "misgrasp:left", "exploded", "stretch", or None
    misgrasps: tuple[str, ...]  # gripper name per close that found no link
    grasps: tuple[tuple[str, int], ...]  # (gripper, link index) per successful close
    max_stretch: float  # largest joint gap seen, as a fraction of the link length
    sim_steps: int
    sim_time: float  # s simulated
    wall_time: float = field(default=0.0, compare=False)  # s of wall clock
    frames: ExecutionFrames | None = field(default=None, compare=False)  # when asked for
    # Wall seconds and simulator steps per phase (`EXECUTION_PHASES`), for the speed benches.
    phase_s: dict[str, float] = field(default_factory=dict, compare=False)
    phase_steps: dict[str, int] = field(default_factory=dict, compare=False)

    @property
    def failure_kind(self) -> FailureKind | None:
        """The kind of ``failure``: EXPLODED (explosion or over-stretch), MISGRASP, or None."""
        if self.failure is None:
            return None
        if self.failure in ("exploded", "stretch"):
            return FailureKind.EXPLODED
        return FailureKind.MISGRASP


@dataclass(frozen=True, eq=False)
class SimSnapshot:
    """Full dynamic state of the rope: enough to rebuild the world bit-for-bit."""

    positions_l3: np.ndarray
    quaternions_l4: np.ndarray  # xyzw
    linear_velocities_l3: np.ndarray
    angular_velocities_l3: np.ndarray
    sim_time: float
    params: RopeParams

    def equals(self, other: SimSnapshot) -> bool:
        """Exact equality of every array and the parameters."""
        return (
            self.params == other.params
            and self.sim_time == other.sim_time
            and all(
                np.array_equal(getattr(self, f), getattr(other, f))
                for f in (
                    "positions_l3",
                    "quaternions_l4",
                    "linear_velocities_l3",
                    "angular_velocities_l3",
                )
            )
        )


def _quat_z_to(dirs_l3: np.ndarray) -> np.ndarray:
    """Shortest-arc xyzw quaternions rotating +z onto each unit direction."""
    cos = np.clip(dirs_l3[:, 2], -1.0, 1.0)
    axis = np.stack([-dirs_l3[:, 1], dirs_l3[:, 0], np.zeros(len(dirs_l3))], axis=1)
    norm = np.linalg.norm(axis, axis=1)
    # Straight down has no unique axis: flip about x.
    axis = np.where(norm[:, None] > 1e-12, axis / np.maximum(norm, 1e-300)[:, None], [1.0, 0, 0])
    half = 0.5 * np.arccos(cos)
    return np.concatenate([axis * np.sin(half)[:, None], np.cos(half)[:, None]], axis=1)


def _quat_z_axes(quats_l4: np.ndarray) -> np.ndarray:
    """The third column of `observation._quat_to_axes` (each link's axis), (L, 3), same arithmetic.

    The health check runs every few simulator steps and needs only the axes; building the full
    matrices there took a sixth of an execution's wall time.
    """
    x, y, z, w = quats_l4[:, 0], quats_l4[:, 1], quats_l4[:, 2], quats_l4[:, 3]
    out = np.empty((len(quats_l4), 3))
    out[:, 0] = 2 * (x * z + y * w)
    out[:, 1] = 2 * (y * z - x * w)
    out[:, 2] = 1 - 2 * (x * x + y * y)
    return out


def _link_ends(state: SimSnapshot) -> tuple[np.ndarray, np.ndarray]:
    """World positions of each link's lower (-z) and upper (+z) pivot, (L, 3) each."""
    half = 0.5 * state.params.link_length
    axis_l3 = _quat_z_axes(state.quaternions_l4)
    return state.positions_l3 - half * axis_l3, state.positions_l3 + half * axis_l3


def _nodes_of(state: SimSnapshot) -> np.ndarray:
    """Rope nodes (L + 1, 3) of a state: the two free ends and the averaged joints."""
    lower_l3, upper_l3 = _link_ends(state)
    joints = 0.5 * (upper_l3[:-1] + lower_l3[1:])
    return np.concatenate([lower_l3[:1], joints, upper_l3[-1:]], axis=0)


def _point_segment_distance(q_3: np.ndarray, a_l3: np.ndarray, b_l3: np.ndarray) -> np.ndarray:
    """Distance from point q to each segment [a_l, b_l]."""
    d = b_l3 - a_l3
    t = np.clip(np.einsum("li,li->l", q_3 - a_l3, d) / np.einsum("li,li->l", d, d), 0.0, 1.0)
    return np.linalg.norm(a_l3 + t[:, None] * d - q_3, axis=1)


def _disconnect(client: int, alive: list[bool]) -> None:
    if alive[0]:
        alive[0] = False
        p.disconnect(physicsClientId=client)


class RopeWorld:
    """A table, one rope and two point grippers in a private PyBullet DIRECT client."""

    def __init__(
        self, params: RopeParams | None = None, gripper: GripperParams | None = None
    ) -> None:
        self.params = params if params is not None else RopeParams()
        self.gripper = gripper if gripper is not None else GripperParams()
        self._client = p.connect(p.DIRECT)
        if self._client < 0:
            raise RuntimeError("pybullet could not open a DIRECT physics client")
        self._alive = [True]
        # Disconnect even if the user forgets close(): a leaked client keeps its memory.
        self._finalizer = weakref.finalize(self, _disconnect, self._client, self._alive)
        self._links: list[int] = []
        self._pending: SimSnapshot | None = None
        self._broken: str | None = None
        self.reset(self._straight_nodes())

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Disconnect the physics client; the world cannot be used afterwards."""
        self._finalizer()

    def __enter__(self) -> RopeWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _require_open(self) -> None:
        if not self._alive[0]:
            raise InvalidInputError("RopeWorld is closed")

    # ------------------------------------------------------------------ state
    def _straight_nodes(self) -> np.ndarray:
        nodes = np.zeros((self.params.n_links + 1, 3))
        nodes[:, 0] = np.linspace(-self.params.length / 2, self.params.length / 2, len(nodes))
        nodes[:, 2] = self.params.radius
        return nodes

    def _check_nodes(self, rope_nodes_k3: np.ndarray) -> np.ndarray:
        prm = self.params
        nodes = as_nodes(rope_nodes_k3, min_nodes=3)
        length = rope_length(nodes)
        if abs(length - prm.length) > prm.length_tolerance * prm.length:
            raise InvalidInputError(
                f"rope nodes span {length:.4f} m of arc length but RopeParams.length is "
                f"{prm.length} m (+-{prm.length_tolerance:.0%}): wrong scale or units?"
            )
        if nodes.shape[0] == prm.n_links + 1:
            seg_m = np.linalg.norm(np.diff(nodes, axis=0), axis=1)
            worst = int(np.argmax(seg_m))
            if seg_m[worst] > 1.25 * prm.link_length:
                raise InvalidInputError(
                    f"rope segment {worst} is {seg_m[worst]:.4f} m long; links are "
                    f"{prm.link_length:.4f} m (at most 25 % stretch allowed)"
                )
        if nodes[:, 2].min() < -0.05:
            raise InvalidInputError(
                f"rope nodes reach z = {nodes[:, 2].min():.3f} m, below the table top at z = 0"
            )
        return nodes

    def reset(self, rope_nodes_k3: np.ndarray) -> None:
        """Place the rope at rest along the given polyline (any K >= 3, resampled by arc length)."""
        self._require_open()
        prm = self.params
        nodes = resample_by_arc_length(self._check_nodes(rope_nodes_k3), prm.n_links + 1)
        # The rope rests on the table: centre lines below one radius would start inside it.
        nodes[:, 2] = np.maximum(nodes[:, 2], prm.radius)
        seg_l3 = np.diff(nodes, axis=0)
        dirs_l3 = seg_l3 / np.linalg.norm(seg_l3, axis=1, keepdims=True)
        n = prm.n_links
        self._pending = SimSnapshot(
            positions_l3=0.5 * (nodes[:-1] + nodes[1:]),
            quaternions_l4=_quat_z_to(dirs_l3),
            linear_velocities_l3=np.zeros((n, 3)),
            angular_velocities_l3=np.zeros((n, 3)),
            sim_time=0.0,
            params=prm,
        )
        self._broken = None

    def _read_state(self) -> SimSnapshot:
        cid = self._client
        pos, quat, lin, ang = [], [], [], []
        for body in self._links:
            xyz, q = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            v, w = p.getBaseVelocity(body, physicsClientId=cid)
            pos.append(xyz)
            quat.append(q)
            lin.append(v)
            ang.append(w)
        return SimSnapshot(
            positions_l3=np.array(pos),
            quaternions_l4=np.array(quat),
            linear_velocities_l3=np.array(lin),
            angular_velocities_l3=np.array(ang),
            sim_time=self._sim_time,
            params=self.params,
        )

    def _state(self) -> SimSnapshot:
        self._require_open()
        return self._pending if self._pending is not None else self._read_state()

    def snapshot(self) -> SimSnapshot:
        """The current full state (a plain, picklable record)."""
        return self._state()

    def restore(self, snapshot: SimSnapshot) -> None:
        """Return to a snapshot; what follows is bit-identical to the run that made it."""
        self._require_open()
        if not isinstance(snapshot, SimSnapshot):
            raise InvalidInputError(f"restore expects a SimSnapshot, got {type(snapshot).__name__}")
        if snapshot.params != self.params:
            raise InvalidInputError("snapshot was taken with different RopeParams than this world")
        self._pending = snapshot
        self._broken = None if np.all(np.isfinite(snapshot.positions_l3)) else "exploded"

    def rope_nodes(self) -> np.ndarray:
        """Rope node positions (n_links + 1, 3): the capsule end points (joints averaged)."""
        return _nodes_of(self._state())

    @property
    def sim_time(self) -> float:
        """Simulated seconds since the last reset."""
        return self._state().sim_time

    # ------------------------------------------------------------------ building
    def _build(self, state: SimSnapshot) -> None:
        """Rebuild the PyBullet world from scratch in exactly `state` (see module docstring)."""
        cid, prm = self._client, self.params
        p.resetSimulation(physicsClientId=cid)
        p.setPhysicsEngineParameter(
            fixedTimeStep=prm.timestep,
            numSubSteps=0,
            numSolverIterations=prm.solver_iterations,
            deterministicOverlappingPairs=1,
            physicsClientId=cid,
        )
        p.setGravity(0, 0, -prm.gravity, physicsClientId=cid)
        plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
        table = p.createMultiBody(0, plane, physicsClientId=cid)
        table_friction = prm.friction if prm.table_friction is None else prm.table_friction
        p.changeDynamics(table, -1, lateralFriction=table_friction, physicsClientId=cid)
        half = 0.5 * prm.link_length
        shape = p.createCollisionShape(
            p.GEOM_CAPSULE,
            radius=prm.radius,
            height=max(prm.link_length - 2 * prm.radius, 1e-6),
            physicsClientId=cid,
        )
        link_mass = prm.mass / prm.n_links
        links = []
        for i in range(prm.n_links):
            body = p.createMultiBody(
                link_mass,
                shape,
                basePosition=state.positions_l3[i].tolist(),
                baseOrientation=state.quaternions_l4[i].tolist(),
                useMaximalCoordinates=False,
                physicsClientId=cid,
            )
            p.changeDynamics(
                body,
                -1,
                lateralFriction=prm.friction,
                rollingFriction=0.0,
                spinningFriction=0.0,
                restitution=0.0,
                linearDamping=prm.linear_damping,
                angularDamping=prm.angular_damping,
                activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING,
                physicsClientId=cid,
            )
            p.resetBaseVelocity(
                body,
                state.linear_velocities_l3[i].tolist(),
                state.angular_velocities_l3[i].tolist(),
                physicsClientId=cid,
            )
            links.append(body)
        for a, b in itertools.pairwise(links):
            c = p.createConstraint(
                a,
                -1,
                b,
                -1,
                p.JOINT_POINT2POINT,
                [0, 0, 0],
                [0, 0, half],
                [0, 0, -half],
                physicsClientId=cid,
            )
            p.changeConstraint(
                c, maxForce=prm.joint_max_force, erp=prm.joint_erp, physicsClientId=cid
            )
            p.setCollisionFilterPair(a, b, -1, -1, 0, physicsClientId=cid)
        self._links = links
        self._sim_time = state.sim_time
        self._pending = None

    # ------------------------------------------------------------------ stepping
    def _positions(self) -> np.ndarray:
        cid = self._client
        return np.array(
            [p.getBasePositionAndOrientation(b, physicsClientId=cid)[0] for b in self._links]
        )

    def _health(self, prev_pos_l3: np.ndarray, steps: int) -> tuple[str | None, float, np.ndarray]:
        """(failure or None, max stretch, positions) from a cheap read of the link states."""
        cid = self._client
        # One (L, 7) array from the poses: a third of the check's cost was building arrays
        # (and a snapshot) from the tuples. The arithmetic is `_link_ends`', bit for bit.
        pose_l7 = np.array(
            [xyz + q for xyz, q in (p.getBasePositionAndOrientation(b, physicsClientId=cid)
                                    for b in self._links)]
        )  # fmt: skip
        pos = pose_l7[:, :3]
        if not np.all(np.isfinite(pose_l7)):
            return "exploded", math.inf, pos
        half_axis_l3 = 0.5 * self.params.link_length * _quat_z_axes(pose_l7[:, 3:])
        lower, upper = pos - half_axis_l3, pos + half_axis_l3
        stretch = float(np.linalg.norm(upper[:-1] - lower[1:], axis=1).max())
        stretch /= self.params.link_length
        speed = np.linalg.norm(pos - prev_pos_l3, axis=1).max() / (steps * self.params.timestep)
        if speed > self.params.explode_speed or np.abs(pos).max() > 100.0:
            return "exploded", stretch, pos
        if stretch > self.params.stretch_limit:
            return "stretch", stretch, pos
        return None, stretch, pos

    def _step(self) -> None:
        p.stepSimulation(physicsClientId=self._client)
        self._sim_time += self.params.timestep

    def _settle_steps(
        self,
        seconds: float,
        early_stop: bool,
        frames: tuple[FrameRecorder, float, np.ndarray] | None = None,
    ) -> tuple[int, str | None, float]:
        """Step with no grasp for up to `seconds`; stop early once everything is at rest.

        ``frames`` = (recorder, execution start time, gripper positions) records the settle too.
        """
        prm = self.params
        n_max = math.ceil(seconds / prm.timestep - 1e-9)
        block = max(prm.check_every, 12)
        pos = self._positions()
        steps, stretch = 0, 0.0
        while steps < n_max:
            n = min(block, n_max - steps)
            for k in range(n):
                self._step()
                if frames is not None and (steps + k + 1) % frames[0].every == 0:
                    self._record(frames[0], frames[1], frames[2], (False, False))
            steps += n
            failure, s, new_pos = self._health(pos, n)
            stretch = max(stretch, s)
            if failure:
                return steps, failure, stretch
            if early_stop:
                speed = np.linalg.norm(new_pos - pos, axis=1).max() / (n * prm.timestep)
                if speed < self.gripper.rest_speed:
                    break
            pos = new_pos
        return steps, None, stretch

    def settle(self, seconds: float = 1.0, early_stop: bool = False) -> None:
        """Let the rope fall and come to rest for `seconds` with both grippers open."""
        if not (np.isfinite(seconds) and seconds >= 0):
            raise InvalidInputError(f"settle seconds must be finite and >= 0, got {seconds}")
        self._build(self._state())
        _, failure, _ = self._settle_steps(seconds, early_stop)
        if failure:
            self._broken = failure

    def _grasp(self, point_3: np.ndarray) -> tuple[int, int, np.ndarray] | None:
        """Attach the nearest link within grasp_radius: (link, constraint id, pivot offset)."""
        state = self._read_state()
        lower, upper = _link_ends(state)
        dist_l = _point_segment_distance(point_3, lower, upper)
        link = int(np.argmin(dist_l))
        if dist_l[link] > self.gripper.grasp_radius:
            return None
        centre = state.positions_l3[link]
        # The pivot starts where the link centre is, so grasping never yanks the rope; it then
        # keeps the link centre's offset from the gripper point.
        cons = p.createConstraint(
            self._links[link],
            -1,
            -1,
            -1,
            p.JOINT_POINT2POINT,
            [0, 0, 0],
            [0, 0, 0],
            centre.tolist(),
            physicsClientId=self._client,
        )
        p.changeConstraint(
            cons, centre.tolist(), maxForce=self.gripper.grip_force, physicsClientId=self._client
        )
        return link, cons, centre - point_3

    def _record(
        self,
        rec: FrameRecorder,
        t0: float,
        grippers_g3: np.ndarray,
        closed_g: Sequence[bool] | np.ndarray,
    ) -> None:
        """Append the rope's current nodes (read from PyBullet) and the grippers to ``rec``."""
        cid = self._client
        poses = [p.getBasePositionAndOrientation(b, physicsClientId=cid) for b in self._links]
        pos = np.array([xyz for xyz, _ in poses])
        zeros = np.zeros_like(pos)
        quats = np.array([q for _, q in poses])
        nodes = _nodes_of(SimSnapshot(pos, quats, zeros, zeros, 0.0, self.params))
        rec.add(self._sim_time - t0, nodes, grippers_g3, closed_g)
        if rec.correct is not None:
            moved = rec.correct(len(rec) - 1, nodes)
            if moved is not None:
                self._shift_links(pos, quats, moved - nodes)

    def _shift_links(
        self, pos_l3: np.ndarray, quats_l4: np.ndarray, node_moves_k3: np.ndarray
    ) -> None:
        """Translate each link by the mean move of its two nodes, keeping its orientation and
        velocities (links whose nodes did not move are not touched)."""
        cid = self._client
        moves_l3 = 0.5 * (node_moves_k3[1:] + node_moves_k3[:-1])
        for i in np.flatnonzero(np.any(moves_l3 != 0.0, axis=1)):
            p.resetBasePositionAndOrientation(
                self._links[i],
                (pos_l3[i] + moves_l3[i]).tolist(),
                quats_l4[i].tolist(),
                physicsClientId=cid,
            )

    def execute(
        self,
        traj: GripperTrajectory,
        settle_time: float | None = None,
        frames: FrameRecorder | None = None,
    ) -> ExecutionResult:
        """Move the grippers along `traj`, grasping and releasing per its closed flags, then settle.

        Waypoint segments take their nominal duration, stretched where needed so that no gripper
        exceeds ``max_speed`` (3-D) or ``max_descent_speed`` (downwards). Never raises on a
        simulation blow-up: that ends the run with ``ok=False``. With a ``frames`` recorder the
        rope and grippers are recorded every ``frames.dt`` simulated seconds for animation
        (reading poses only: the physics is the same with or without frames), unless the
        recorder carries a ``correct``ion, which moves the rope at each frame (a tracker's
        model world following a camera).
        """
        if not isinstance(traj, GripperTrajectory):
            raise InvalidInputError(
                f"execute expects a GripperTrajectory, got {type(traj).__name__}"
            )
        settle = self.gripper.settle_time if settle_time is None else float(settle_time)
        if not (np.isfinite(settle) and settle >= 0):
            raise InvalidInputError(f"settle_time must be finite and >= 0, got {settle_time}")
        rec = frames
        if rec is not None:
            rec.start(self.params.timestep)
        wall0 = time.perf_counter()
        state = self._state()
        if self._broken is not None or not np.all(np.isfinite(state.positions_l3)):
            if rec is not None:
                rec.finished = True
            return ExecutionResult(False, "exploded", (), (), math.inf, 0, 0.0, 0.0)
        self._build(state)
        phase_s = dict.fromkeys(EXECUTION_PHASES, 0.0)
        phase_steps = dict.fromkeys(EXECUTION_PHASES, 0)
        phase_s["rebuild"] = time.perf_counter() - wall0
        t0 = self._sim_time
        prm, grp = self.params, self.gripper
        pos_gt3, closed_gt = traj.positions_gt3, traj.closed_gt
        held: list[tuple[int, int, np.ndarray] | None] = [None, None]
        misgrasps: list[str] = []
        grasps: list[tuple[str, int]] = []
        steps, max_stretch, failure = 0, 0.0, None
        was_closed = [False, False]

        def apply_flags(t: int) -> None:
            for g in range(2):
                want = bool(closed_gt[g, t])
                if want and not was_closed[g]:
                    got = self._grasp(pos_gt3[g, t])
                    if got is None:
                        misgrasps.append(GRIPPERS[g])
                    else:
                        held[g] = got
                        grasps.append((GRIPPERS[g], got[0]))
                elif not want and was_closed[g]:
                    self._release(held, g)
                was_closed[g] = want

        apply_flags(0)
        if rec is not None:
            self._record(rec, t0, pos_gt3[:, 0], [h is not None for h in held])
        last_pos = self._positions()
        since_check = 0
        for t in range(1, traj.n_waypoints):
            start_g3, delta_g3 = pos_gt3[:, t - 1], pos_gt3[:, t] - pos_gt3[:, t - 1]
            duration = max(
                float(traj.times_t[t] - traj.times_t[t - 1]),
                float(np.linalg.norm(delta_g3, axis=1).max()) / grp.max_speed,
                float(max(0.0, -delta_g3[:, 2].min())) / grp.max_descent_speed,
            )
            n_steps = math.ceil(duration / prm.timestep - 1e-9)
            phase = "drag" if held[0] is not None or held[1] is not None else "approach"
            seg0, steps0 = time.perf_counter(), steps
            for k in range(1, n_steps + 1):
                for g in range(2):
                    hold = held[g]
                    if hold is not None:
                        target = start_g3[g] + delta_g3[g] * (k / n_steps) + hold[2]
                        p.changeConstraint(
                            hold[1],
                            target.tolist(),
                            maxForce=grp.grip_force,
                            physicsClientId=self._client,
                        )
                self._step()
                steps += 1
                since_check += 1
                if rec is not None and steps % rec.every == 0:
                    grip_g3 = start_g3 + delta_g3 * (k / n_steps)
                    self._record(rec, t0, grip_g3, [h is not None for h in held])
                if since_check == prm.check_every:
                    failure, stretch, last_pos = self._health(last_pos, since_check)
                    max_stretch = max(max_stretch, stretch)
                    since_check = 0
                    if failure:
                        break
            phase_s[phase] += time.perf_counter() - seg0
            phase_steps[phase] += steps - steps0
            if failure:
                break
            apply_flags(t)
        for g in range(2):
            self._release(held, g)
        if failure is None:
            at_rest = (rec, t0, pos_gt3[:, -1]) if rec is not None else None
            settle0 = time.perf_counter()
            n, failure, stretch = self._settle_steps(settle, early_stop=True, frames=at_rest)
            phase_s["settle"] = time.perf_counter() - settle0
            phase_steps["settle"] = n
            steps += n
            max_stretch = max(max_stretch, stretch)
        if failure in ("exploded", "stretch"):
            self._broken = failure
        else:
            if rec is not None:  # the rope at rest: the animation's last frame
                self._record(rec, t0, pos_gt3[:, -1], (False, False))
            if misgrasps:
                failure = f"misgrasp:{misgrasps[0]}"
        if rec is not None:
            rec.finished = True
        return ExecutionResult(
            ok=failure is None,
            failure=failure,
            misgrasps=tuple(misgrasps),
            grasps=tuple(grasps),
            max_stretch=float(max_stretch),
            sim_steps=steps,
            sim_time=self._sim_time - t0,
            wall_time=time.perf_counter() - wall0,
            frames=None if rec is None else rec.frames(),
            phase_s=phase_s,
            phase_steps=phase_steps,
        )

    def _release(self, held: list, g: int) -> None:
        if held[g] is not None:
            p.removeConstraint(held[g][1], physicsClientId=self._client)
            held[g] = None

    # ------------------------------------------------------------------ sensing
    def observe(
        self,
        noise: float = 0.0,
        seed: int | None = None,
        max_points: int = 150,
        voxel: float = 0.025,
    ) -> np.ndarray:
        """Point cloud (N <= max_points, 3) on the rope's upper surface (`surface_cloud`)."""
        return surface_cloud(
            self._state(), noise=noise, seed=seed, max_points=max_points, voxel=voxel
        )
