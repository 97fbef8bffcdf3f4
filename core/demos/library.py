"""Demonstration segments and the demonstration library file.

A *segment* is one step of an expert demonstration: the rope before the step (simulator nodes and
the cloud as observed), the gripper trajectory that performed it, and the rope after it.
Shape suffixes: k = rope nodes, n = cloud points, s = segments.

File format (``.npz`` written by :mod:`core.npzfile`, byte-deterministic): a JSON header with
format name, version, per-segment keys and metadata, library metadata and a content hash; and
arrays concatenated over segments with offset vectors for the ragged ones (clouds, trajectories).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from knotlab.core.arrays import points_n3
from knotlab.core.errors import CorruptFileError, InvalidInputError
from knotlab.core.hashing import ContentHash
from knotlab.core.npzfile import read_npz, write_npz
from knotlab.core.world.trajectory import GripperTrajectory

LIBRARY_FORMAT = "knotlab-demo-library"
LIBRARY_VERSION = 1


def segment_key(start_index: int, step_index: int) -> str:
    """Stable library key of a segment: start state and step, e.g. 's012-t1'."""
    return f"s{start_index:03d}-t{step_index}"


@dataclass(frozen=True, eq=False)
class DemoSegment:
    """One demonstrated step: pre-step rope and cloud, gripper trajectory, post-step rope."""

    key: str
    start_index: int
    step_index: int
    pre_nodes_k3: np.ndarray
    pre_cloud_n3: np.ndarray
    trajectory: GripperTrajectory
    post_nodes_k3: np.ndarray
    metadata: dict = field(default_factory=dict)  # seed, style parameters, demo_knotted, ...

    def __post_init__(self) -> None:
        if not isinstance(self.trajectory, GripperTrajectory):
            raise InvalidInputError(f"segment {self.key}: trajectory must be a GripperTrajectory")
        if self.step_index < 0 or self.start_index < 0:
            raise InvalidInputError(f"segment {self.key}: negative step or start index")
        # A recorded demo may come without a rope-state estimate: no nodes (K = 0) before and
        # after. Registration needs only the cloud; what needs the nodes says so.
        pre = points_n3(f"segment {self.key} pre_nodes_k3", self.pre_nodes_k3, min_points=0)
        post = points_n3(f"segment {self.key} post_nodes_k3", self.post_nodes_k3, min_points=0)
        if pre.shape != post.shape:
            raise InvalidInputError(
                f"segment {self.key}: pre and post node shapes differ ({pre.shape} vs {post.shape})"
            )
        object.__setattr__(self, "pre_nodes_k3", pre)
        object.__setattr__(self, "post_nodes_k3", post)
        object.__setattr__(
            self, "pre_cloud_n3", points_n3(f"segment {self.key} pre_cloud_n3", self.pre_cloud_n3)
        )
        json.dumps(self.metadata)  # metadata must be JSON-able: fail now, not at save time


class DemoLibrary:
    """An ordered, immutable collection of demo segments with a content hash."""

    def __init__(self, segments: Sequence[DemoSegment], metadata: dict | None = None) -> None:
        segs = tuple(segments)
        if not segs:
            raise InvalidInputError("a DemoLibrary needs at least one segment")
        keys = [s.key for s in segs]
        if len(set(keys)) != len(keys):
            dup = sorted({k for k in keys if keys.count(k) > 1})
            raise InvalidInputError(f"duplicate segment keys: {dup[:5]}")
        k = segs[0].pre_nodes_k3.shape[0]
        for s in segs:
            if s.pre_nodes_k3.shape[0] != k:
                raise InvalidInputError(
                    f"segment {s.key} has {s.pre_nodes_k3.shape[0]} rope nodes, expected {k}"
                )
        self._segments = segs
        self._index = {key: i for i, key in enumerate(keys)}
        self.metadata: dict = dict(metadata or {})
        json.dumps(self.metadata)
        self._hash: str | None = None

    def __len__(self) -> int:
        return len(self._segments)

    def __iter__(self) -> Iterator[DemoSegment]:
        return iter(self._segments)

    def __getitem__(self, i: int) -> DemoSegment:
        return self._segments[i]

    @property
    def task(self) -> str:
        """The task these demos perform (libraries made before tasks were named: overhand)."""
        return str(self.metadata.get("task", "overhand"))

    @property
    def has_rope_nodes(self) -> bool:
        """Whether the segments carry rope states (a recorded library may have clouds only)."""
        return self._segments[0].pre_nodes_k3.shape[0] > 0

    def require_rope_nodes(self, purpose: str) -> None:
        """Raise a clear error when ``purpose`` needs rope states this library lacks."""
        if not self.has_rope_nodes:
            raise InvalidInputError(
                f"{purpose} needs the demos' rope states (rope_nodes), and this library has "
                "clouds only; nearest neighbour and greedy need only the clouds"
            )

    @property
    def segments(self) -> tuple[DemoSegment, ...]:
        """All segments, in library order (the action index of the learner)."""
        return self._segments

    @property
    def keys(self) -> tuple[str, ...]:
        """Segment keys in library order."""
        return tuple(s.key for s in self._segments)

    def index_of(self, key: str) -> int:
        """Library index of segment ``key``."""
        try:
            return self._index[key]
        except KeyError:
            raise InvalidInputError(f"no segment with key {key!r} in this library") from None

    def clouds(self) -> list[np.ndarray]:
        """Pre-step clouds of every segment (what registration matches against)."""
        return [s.pre_cloud_n3 for s in self._segments]

    def start_indices(self) -> np.ndarray:
        """Start-state index of every segment."""
        return np.array([s.start_index for s in self._segments], dtype=np.int64)

    def step_indices(self) -> np.ndarray:
        """Step index (0, 1, 2, ...) of every segment."""
        return np.array([s.step_index for s in self._segments], dtype=np.int64)

    def start_states(self) -> dict[int, np.ndarray]:
        """Pre-step rope nodes of each demonstration's first segment, by start index."""
        self.require_rope_nodes("start states from a library (tasks generate)")
        out: dict[int, np.ndarray] = {}
        for s in sorted(self._segments, key=lambda s: (s.start_index, s.step_index)):
            out.setdefault(s.start_index, s.pre_nodes_k3)
        return out

    def _arrays(self) -> dict[str, np.ndarray]:
        segs = self._segments
        cloud_off = np.cumsum([0] + [s.pre_cloud_n3.shape[0] for s in segs]).astype(np.int64)
        traj_off = np.cumsum([0] + [s.trajectory.n_waypoints for s in segs]).astype(np.int64)
        return {
            "start_index_s": np.array([s.start_index for s in segs], dtype=np.int64),
            "step_index_s": np.array([s.step_index for s in segs], dtype=np.int64),
            "pre_nodes_sk3": np.stack([s.pre_nodes_k3 for s in segs]).astype(np.float64),
            "post_nodes_sk3": np.stack([s.post_nodes_k3 for s in segs]).astype(np.float64),
            "cloud_offsets": cloud_off,
            "clouds_n3": np.concatenate([s.pre_cloud_n3 for s in segs]).astype(np.float64),
            "traj_offsets": traj_off,
            "traj_times_t": np.concatenate([s.trajectory.times_t for s in segs]),
            "traj_positions_tg3": np.concatenate(
                [s.trajectory.positions_gt3.transpose(1, 0, 2) for s in segs]
            ),
            "traj_rotations_tg33": np.concatenate(
                [s.trajectory.rotations_gt33.transpose(1, 0, 2, 3) for s in segs]
            ),
            "traj_closed_tg": np.concatenate([s.trajectory.closed_gt.T for s in segs]),
        }

    def _header_body(self) -> dict:
        return {
            "keys": list(self.keys),
            "segment_metadata": [s.metadata for s in self._segments],
            "metadata": self.metadata,
        }

    def content_hash(self) -> str:
        """SHA-256 (hex, 16 chars) of every array and the metadata: identifies the library."""
        if self._hash is None:
            self._hash = _hash_content(self._arrays(), self._header_body())
        return self._hash

    def save(self, path: str | Path) -> Path:
        """Write the library to one versioned, byte-deterministic .npz file."""
        header = {
            "format": LIBRARY_FORMAT,
            "version": LIBRARY_VERSION,
            "hash": self.content_hash(),
            **self._header_body(),
        }
        return write_npz(path, self._arrays(), header)

    @classmethod
    def load(cls, path: str | Path) -> DemoLibrary:
        """Read and validate a library file; errors name the file and what is wrong."""
        path = Path(path)
        arrays, header = read_npz(path, "demo library")
        try:
            lib = _library_from_parts(arrays, header)
        except CorruptFileError as exc:
            raise CorruptFileError(f"{path}: {exc}") from None
        except (InvalidInputError, KeyError, ValueError, TypeError) as exc:
            raise CorruptFileError(f"{path}: invalid demo library contents: {exc}") from exc
        if header.get("hash") != lib.content_hash():
            raise CorruptFileError(
                f"{path}: content hash mismatch (stored {header.get('hash')!r}, "
                f"computed {lib.content_hash()!r}): the file was altered"
            )
        return lib

    def summary(self) -> dict:
        """Counts for `knotlab demos info`: segments, start states, segments per step, hash."""
        steps = self.step_indices()
        per_step = {int(t): int(np.sum(steps == t)) for t in np.unique(steps)}
        return {
            "segments": len(self),
            "start_states": len(set(self.start_indices().tolist())),
            "segments_per_step": per_step,
            "hash": self.content_hash(),
            "version": LIBRARY_VERSION,
            "observation_model": self.metadata.get("observation_model", "cloud"),
            "metadata": self.metadata,
        }


_EXPECTED = {
    "start_index_s": (np.int64, 1),
    "step_index_s": (np.int64, 1),
    "pre_nodes_sk3": (np.float64, 3),
    "post_nodes_sk3": (np.float64, 3),
    "cloud_offsets": (np.int64, 1),
    "clouds_n3": (np.float64, 2),
    "traj_offsets": (np.int64, 1),
    "traj_times_t": (np.float64, 1),
    "traj_positions_tg3": (np.float64, 3),
    "traj_rotations_tg33": (np.float64, 4),
    "traj_closed_tg": (np.bool_, 2),
}


def _hash_content(arrays: dict[str, np.ndarray], body: dict) -> str:
    h = ContentHash()
    for name in sorted(arrays):
        h.tagged_array(name, arrays[name])
    return h.json(body).hexdigest()


def _library_from_parts(arrays: dict[str, np.ndarray], header: dict) -> DemoLibrary:
    if header.get("format") != LIBRARY_FORMAT:
        raise CorruptFileError(f"not a demo library (format {header.get('format')!r})")
    if header.get("version") != LIBRARY_VERSION:
        raise CorruptFileError(
            f"demo library version {header.get('version')} is not supported "
            f"(this knotlab reads version {LIBRARY_VERSION}); regenerate it with "
            "`knotlab demos generate`"
        )
    for name, (dtype, ndim) in _EXPECTED.items():
        if name not in arrays:
            raise CorruptFileError(f"missing array {name!r}")
        arr = arrays[name]
        if arr.dtype != dtype or arr.ndim != ndim:
            raise CorruptFileError(
                f"array {name!r} has dtype {arr.dtype} and {arr.ndim} dims, "
                f"expected {np.dtype(dtype)} with {ndim}"
            )
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise CorruptFileError(f"array {name!r} contains NaN or infinite values")
    n_seg = arrays["start_index_s"].shape[0]
    keys = header.get("keys")
    seg_meta = header.get("segment_metadata")
    if not isinstance(keys, list) or len(keys) != n_seg:
        raise CorruptFileError(f"header lists {len(keys or [])} keys for {n_seg} segments")
    if not isinstance(seg_meta, list) or len(seg_meta) != n_seg:
        raise CorruptFileError("segment metadata count does not match the segments")
    for name in ("step_index_s", "pre_nodes_sk3", "post_nodes_sk3"):
        if arrays[name].shape[0] != n_seg:
            raise CorruptFileError(f"array {name!r} has {arrays[name].shape[0]} rows, not {n_seg}")
    c_off, t_off = arrays["cloud_offsets"], arrays["traj_offsets"]
    for name, off, total in (
        ("cloud_offsets", c_off, arrays["clouds_n3"].shape[0]),
        ("traj_offsets", t_off, arrays["traj_times_t"].shape[0]),
    ):
        if off.shape != (n_seg + 1,) or off[0] != 0 or off[-1] != total or np.any(np.diff(off) < 1):
            raise CorruptFileError(f"{name} are inconsistent with the stored arrays")
    n_t = arrays["traj_times_t"].shape[0]
    for name, shape in (
        ("traj_positions_tg3", (n_t, 2, 3)),
        ("traj_rotations_tg33", (n_t, 2, 3, 3)),
        ("traj_closed_tg", (n_t, 2)),
    ):
        if arrays[name].shape != shape:
            raise CorruptFileError(f"array {name!r} has shape {arrays[name].shape}, not {shape}")
    segments = []
    for i in range(n_seg):
        lo, hi = t_off[i], t_off[i + 1]
        traj = GripperTrajectory(
            arrays["traj_times_t"][lo:hi],
            arrays["traj_positions_tg3"][lo:hi].transpose(1, 0, 2),
            arrays["traj_rotations_tg33"][lo:hi].transpose(1, 0, 2, 3),
            arrays["traj_closed_tg"][lo:hi].T,
        )
        segments.append(
            DemoSegment(
                key=str(keys[i]),
                start_index=int(arrays["start_index_s"][i]),
                step_index=int(arrays["step_index_s"][i]),
                pre_nodes_k3=arrays["pre_nodes_sk3"][i],
                pre_cloud_n3=arrays["clouds_n3"][c_off[i] : c_off[i + 1]],
                trajectory=traj,
                post_nodes_k3=arrays["post_nodes_sk3"][i],
                metadata=dict(seg_meta[i]),
            )
        )
    return DemoLibrary(segments, header.get("metadata", {}))
