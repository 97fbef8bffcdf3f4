"""Frames of an execution for animation: rope nodes and gripper positions at fixed sim times."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from knotlab.core.errors import InvalidInputError


@dataclass(frozen=True, eq=False)
class ExecutionFrames:
    """What the rope and grippers looked like every ``dt`` simulated seconds of an execution.

    Shape suffixes: f = frames, k = rope nodes, g = grippers (left, right).
    """

    times_f: np.ndarray  # (F,) s since the execution started
    nodes_fk3: np.ndarray  # (F, K, 3) m
    grippers_fg3: np.ndarray  # (F, 2, 3) m, commanded gripper positions
    closed_fg: np.ndarray  # (F, 2) bool, gripper holding the rope

    def __post_init__(self) -> None:
        n = len(self.times_f)
        if self.nodes_fk3.shape[0] != n or self.grippers_fg3.shape != (n, 2, 3):
            raise InvalidInputError("ExecutionFrames: arrays disagree on the frame count")

    def __len__(self) -> int:
        return len(self.times_f)


# Called with a frame's index and the rope's nodes (K, 3) as just recorded; returns the nodes
# the rope should be moved to, or None to leave it.
FrameCorrection = Callable[[int, np.ndarray], np.ndarray | None]


class FrameRecorder:
    """Collects frames during an execution, ``dt`` simulated seconds apart.

    Another thread may read frames while the simulation appends them (:meth:`frame`,
    ``len``, :meth:`wait_for_frame`): an animation can start playing at the first frame
    instead of after the run.
    """

    def __init__(self, dt: float, correct: FrameCorrection | None = None) -> None:
        if not (np.isfinite(dt) and dt > 0):
            raise InvalidInputError(f"frame interval must be finite and > 0 s, got {dt}")
        self.dt = float(dt)
        # A tracker's correction of a model world it follows (the simulator moves its links to
        # the nodes returned, keeping their velocities); None in a world that only records.
        self.correct = correct
        self.every = 0  # sim steps between frames, set by the world that records
        # Wakes a reader waiting for the next frame (instead of it polling the length).
        self._arrived = threading.Condition()
        self._finished = False
        self._t: list[float] = []
        self._nodes: list[np.ndarray] = []
        self._grippers: list[np.ndarray] = []
        self._closed: list[np.ndarray] = []

    def start(self, timestep: float) -> None:
        """Called by the simulator before stepping: frames every round(dt / timestep) steps."""
        self.every = max(1, round(self.dt / timestep))

    def __len__(self) -> int:
        return len(self._t)

    @property
    def finished(self) -> bool:
        """True once the execution has ended (no frame follows)."""
        return self._finished

    @finished.setter
    def finished(self, value: bool) -> None:
        with self._arrived:
            self._finished = bool(value)
            self._arrived.notify_all()

    def wait_for_frame(self, i: int, timeout: float) -> bool:
        """Wait until frame ``i`` is recorded or the execution has ended, at most ``timeout``
        s; True if frame ``i`` is there."""
        with self._arrived:
            self._arrived.wait_for(lambda: len(self._t) > i or self._finished, timeout)
        return len(self._t) > i

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        del state["_arrived"]  # a lock does not pickle; a copy gets its own
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._arrived = threading.Condition()

    def frame(self, i: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Frame i as (time, nodes_k3, grippers_g3, closed_g)."""
        return self._t[i], self._nodes[i], self._grippers[i], self._closed[i]

    def add(
        self,
        t: float,
        nodes_k3: np.ndarray,
        grippers_g3: np.ndarray,
        closed_g: Sequence[bool] | np.ndarray,
    ) -> None:
        """Append one frame."""
        self._t.append(float(t))
        self._nodes.append(np.asarray(nodes_k3, dtype=np.float32))
        self._grippers.append(np.asarray(grippers_g3, dtype=np.float32))
        self._closed.append(np.asarray(closed_g, dtype=bool))
        with self._arrived:
            self._arrived.notify_all()

    def frames(self) -> ExecutionFrames | None:
        """Everything recorded (None when nothing was recorded)."""
        if not self._t:
            return None
        return ExecutionFrames(
            np.array(self._t),
            np.stack(self._nodes),
            np.stack(self._grippers),
            np.stack(self._closed),
        )
