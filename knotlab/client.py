"""A small Python client of `knotlab serve`, for a robot's controller or a script.

    from knotlab.client import KnotlabClient
    with KnotlabClient("http://127.0.0.1:8090") as kl:
        best = kl.rank(cloud_n3, top_k=5)[0]          # RankedDemo, best first
        traj = best.trajectory                         # WarpedPath: times, poses, grip events
        choice = kl.choose(cloud_n3, policy="la2x5", rope_nodes=nodes_k3)

It needs only httpx and numpy; `WarpedPath.to_gripper_trajectory` builds knotlab's own
trajectory record when knotlab's simulator should execute it. Errors the service answers
(bad input, wrong token, too large) raise `ServiceError` with the service's one sentence.
Shape suffixes: n = cloud points, k = rope nodes, t = waypoints, g = grippers (left, right).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import httpx

    from knotlab.core.world.trajectory import GripperTrajectory

DEFAULT_URL = "http://127.0.0.1:8090"


class ServiceError(RuntimeError):
    """The service refused or failed a request; ``status`` is the HTTP status."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(f"{status}: {message}")
        self.status = status
        self.message = message


@dataclass(frozen=True)
class WarpedPath:
    """A demo's gripper path warped onto the scene: poses, closed flags, grip event times."""

    times_t: np.ndarray  # (T,) seconds
    hmat_gt44: np.ndarray  # (2, T, 4, 4) left and right end-effector poses
    closed_gt: np.ndarray  # (2, T) closed on arrival at each waypoint
    close_times: tuple[tuple[float, ...], tuple[float, ...]]  # grasps, per gripper
    open_times: tuple[tuple[float, ...], tuple[float, ...]]  # releases, per gripper

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> WarpedPath:
        """Read the service's trajectory JSON."""
        grippers = data["grippers"]
        return cls(
            np.asarray(data["times"], dtype=float),
            np.asarray([g["hmat"] for g in grippers], dtype=float),
            np.asarray([g["closed"] for g in grippers], dtype=bool),
            (tuple(grippers[0]["close_times"]), tuple(grippers[1]["close_times"])),
            (tuple(grippers[0]["open_times"]), tuple(grippers[1]["open_times"])),
        )

    def to_gripper_trajectory(self) -> GripperTrajectory:
        """knotlab's trajectory record of this path (to execute it in knotlab's simulator)."""
        from knotlab.core.world.trajectory import GripperTrajectory

        return GripperTrajectory(
            self.times_t, self.hmat_gt44[:, :, :3, 3], self.hmat_gt44[:, :, :3, :3], self.closed_gt
        )


@dataclass(frozen=True)
class RankedDemo:
    """One candidate demo: its key, scores and warped path (None when transfer failed)."""

    rank: int
    demo: str
    demo_index: int
    score: float | None
    q: float | None
    registration_cost: float | None
    trajectory: WarpedPath | None
    failure: str | None

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> RankedDemo:
        """Read one candidate of the service's JSON."""
        traj = data.get("trajectory")
        return cls(
            data["rank"],
            data["demo"],
            data["demo_index"],
            data["score"],
            data["q"],
            data["registration_cost"],
            None if traj is None else WarpedPath.from_json(traj),
            data.get("failure"),
        )


@dataclass(frozen=True)
class Choice:
    """A policy's choice and the scores it chose among."""

    policy: str
    chosen: RankedDemo
    top_scores: tuple[tuple[str, float | None], ...]
    search_ms: float | None
    elapsed_ms: float


class KnotlabClient:
    """Calls a running `knotlab serve` (one HTTP connection pool; use as a context manager)."""

    def __init__(
        self, url: str = DEFAULT_URL, *, token: str | None = None, timeout: float = 120.0
    ) -> None:
        import httpx

        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.url = url.rstrip("/")
        self._http: httpx.Client = httpx.Client(
            base_url=f"{self.url}/v1", headers=headers, timeout=timeout
        )

    def __enter__(self) -> KnotlabClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def _call(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        response: httpx.Response = self._http.request(method, path, json=body)
        if response.status_code >= 400:
            try:
                message = response.json().get("error", response.text)
            except ValueError:
                message = response.text
            raise ServiceError(response.status_code, str(message))
        return response.json()

    def health(self) -> dict[str, Any]:
        """The service's health record (status, workers, uptime, requests served)."""
        return dict(self._call("GET", "/health"))

    def model(self) -> dict[str, Any]:
        """The task, library, model, policies and limits the service decides with."""
        return dict(self._call("GET", "/model"))

    def rank(
        self, cloud_n3: np.ndarray, *, top_k: int = 5, transfer: bool = True
    ) -> list[RankedDemo]:
        """The best ``top_k`` demos for the cloud, best first, with their warped paths."""
        body = {"cloud": np.asarray(cloud_n3, dtype=float).tolist(), "top_k": top_k}
        body["transfer"] = transfer
        data = self._call("POST", "/rank", body)
        return [RankedDemo.from_json(c) for c in data["candidates"]]

    def choose(
        self,
        cloud_n3: np.ndarray,
        *,
        policy: str | None = None,
        rope_nodes_k3: np.ndarray | None = None,
        step_index: int = 0,
    ) -> Choice:
        """A policy's choice (default: the service's); lookahead and the oracle need the
        rope-state estimate ``rope_nodes_k3``."""
        body: dict[str, Any] = {
            "cloud": np.asarray(cloud_n3, dtype=float).tolist(),
            "step_index": step_index,
        }
        if policy is not None:
            body["policy"] = policy
        if rope_nodes_k3 is not None:
            body["rope_nodes"] = np.asarray(rope_nodes_k3, dtype=float).tolist()
        data = self._call("POST", "/choose", body)
        return Choice(
            data["policy"],
            RankedDemo.from_json(data["chosen"]),
            tuple((s["demo"], s["score"]) for s in data["top_scores"]),
            data["search_ms"],
            data["elapsed_ms"],
        )
