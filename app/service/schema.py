"""The JSON of `knotlab serve`: requests validated by pydantic, responses as typed models.

These models are the service's contract (served as its OpenAPI schema at /openapi.json).
Lengths are metres, times seconds; a pose is a 4 x 4 homogeneous transform in the world frame.
Non-finite scores (a demo whose registration failed) are sent as null.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat

MAX_CLOUD_POINTS = 20_000  # a voxelised camera cloud of a 1 m rope is a few hundred points
MAX_ROPE_NODES = 2_000
MAX_TOP_K = 50
MAX_BODY_BYTES = 4 * 2**20  # 20 000 points as JSON text is about 1.2 MB

Point = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RankRequest(_Strict):
    """Rank the library's demos for an observed cloud."""

    cloud: list[Point] = Field(
        min_length=10,
        max_length=MAX_CLOUD_POINTS,
        description="the rope as observed, N x 3 metres, in the library's observation model",
    )
    task: str | None = Field(None, max_length=64, description="must be the service's task")
    top_k: int = Field(5, ge=1, le=MAX_TOP_K, description="how many candidates")
    transfer: bool = Field(True, description="warp each candidate's gripper path onto the cloud")
    request_id: str | None = Field(None, max_length=128, description="echoed back")


class ChooseRequest(_Strict):
    """Let a policy choose the demo to transfer."""

    policy: str | None = Field(
        None,
        max_length=16,
        description="nn, greedy, la<D>x<W> (lookahead) or oracle; the last two need rope_nodes "
        "(default: greedy with a model, else nn)",
    )
    cloud: list[Point] = Field(min_length=10, max_length=MAX_CLOUD_POINTS)
    rope_nodes: list[Point] | None = Field(
        None,
        min_length=3,
        max_length=MAX_ROPE_NODES,
        description="the rope-state estimate (K x 3 metres): what a simulating policy plans from",
    )
    step_index: int = Field(0, ge=0, le=100, description="steps already taken in this episode")
    task: str | None = Field(None, max_length=64)
    request_id: str | None = Field(None, max_length=128)


class GripperPath(BaseModel):
    """One gripper's warped poses and when it closes and opens."""

    name: str = Field(description="left or right")
    hmat: list[list[list[float]]] = Field(description="T x 4 x 4 poses")
    closed: list[bool] = Field(description="closed on arrival at each waypoint")
    close_times: list[float] = Field(description="times at which the gripper closes (grasps)")
    open_times: list[float] = Field(description="times at which the gripper opens (releases)")


class Trajectory(BaseModel):
    """A warped demonstration, ready to execute: shared waypoint times and both grippers."""

    times: list[float]
    grippers: list[GripperPath]


class CandidateOut(BaseModel):
    """One ranked demo."""

    rank: int
    demo: str = Field(description="the library's segment key")
    demo_index: int
    score: float | None = Field(description="Q with a model, else minus the registration cost")
    q: float | None
    registration_cost: float | None = Field(description="bidirectional TPS-RPM cost")
    trajectory: Trajectory | None
    failure: str | None = Field(description="why there is no trajectory, if there is none")


class RankResponse(BaseModel):
    """The ranked candidates of one cloud."""

    request_id: str | None
    task: str
    model: str | None = Field(description="the Q-model's content hash; null: nearest neighbour")
    library: str = Field(description="the library's content hash")
    cloud_points: int
    cloud_digest: str = Field(description="digest of the cloud as received (check for mix-ups)")
    candidates: list[CandidateOut]
    elapsed_ms: float
    worker: int = Field(description="the worker process that answered")


class ScoreOut(BaseModel):
    """A demo's score in a decision."""

    demo: str
    score: float | None


class ChooseResponse(BaseModel):
    """A policy's choice."""

    request_id: str | None
    task: str
    policy: str
    chosen: CandidateOut
    top_scores: list[ScoreOut]
    search_ms: float | None
    cloud_digest: str
    elapsed_ms: float
    worker: int


class LibraryInfo(BaseModel):
    """The demo library the service decides with."""

    hash: str
    segments: int
    observation_model: str
    rope_nodes: bool


class ModelInfo(BaseModel):
    """The model and library the service decides with, and what it accepts."""

    task: str
    library: LibraryInfo
    model: str | None
    features: int | None
    policies: list[str]
    default_policy: str
    limits: dict[str, int]
    step_limit: int


class Health(BaseModel):
    """Whether the service answers, with how many workers."""

    status: str
    workers: int
    uptime_s: float
    served: int


class ErrorOut(BaseModel):
    """Every error: one sentence naming the field or the problem."""

    error: str
