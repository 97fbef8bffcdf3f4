"""A rope with visible marks: the camera reads which part of the rope lies where.

A cloud of the rope's surface says where the rope is, not which part of it (a chain slid along
its own curve fits the cloud as well as the true one). A rope with distinguishable marks at
known places along it (a sequence of coloured bands, as a tape measure's numbers) gives the
tracker that missing coordinate wherever a mark is in view. `observe_marks` is the camera's
reading (each mark's top, with sensor noise, unless another strand lies over it);
`move_to_marks` moves a tracker's chain so that its point at each seen mark's place along the
rope lies at the mark, straight between neighbouring marks in view, the moves interpolated
across hidden ones, and the ends beyond the outermost marks slid along the chain.

Marks are known by their fraction of the rope's length, so a model rope of another length reads
them at its own scale. Shape suffixes: k = rope nodes, j = marks, p = dense centreline points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knotlab.core.world.rope import arc_lengths, points_at_arc

MARK_SPACING = 0.05  # m between marks along the rope, about (the first one half that from the end)
# A move shrinks by this much (m): a mark's reading wanders by the camera's noise, and a chain
# that follows the noise zigzags across a strand lying beside it (extra crossings, measured).
MARK_DEAD_BAND = 0.005


@dataclass(frozen=True)
class MarkReading:
    """The marks in view: their fractions along the rope (J,), increasing, their seen tops
    (J, 3), the rope's radius (a mark's centre is one radius under its top) and how many
    marks the rope carries, seen or not (``mark_fractions``)."""

    fraction_j: np.ndarray
    top_j3: np.ndarray
    radius: float
    count: int

    def neighbours(self, j: int) -> bool:
        """Whether seen marks j and j + 1 are next to each other on the rope (none hidden
        between them)."""
        return round((self.fraction_j[j + 1] - self.fraction_j[j]) * self.count) == 1

    def __len__(self) -> int:
        return len(self.fraction_j)

    @property
    def centre_j3(self) -> np.ndarray:
        """Where each mark's rope centre is, as seen (J, 3)."""
        return self.top_j3 - np.array([0.0, 0.0, self.radius])


def mark_fractions(length: float, spacing: float = MARK_SPACING) -> np.ndarray:
    """The marks' places along a rope of ``length``, as fractions of it: evenly, about
    ``spacing`` apart (a rope stretched a little keeps its marks)."""
    count = max(1, round(length / spacing))
    return (np.arange(count) + 0.5) / count


def observe_marks(
    nodes_k3: np.ndarray,
    radius: float,
    *,
    rng: np.random.Generator,
    noise: float,
    spacing: float = MARK_SPACING,
) -> MarkReading:
    """The marks the camera sees on a rope (its true node chain), with per-coordinate noise.

    A mark is hidden where another part of the rope (more than two diameters away along it)
    passes over it in the camera's view: within a diameter in xy and higher.
    """
    nodes = np.asarray(nodes_k3, dtype=float)
    arc_k = arc_lengths(nodes)
    length = float(arc_k[-1])
    fraction_j = mark_fractions(length, spacing)
    centre_j3 = np.stack(
        [np.interp(fraction_j * length, arc_k, nodes[:, d]) for d in range(3)], axis=1
    )
    # The rope's centreline densely, to find a strand over each mark.
    dense_arc = np.linspace(0.0, length, 4 * len(nodes))
    dense_p3 = np.stack([np.interp(dense_arc, arc_k, nodes[:, d]) for d in range(3)], axis=1)
    far_jp = np.abs(dense_arc[None, :] - fraction_j[:, None] * length) > 4.0 * radius
    gap_jp = np.linalg.norm(dense_p3[None, :, :2] - centre_j3[:, None, :2], axis=2)
    over_jp = far_jp & (gap_jp < 2.0 * radius) & (dense_p3[None, :, 2] > centre_j3[:, None, 2])
    seen_j = ~over_jp.any(axis=1)
    top_j3 = centre_j3[seen_j] + np.array([0.0, 0.0, radius])
    top_j3 = top_j3 + rng.normal(0.0, noise, size=top_j3.shape)
    return MarkReading(fraction_j[seen_j], top_j3, radius, len(fraction_j))


def move_to_marks(nodes_k3: np.ndarray, marks: MarkReading) -> np.ndarray:
    """The chain (K, 3) moved so that its points at the marks' places lie where the marks are
    seen.

    Node k is the rope's point at fraction k / (K - 1) of its length (the tracker's chain keeps
    which part of the rope each node is). Each mark in view gives a move: from the chain's point
    at the mark's fraction to the mark's centre (its seen top, one radius down), shrunk by
    ``MARK_DEAD_BAND``. Between two neighbouring marks in view the chain runs straight from one
    moved place to the next; across hidden marks the moves are interpolated along the rope;
    beyond the outermost marks in view the chain slides along itself by the outermost move's
    part along the rope and shifts by the rest. Where no mark is in view it is unchanged.
    """
    nodes = np.asarray(nodes_k3, dtype=float)
    if len(marks) == 0 or len(nodes) < 2:
        return nodes
    fraction_k = np.linspace(0.0, 1.0, len(nodes))
    fraction_j = marks.fraction_j
    on_chain_j3 = np.stack(
        [np.interp(fraction_j, fraction_k, nodes[:, d]) for d in range(3)], axis=1
    )
    move_j3 = marks.centre_j3 - on_chain_j3
    size_j = np.linalg.norm(move_j3, axis=1, keepdims=True)
    move_j3 *= np.maximum(0.0, 1.0 - MARK_DEAD_BAND / np.maximum(size_j, 1e-12))
    moved = nodes + np.stack(
        [np.interp(fraction_k, fraction_j, move_j3[:, d]) for d in range(3)], axis=1
    )
    # Two neighbouring marks hold the rope between them nearly straight (a rope bent to a 5 cm
    # radius bows 7 mm off a 5 cm chord), while the prior's bend there is what the marks say is
    # wrong: interpolated moves left the nodes between marks twice as far off as the nodes at
    # marks, a zigzag along the chain (docs/robustness.md, "A marked rope").
    place_j3 = on_chain_j3 + move_j3
    for j in range(len(marks) - 1):
        if not marks.neighbours(j):
            continue
        between = (fraction_k > fraction_j[j]) & (fraction_k < fraction_j[j + 1])
        w_n1 = ((fraction_k[between] - fraction_j[j]) / (fraction_j[j + 1] - fraction_j[j]))[
            :, None
        ]
        moved[between] = (1.0 - w_n1) * place_j3[j] + w_n1 * place_j3[j + 1]
    # Past the outermost marks in view (a tail under another strand) a held move would carry
    # the tail off the rope wherever that move runs along a bend; a slide keeps its shape.
    arc_k = arc_lengths(nodes)
    for beyond, j in ((fraction_k < fraction_j[0], 0), (fraction_k > fraction_j[-1], -1)):
        if not beyond.any():
            continue
        at = float(np.interp(fraction_j[j], fraction_k, arc_k))
        link = min(int(np.searchsorted(arc_k, at, side="right")) - 1, len(nodes) - 2)
        tangent = nodes[link + 1] - nodes[link]
        tangent /= max(float(np.linalg.norm(tangent)), 1e-12)
        along = float(move_j3[j] @ tangent)
        moved[beyond] = points_at_arc(nodes, arc_k[beyond] + along) + (move_j3[j] - along * tangent)
    return moved
