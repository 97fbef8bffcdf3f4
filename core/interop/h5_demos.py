"""Demo libraries in the original system's HDF5 layout: import and export.

One group per segment, named ``<demo>-seg<NN>``, holding:

- ``cloud_xyz`` (N x 3, metres): the rope as observed before the segment;
- ``l_gripper_tool_frame/hmat`` and ``r_gripper_tool_frame/hmat`` (T x 4 x 4): end-effector poses;
- ``l_gripper_joint`` and ``r_gripper_joint`` (T): gripper openings, closed below 0.04;
- ``rope_nodes`` (K x 3), optional: the rope-state estimate before the segment;
- ``description``: free text;
- ``stamps`` (T), optional: waypoint times in seconds.

knotlab writes two additions the original readers ignore, so an export re-imports to the same
content hash: a ``knotlab`` sub-group per segment (the key, start and step index, the segment's
metadata as JSON, the rope after the segment) and file attributes with the library's metadata
and segment order. A file without them (a lab's own recordings) imports with: segments ordered
by demo name (natural order) and segment number; start index = the demo's position in that
order; key = the group name; times from the path at a nominal gripper speed when there are no
stamps; the rope after a segment = the next segment's rope, or unknown (the same as before) for a
demo's last segment. A library without rope nodes ranks with nearest neighbour and greedy
(registration needs only clouds); whatever needs the demos' rope states says so.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from knotlab.core.atomic import atomic_path
from knotlab.core.demos.library import DemoLibrary, DemoSegment
from knotlab.core.errors import InvalidInputError
from knotlab.core.interop.h5read import H5File, open_h5
from knotlab.core.world.trajectory import GripperTrajectory

CLOSED_BELOW = 0.04  # a gripper joint opening below this is closed (the PR2 convention)
OPEN_JOINT = 0.08  # what an open gripper is written as (about the PR2's full opening)
CLOSED_JOINT = 0.0
NOMINAL_SPEED = 0.2  # m/s: the pace given to recorded waypoints that come without stamps
MIN_WAYPOINT_DT = 0.05  # s: the shortest step between unstamped waypoints
RIGID_TOLERANCE = 1e-4  # how far a pose's rotation may be from orthonormal
SIDES: tuple[str, str] = ("l", "r")  # GripperTrajectory's gripper 0 is the left one
SEGMENT_NAME = re.compile(r"(?P<demo>.+)-seg(?P<seg>[0-9]{1,6})")
FORMAT_ATTR = "knotlab_format"
FORMAT_NAME = "knotlab-demo-library-h5/1"


@dataclass(frozen=True)
class ImportReport:
    """What an import read: the library, and how many segments needed knotlab's guesses."""

    library: DemoLibrary
    groups: int
    native: bool  # written by knotlab (lossless) rather than a foreign recording
    timed_from_path: int  # segments whose times came from the nominal speed (no stamps)
    has_rope_nodes: bool


def group_name(segment: DemoSegment) -> str:
    """The ``<demo>-seg<NN>`` group of a segment (its start state is the demo)."""
    demo = str(segment.metadata.get("demo") or f"s{segment.start_index:03d}")
    return f"{demo}-seg{segment.step_index:02d}"


def _natural_key(text: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"([0-9]+)", text))


def export_library_h5(library: DemoLibrary, path: str | Path) -> Path:
    """Write ``library`` to ``path`` in the original HDF5 layout (plus knotlab's additions)."""
    import h5py

    names = [group_name(s) for s in library]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})[:3]
        raise InvalidInputError(f"two segments share the HDF5 group name(s) {dup}")
    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs[FORMAT_ATTR] = FORMAT_NAME
        f.attrs["knotlab_library"] = json.dumps(library.metadata, sort_keys=True)
        f.attrs["knotlab_order"] = json.dumps(names)
        f.attrs["knotlab_hash"] = library.content_hash()
        for name, seg in zip(names, library, strict=False):
            _write_segment(f.create_group(name), seg)
    return path


def _write_segment(g: object, seg: DemoSegment) -> None:
    traj = seg.trajectory
    g.create_dataset("cloud_xyz", data=seg.pre_cloud_n3)  # type: ignore[attr-defined]
    for side, gi in zip(SIDES, range(2), strict=False):
        hmat = np.zeros((traj.n_waypoints, 4, 4))
        hmat[:, :3, :3] = traj.rotations_gt33[gi]
        hmat[:, :3, 3] = traj.positions_gt3[gi]
        hmat[:, 3, 3] = 1.0
        g.create_dataset(f"{side}_gripper_tool_frame/hmat", data=hmat)  # type: ignore[attr-defined]
        joint = np.where(traj.closed_gt[gi], CLOSED_JOINT, OPEN_JOINT)
        g.create_dataset(f"{side}_gripper_joint", data=joint)  # type: ignore[attr-defined]
    g.create_dataset("stamps", data=traj.times_t)  # type: ignore[attr-defined]
    if seg.pre_nodes_k3.shape[0]:
        g.create_dataset("rope_nodes", data=seg.pre_nodes_k3)  # type: ignore[attr-defined]
    g.create_dataset("description", data=str(seg.metadata.get("description", seg.key)))  # type: ignore[attr-defined]
    extra = g.create_group("knotlab")  # type: ignore[attr-defined]
    extra.attrs["key"] = seg.key
    extra.attrs["start_index"] = seg.start_index
    extra.attrs["step_index"] = seg.step_index
    extra.attrs["metadata"] = json.dumps(seg.metadata, sort_keys=True)
    if seg.post_nodes_k3.shape[0]:
        extra.create_dataset("post_rope_nodes", data=seg.post_nodes_k3)


def import_library_h5(
    path: str | Path, *, task: str | None = None, observation: str | None = None
) -> ImportReport:
    """Read a demo library in the original HDF5 layout; a bad file names the group and key.

    ``observation`` names how the clouds were perceived (default: a camera's surface cloud);
    a file knotlab exported keeps its own, and a different one is refused.
    """
    with open_h5(path, "HDF5 demo") as f:
        names = f.group_names()
        if not names:
            raise f.fail("/", "no segment groups")
        native = f.handle.attrs.get(FORMAT_ATTR) == FORMAT_NAME
        order = f.json_attr("/", "knotlab_order") if native else None
        parsed = {}
        for name in names:
            m = SEGMENT_NAME.fullmatch(name)
            if m is None:
                raise f.fail(name, "group name is not <demo>-seg<NN>")
            parsed[name] = (m.group("demo"), int(m.group("seg")))
        if order is not None:
            if sorted(order) != sorted(names):
                raise f.fail("/@knotlab_order", "does not list exactly the file's groups")
            names = list(order)
        else:
            names.sort(key=lambda n: (_natural_key(parsed[n][0]), parsed[n][1]))
        demos = list(dict.fromkeys(parsed[n][0] for n in names))
        raw = [_read_segment(f, n, demos.index(parsed[n][0]), parsed[n][1]) for n in names]
        with_nodes = {n for n, r in zip(names, raw, strict=False) if r.nodes is not None}
        if with_nodes and len(with_nodes) != len(names):
            missing = next(n for n in names if n not in with_nodes)
            raise f.fail(f"{missing}/rope_nodes", "missing, while other segments have rope nodes")
        counts = {r.nodes.shape[0] for r in raw if r.nodes is not None}
        if len(counts) > 1:
            raise f.fail("rope_nodes", f"segments differ in rope node count {sorted(counts)}")
        segments = [_segment(f, names, raw, i) for i in range(len(raw))]
        meta = f.json_attr("/", "knotlab_library") if native else None
        if meta is None:
            meta = {
                "observation_model": observation or "cloud",
                "source": f"hdf5:{Path(path).name}",
            }
        elif observation is not None and observation != meta.get("observation_model", "cloud"):
            raise InvalidInputError(
                f"{path}: the library's clouds are {meta.get('observation_model', 'cloud')!r} "
                f"observations, not {observation!r}"
            )
        if task is not None and task != meta.get("task", "overhand"):
            if native:
                raise InvalidInputError(
                    f"{path}: the library is for task {meta.get('task', 'overhand')!r}, "
                    f"not {task!r}"
                )
            meta["task"] = task
        if meta.get("task") == "overhand":
            del meta["task"]  # overhand libraries do not name their task (unchanged hashes)
        try:
            library = DemoLibrary(segments, meta)
        except InvalidInputError as exc:
            raise f.fail("/", str(exc)) from None
    return ImportReport(
        library, len(names), native, sum(r.timed_from_path for r in raw), bool(with_nodes)
    )


@dataclass(frozen=True)
class _RawSegment:
    name: str
    start_index: int
    step_index: int
    cloud: np.ndarray
    trajectory: GripperTrajectory
    nodes: np.ndarray | None
    description: str
    timed_from_path: bool
    extra_key: str | None
    extra_meta: dict | None
    post_nodes: np.ndarray | None


def _read_segment(f: H5File, name: str, demo_index: int, seg: int) -> _RawSegment:
    cloud = f.array(name, "cloud_xyz", (None, 3))
    poses = [f.array(name, f"{s}_gripper_tool_frame/hmat", (None, 4, 4)) for s in SIDES]
    n_t = poses[0].shape[0]
    if poses[1].shape[0] != n_t:
        raise f.fail(f"{name}/r_gripper_tool_frame/hmat", f"{poses[1].shape[0]} poses, left {n_t}")
    joints = [f.array(name, f"{s}_gripper_joint", (n_t,)) for s in SIDES]
    for side, hmat in zip(SIDES, poses, strict=False):
        _check_rigid(f, f"{name}/{side}_gripper_tool_frame/hmat", hmat)
    closed = np.stack([j < CLOSED_BELOW for j in joints])
    if not closed.any():
        raise f.fail(
            f"{name}/l_gripper_joint, r_gripper_joint",
            f"neither gripper ever closes (closed below {CLOSED_BELOW})",
        )
    timed = not f.has(name, "stamps")
    times = _path_times(poses) if timed else f.array(name, "stamps", (n_t,))
    if np.any(np.diff(times) < 0):
        raise f.fail(f"{name}/stamps", "times go backwards")
    try:
        traj = GripperTrajectory(
            times,
            np.stack([p[:, :3, 3] for p in poses]),
            np.stack([p[:, :3, :3] for p in poses]),
            closed,
        )
    except InvalidInputError as exc:
        raise f.fail(name, str(exc)) from None
    nodes = f.array(name, "rope_nodes", (None, 3)) if f.has(name, "rope_nodes") else None
    extra_key = extra_meta = post = None
    start, step = demo_index, seg
    if f.has(name, "knotlab"):
        where = f"{name}/knotlab"
        attrs = f.handle[where].attrs
        try:
            extra_key, start, step = (
                str(attrs["key"]),
                int(attrs["start_index"]),
                int(attrs["step_index"]),
            )
        except (KeyError, ValueError, TypeError):
            raise f.fail(where, "needs key, start_index and step_index attributes") from None
        extra_meta = f.json_attr(where, "metadata", {})
        if not isinstance(extra_meta, dict):
            raise f.fail(f"{where}@metadata", "expected a JSON object")
        if f.has(where, "post_rope_nodes"):
            post = f.array(where, "post_rope_nodes", (None, 3))
    return _RawSegment(
        name,
        start,
        step,
        cloud,
        traj,
        nodes,
        f.text(name, "description", default=""),
        timed,
        extra_key,
        extra_meta,
        post,
    )


def _check_rigid(f: H5File, where: str, hmat_t44: np.ndarray) -> None:
    bottom = np.abs(hmat_t44[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    rot = hmat_t44[:, :3, :3]
    ortho = np.abs(np.einsum("tji,tjk->tik", rot, rot) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    bad = np.flatnonzero((bottom > 1e-6) | (ortho > RIGID_TOLERANCE) | (det < 0))
    if bad.size:
        t = int(bad[0])
        raise f.fail(
            where,
            f"pose {t} is not a rigid transform (rotation error {ortho[t]:.2g}, "
            f"determinant {det[t]:.3g}, bottom row off by {bottom[t]:.2g}); "
            f"{bad.size} such poses",
        )


def _path_times(poses: list[np.ndarray]) -> np.ndarray:
    """Waypoint times at the nominal speed of the faster-moving gripper (no stamps given)."""
    step = np.max([np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1) for p in poses], axis=0)
    dt = np.maximum(step / NOMINAL_SPEED, MIN_WAYPOINT_DT)
    return np.concatenate([[0.0], np.cumsum(dt)])


def _segment(f: H5File, names: list[str], raw: list[_RawSegment], i: int) -> DemoSegment:
    r = raw[i]
    empty = np.zeros((0, 3))
    pre = r.nodes if r.nodes is not None else empty
    if r.extra_meta is not None:  # written by knotlab: exactly what was exported
        post = r.post_nodes if r.post_nodes is not None else empty
        meta = r.extra_meta
        key = r.extra_key or r.name
    else:
        nxt = raw[i + 1] if i + 1 < len(raw) else None
        same_demo = nxt is not None and nxt.start_index == r.start_index
        if r.nodes is not None and same_demo and nxt is not None and nxt.nodes is not None:
            post, post_source = nxt.nodes, "the next segment's rope_nodes"
        else:
            post, post_source = pre, "unknown (the rope before the segment)"
        meta = {
            "demo": SEGMENT_NAME.fullmatch(r.name).group("demo"),  # type: ignore[union-attr]
            "description": r.description,
            "post_nodes": post_source if r.nodes is not None else "none",
            "times": "from the path at the nominal speed" if r.timed_from_path else "stamps",
        }
        key = r.name
    try:
        return DemoSegment(key, r.start_index, r.step_index, pre, r.cloud, r.trajectory, post, meta)
    except InvalidInputError as exc:
        raise f.fail(names[i], str(exc)) from None
