"""What the robot perceives of the rope: the point cloud that registration matches.

Three observation models, named so that every library, model and results file can record which one
made its clouds (mixing them is refused where they meet: `LibraryFeaturizer.for_model`, the bench):

- ``centreline`` (default): the rope state estimate, i.e. its K simulator nodes plus the K - 1
  segment midpoints (81 points for the 40-link rope). It stands in for a rope tracker, as the
  original system's pipeline was a Kinect cloud of a rope that a tracker could follow. Measured on
  training starts: with it, nearest-neighbour transfer succeeds about 5x as often as
  with the surface cloud, mostly because step 2 and step 3 grasps land on the right node.
- ``cloud``: `surface_cloud` (what `RopeWorld.observe()` returns), the voxel-downsampled (2.5 cm)
  upper surface a camera above the table sees, as the original system's ray-cast Kinect cloud.
- ``tracked``: a centreline *estimated from the camera cloud*, as a rope tracker would report it:
  the tracker's prior is the rope's node chain (an idealisation: it was following the rope
  without drift), every centreline point
  is then pulled to the visible surface points near it (a 1 cm voxel cloud with ``TRACKER_NOISE``
  sensor noise), lowered by the rope radius, and the chain is smoothed. Where the rope is hidden
  (the lower strand at a crossing) the point keeps its prior plus noise. It sits between the two
  others: camera-like errors, the centreline's coverage.

Noise: N(0, noise^2) per coordinate from a Generator seeded with ``seed`` (same seed, same cloud).
The tracker's own noise is seeded the same way; without a seed it is seeded by the rope state's
bytes, so the same state always gives the same estimate (lookahead and the oracle rely on it).
Shape suffixes: k = rope nodes, l = rope links (capsules), n = cloud points, 4 = xyzw quaternion.
"""

from __future__ import annotations

import zlib
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np

from knotlab.core.arrays import points_n3
from knotlab.core.errors import InvalidInputError, parse_choice
from knotlab.core.voxels import voxel_groups

if TYPE_CHECKING:  # the simulator imports this module (and pybullet): only for the checker
    from knotlab.core.world.protocol import World
    from knotlab.core.world.sim import SimSnapshot


class ObservationModel(StrEnum):
    """How a rope state becomes the cloud that registration sees."""

    CENTRELINE = "centreline"
    CLOUD = "cloud"
    TRACKED = "tracked"

    @classmethod
    def parse(cls, value: str | ObservationModel) -> ObservationModel:
        """The model named ``value``; a clear error naming the choices otherwise."""
        return parse_choice(cls, value, "observation model")

    @classmethod
    def of_library_metadata(cls, metadata: dict) -> ObservationModel:
        """The model a library's clouds were made with (libraries before it was named: cloud)."""
        value = metadata.get("observation_model")
        return cls.CLOUD if value is None else cls.parse(value)


DEFAULT_OBSERVATION = ObservationModel.CENTRELINE
TRACKER_NOISE = 0.003  # m, per-coordinate sensor noise of the tracker's camera cloud
TRACKER_RADIUS = 0.02  # m, visible points within this xy distance pull a centreline point
_TRACKER_VOXEL = 0.01  # m


def _quat_to_axes(quats_l4: np.ndarray) -> np.ndarray:
    """Rotation matrices (L, 3, 3) from xyzw quaternions."""
    x, y, z, w = (quats_l4[:, i] for i in range(4))
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def surface_cloud(
    state: SimSnapshot,
    *,
    noise: float = 0.0,
    seed: int | None = None,
    max_points: int = 150,
    voxel: float = 0.025,
) -> np.ndarray:
    """Point cloud (N <= max_points, 3) on the upper surface of the rope in ``state``.

    Samples each capsule's cylinder where its normal faces up (what a camera above sees),
    keeps per voxel the sample nearest to the voxel's mean (so points stay ON the surface),
    then adds N(0, noise^2) per coordinate from a Generator seeded with `seed`.
    """
    _check_cloud_settings(noise, max_points, voxel)
    prm = state.params
    rot_l33 = _quat_to_axes(state.quaternions_l4)
    cloud = _upper_surface(state.positions_l3, rot_l33, prm.link_length, prm.radius, voxel)
    return _thin_and_noise(cloud, noise, seed, max_points)


def surface_cloud_of_nodes(
    nodes_k3: np.ndarray,
    radius: float,
    *,
    max_points: int = 150,
    voxel: float = 0.025,
) -> np.ndarray:
    """The upper-surface cloud (N <= max_points, 3) of a rope known only by its node chain.

    The same sampling as `surface_cloud` on capsules spanning consecutive nodes (a frame of an
    execution records nodes, not link poses; a capsule's roll about its axis is not visible).
    """
    _check_cloud_settings(0.0, max_points, voxel)
    nodes = np.asarray(nodes_k3, dtype=float)
    seg_l3 = nodes[1:] - nodes[:-1]
    length_l = np.linalg.norm(seg_l3, axis=1)
    axis_l3 = seg_l3 / np.maximum(length_l, 1e-12)[:, None]
    # Any unit vector across the axis: the world's up where the link is not vertical.
    helper = np.where(np.abs(axis_l3[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u_l3 = np.cross(helper, axis_l3)
    u_l3 /= np.maximum(np.linalg.norm(u_l3, axis=1, keepdims=True), 1e-12)
    v_l3 = np.cross(axis_l3, u_l3)
    rot_l33 = np.stack([u_l3, v_l3, axis_l3], axis=2)
    centres_l3 = 0.5 * (nodes[1:] + nodes[:-1])
    cloud = _upper_surface(centres_l3, rot_l33, float(length_l.mean()), radius, voxel)
    return _thin_and_noise(cloud, 0.0, None, max_points)


def _check_cloud_settings(noise: float, max_points: int, voxel: float) -> None:
    if not (np.isfinite(noise) and noise >= 0):
        raise InvalidInputError(f"observe noise must be finite and >= 0, got {noise}")
    if max_points < 1 or not voxel > 0:
        raise InvalidInputError("observe needs max_points >= 1 and voxel > 0")


def _upper_surface(
    centres_l3: np.ndarray, rot_l33: np.ndarray, link_length: float, radius: float, voxel: float
) -> np.ndarray:
    """One surface point per occupied voxel: the sample nearest to its voxel's mean, (N, 3)."""
    u_l3, v_l3, a_l3 = rot_l33[:, :, 0], rot_l33[:, :, 1], rot_l33[:, :, 2]
    along_s = np.linspace(-0.5, 0.5, 5, endpoint=False) * link_length
    phi_r = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    normal_lr3 = (
        np.cos(phi_r)[None, :, None] * u_l3[:, None, :]
        + np.sin(phi_r)[None, :, None] * v_l3[:, None, :]
    )
    pts = (
        centres_l3[:, None, None, :]
        + along_s[None, :, None, None] * a_l3[:, None, None, :]
        + radius * normal_lr3[:, None, :, :]
    )
    visible = np.broadcast_to(normal_lr3[:, None, :, 2] >= -0.2, pts.shape[:3])
    pts = pts[visible & np.isfinite(pts).all(axis=-1)]
    if pts.shape[0] == 0:
        return np.zeros((0, 3))
    inv, _, mean_v3 = voxel_groups(pts, voxel)
    dist = np.linalg.norm(pts - mean_v3[inv], axis=1)
    order = np.lexsort((dist, inv))  # by voxel, nearest first
    first = np.ones(order.size, dtype=bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    return pts[order[first]]


def _thin_and_noise(
    cloud: np.ndarray, noise: float, seed: int | None, max_points: int
) -> np.ndarray:
    """At most ``max_points`` evenly through the cloud's order, plus seeded N(0, noise^2)."""
    if cloud.shape[0] > max_points:
        cloud = cloud[np.linspace(0, cloud.shape[0] - 1, max_points).round().astype(int)]
    if noise > 0 and len(cloud):
        cloud = cloud + np.random.default_rng(seed).normal(0.0, noise, size=cloud.shape)
    return cloud


def centreline_points(nodes_k3: np.ndarray) -> np.ndarray:
    """The rope's nodes and segment midpoints, in order along the rope: (2K - 1, 3)."""
    nodes = points_n3("rope nodes", nodes_k3, min_points=2, unit="nodes")
    out = np.empty((2 * nodes.shape[0] - 1, 3))
    out[0::2] = nodes
    out[1::2] = 0.5 * (nodes[:-1] + nodes[1:])
    return out


def observe(
    world: World,
    model: ObservationModel = DEFAULT_OBSERVATION,
    *,
    noise: float = 0.0,
    seed: int | None = None,
) -> np.ndarray:
    """The cloud (n, 3) of the world's current rope under ``model``, plus seeded noise."""
    if not (np.isfinite(noise) and noise >= 0):
        raise InvalidInputError(f"observation noise must be finite and >= 0, got {noise}")
    if model is ObservationModel.CLOUD:
        return world.observe(noise=noise, seed=seed)
    if model is ObservationModel.TRACKED:
        nodes = world.rope_nodes()
        if seed is None:  # still deterministic: the same rope state gives the same estimate
            seed = zlib.crc32(np.ascontiguousarray(nodes, dtype=np.float64).tobytes())
        rng = np.random.default_rng(seed)
        surface = world.observe(max_points=1000, voxel=_TRACKER_VOXEL)
        surface = surface + rng.normal(0.0, TRACKER_NOISE, size=surface.shape)
        cloud = tracked_centreline(nodes, surface, radius=world.params.radius, rng=rng)
        if noise > 0:
            cloud = cloud + rng.normal(0.0, noise, size=cloud.shape)
        return cloud
    cloud = centreline_points(world.rope_nodes())
    if noise > 0:
        cloud = cloud + np.random.default_rng(seed).normal(0.0, noise, size=cloud.shape)
    return cloud


def tracked_centreline(
    prior_nodes_k3: np.ndarray,
    surface_n3: np.ndarray,
    *,
    radius: float,
    rng: np.random.Generator,
    reach: float = 1.0,
) -> np.ndarray:
    """A tracker's centreline (2K - 1, 3): the prior chain pulled to the visible surface, smoothed.

    Each prior point p takes the mean xy of the surface points within ``reach * TRACKER_RADIUS``
    of it in
    xy whose centre height (z - radius) is within one radius of p's (the other strand at a
    crossing lies a diameter above or below, so it does not pull), and their mean z minus
    ``radius``; points with no such neighbour keep p plus N(0, TRACKER_NOISE^2) (occluded).
    A 1-2-1 filter along the chain then smooths it.
    """
    from scipy.spatial import cKDTree

    prior = centreline_points(prior_nodes_k3)
    est = prior + rng.normal(0.0, TRACKER_NOISE, size=prior.shape)
    surface = np.asarray(surface_n3, dtype=float)
    if len(surface):
        tree = cKDTree(surface[:, :2])
        for i, near in enumerate(tree.query_ball_point(prior[:, :2], reach * TRACKER_RADIUS)):
            if not near:
                continue
            pts = surface[near]
            pts = pts[np.abs(pts[:, 2] - radius - prior[i, 2]) < radius]
            if len(pts):
                est[i, :2] = pts[:, :2].mean(axis=0)
                est[i, 2] = pts[:, 2].mean() - radius
    smooth = est.copy()
    smooth[1:-1] = 0.25 * est[:-2] + 0.5 * est[1:-1] + 0.25 * est[2:]
    return smooth
