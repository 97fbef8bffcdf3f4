"""`knotlab serve`'s HTTP API: rank, choose, health and model, on FastAPI.

FastAPI because its request models validate every field and answer a bad one with a 4xx naming
it, and it serves its OpenAPI schema and docs from the same models; uvicorn runs it. The routes
only validate, dispatch to the decision pool and shape JSON: every decision is made by one
worker's Agent (`app.service.workers`).
"""

from __future__ import annotations

import hmac
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from knotlab.app.service.pool import DecisionPool, WorkerLostError
from knotlab.app.service.schema import (
    MAX_BODY_BYTES,
    MAX_CLOUD_POINTS,
    MAX_ROPE_NODES,
    MAX_TOP_K,
    CandidateOut,
    ChooseRequest,
    ChooseResponse,
    ErrorOut,
    GripperPath,
    Health,
    LibraryInfo,
    ModelInfo,
    RankRequest,
    RankResponse,
    ScoreOut,
    Trajectory,
)
from knotlab.app.service.workers import ChooseResult, RankResult, choose_job, rank_job
from knotlab.core.agent import Candidate
from knotlab.core.errors import KnotlabError
from knotlab.core.selection.policies import policy_config
from knotlab.core.world.trajectory import GRIPPERS, GripperTrajectory

API = "/v1"


@dataclass(frozen=True)
class ServiceInfo:
    """What the service says about itself (read once from the library and model)."""

    task: str
    library_hash: str
    segments: int
    observation_model: str
    rope_nodes: bool
    model_hash: str | None
    features: int | None
    step_limit: int

    @property
    def default_policy(self) -> str:
        """greedy with a model, else nearest neighbour."""
        return "nn" if self.model_hash is None else "greedy"


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def trajectory_out(traj: GripperTrajectory) -> Trajectory:
    """A trajectory as JSON-ready poses, flags and grasp/release times."""
    times = traj.times_t
    grippers = []
    for g, name in enumerate(GRIPPERS):
        hmat = np.zeros((traj.n_waypoints, 4, 4))
        hmat[:, :3, :3] = traj.rotations_gt33[g]
        hmat[:, :3, 3] = traj.positions_gt3[g]
        hmat[:, 3, 3] = 1.0
        closed = traj.closed_gt[g]
        before = np.concatenate([[False], closed[:-1]])
        grippers.append(
            GripperPath(
                name=name,
                hmat=hmat.tolist(),
                closed=closed.tolist(),
                close_times=times[closed & ~before].tolist(),
                open_times=times[~closed & before].tolist(),
            )
        )
    return Trajectory(times=times.tolist(), grippers=grippers)


def candidate_out(c: Candidate) -> CandidateOut:
    """A ranked candidate as JSON."""
    return CandidateOut(
        rank=c.rank,
        demo=c.demo_key,
        demo_index=c.demo_index,
        score=_finite(c.score),
        q=_finite(c.q),
        registration_cost=_finite(c.nn_cost),
        trajectory=None if c.trajectory is None else trajectory_out(c.trajectory),
        failure=c.failure,
    )


def _error(status: int, message: str) -> JSONResponse:
    return JSONResponse(ErrorOut(error=message).model_dump(), status_code=status)


def _field(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc if p != "body"]
    return ".".join(parts) or "body"


class BodyLimit:
    """Refuse request bodies over ``limit`` bytes (413), declared or streamed, before parsing."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            await _error(413, self._message(int(declared)))(scope, receive, send)
            return
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.limit:
                raise _TooLargeError(seen)
            return message

        try:
            await self.app(scope, counted, send)
        except _TooLargeError as exc:
            await _error(413, self._message(exc.size))(scope, receive, send)

    def _message(self, size: int) -> str:
        return f"request body of {size} bytes exceeds the limit of {self.limit} bytes"


class _TooLargeError(Exception):
    def __init__(self, size: int) -> None:
        super().__init__(size)
        self.size = size


def create_app(pool: DecisionPool, info: ServiceInfo, *, token: str | None = None) -> FastAPI:
    """The service's ASGI app over a warm decision pool."""
    app = FastAPI(
        title="knotlab decision service",
        version="1",
        description="Which demonstration to transfer to a rope, and its warped gripper path.",
    )
    started = time.monotonic()
    served = [0]

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        if any(e.get("type") == "json_invalid" for e in errors):
            return _error(422, "body: not valid JSON")
        first = "; ".join(f"{_field(tuple(e['loc']))}: {e['msg']}" for e in errors[:3])
        more = f" (and {len(errors) - 3} more)" if len(errors) > 3 else ""
        return _error(422, first + more)

    @app.middleware("http")
    async def authorise(request: Request, call_next: Callable[[Request], Awaitable[Any]]) -> Any:
        if token is not None:
            given = request.headers.get("authorization", "")
            if not hmac.compare_digest(given.encode(), f"Bearer {token}".encode()):
                response = _error(401, "missing or wrong bearer token (Authorization: Bearer ...)")
                response.headers["WWW-Authenticate"] = "Bearer"
                return response
        return await call_next(request)

    def check_task(task: str | None) -> None:
        if task is not None and task != info.task:
            raise _RefusedError(422, f"task: this service decides for {info.task!r}, not {task!r}")

    async def run(fn: Callable[..., Any], *args: object) -> Any:
        try:
            result = await pool.run(fn, *args)
        except KnotlabError as exc:
            raise _RefusedError(422, str(exc)) from None
        except WorkerLostError as exc:
            raise _RefusedError(503, str(exc)) from None
        served[0] += 1
        return result

    @app.exception_handler(_RefusedError)
    async def refused(_: Request, exc: _RefusedError) -> JSONResponse:
        return _error(exc.status, exc.message)

    responses: dict[int | str, dict[str, Any]] = {
        code: {"model": ErrorOut} for code in (401, 413, 422, 503)
    }

    @app.post(f"{API}/rank", response_model=RankResponse, responses=responses)
    async def rank(req: RankRequest) -> RankResponse:
        """The library's best demos for the cloud, each with its gripper path warped onto it."""
        check_task(req.task)
        result: RankResult = await run(rank_job, req.cloud, req.top_k, req.transfer)
        return RankResponse(
            request_id=req.request_id,
            task=info.task,
            model=info.model_hash,
            library=info.library_hash,
            cloud_points=len(req.cloud),
            cloud_digest=result.cloud_digest,
            candidates=[candidate_out(c) for c in result.candidates],
            elapsed_ms=1000 * result.elapsed_s,
            worker=result.worker_pid,
        )

    @app.post(f"{API}/choose", response_model=ChooseResponse, responses=responses)
    async def choose(req: ChooseRequest) -> ChooseResponse:
        """A policy's choice; lookahead and the oracle plan from ``rope_nodes``."""
        check_task(req.task)
        try:
            policy = policy_config(req.policy or info.default_policy)
        except KnotlabError as exc:
            raise _RefusedError(422, f"policy: {exc}") from None
        if policy.kind == "adaptive":  # its model estimate lives across an episode's calls
            raise _RefusedError(
                422,
                f"policy: {policy.name!r} re-estimates its model from an episode's earlier "
                "steps, which a stateless service does not keep: use la<D>x<W> or rla<D>x<W>k<K>",
            )
        if info.model_hash is None and policy.needs_model:
            raise _RefusedError(
                422, f"policy: {policy.name!r} needs a Q-model and this service has none"
            )
        result: ChooseResult = await run(
            choose_job, policy.name, req.cloud, req.rope_nodes, req.step_index
        )
        return ChooseResponse(
            request_id=req.request_id,
            task=info.task,
            policy=result.policy,
            chosen=candidate_out(result.chosen),
            top_scores=[ScoreOut(demo=d, score=_finite(s)) for d, s in result.top_scores],
            search_ms=None if result.search_s is None else 1000 * result.search_s,
            cloud_digest=result.cloud_digest,
            elapsed_ms=1000 * result.elapsed_s,
            worker=result.worker_pid,
        )

    @app.get(f"{API}/health", response_model=Health)
    async def health() -> Health:
        """Whether the service answers."""
        return Health(
            status="ok",
            workers=pool.workers,
            uptime_s=time.monotonic() - started,
            served=served[0],
        )

    @app.get(f"{API}/model", response_model=ModelInfo)
    async def model() -> ModelInfo:
        """The task, library and model decisions are made with, and the request limits."""
        learned = info.model_hash is not None
        return ModelInfo(
            task=info.task,
            library=LibraryInfo(
                hash=info.library_hash,
                segments=info.segments,
                observation_model=info.observation_model,
                rope_nodes=info.rope_nodes,
            ),
            model=info.model_hash,
            features=info.features,
            policies=(["nn", "greedy", "la<D>x<W>", "oracle"] if learned else ["nn", "oracle"]),
            default_policy=info.default_policy,
            limits={
                "cloud_points": MAX_CLOUD_POINTS,
                "rope_nodes": MAX_ROPE_NODES,
                "top_k": MAX_TOP_K,
                "body_bytes": MAX_BODY_BYTES,
            },
            step_limit=info.step_limit,
        )

    app.add_middleware(BodyLimit, limit=MAX_BODY_BYTES)
    return app


class _RefusedError(Exception):
    """A request the service answers with an error status and one sentence."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
