"""`knotlab serve`: a decision service a robot's controller calls over HTTP (JSON).

POST /v1/rank (a cloud -> the ranked demos with their warped gripper paths), POST /v1/choose (a
policy's choice; lookahead and the oracle need the rope-state estimate), GET /v1/health and
/v1/model; the OpenAPI schema at /openapi.json and browsable docs at /docs. Loopback by default;
any other host needs a bearer token (--token, else $KNOTLAB_TOKEN, else one is generated and
printed).
"""

from __future__ import annotations

import argparse
import socket
import sys
from pathlib import Path

from knotlab.app.cmd_app import LOOPBACK, access_token, check_host
from knotlab.app.options import add_flag, add_task_argument, integer, library_file, task_of

DEFAULT_PORT = 8090
GRACEFUL_S = 3  # Ctrl-C: in-flight requests get this long, then the server stops regardless


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab serve` to the command line."""
    p = subparsers.add_parser(
        "serve",
        help="serve decisions over HTTP: rank demos for a cloud, choose with a policy",
        description=__doc__.split("\n\n")[0],
    )
    add_task_argument(p)
    add_flag(p, "--library", detail="default: the task's shipped library")
    add_flag(
        p,
        "--model",
        metavar="PATH|none",
        detail="default: the task's shipped model; none: nearest neighbour",
    )
    add_flag(p, "--host", default="127.0.0.1", detail="any other host needs a token")
    add_flag(p, "--port", default=DEFAULT_PORT, detail=f"default {DEFAULT_PORT}")
    add_flag(p, "--token", detail="every request carries it as a bearer token")
    add_flag(p, "--workers", type=integer(1, maximum=64), detail="decision processes")
    p.set_defaults(func=run)


def _model_path(args: argparse.Namespace) -> Path | None:
    from knotlab.app import defaults

    if args.model is not None and args.model.lower() == "none":
        return None
    return Path(args.model) if args.model else defaults.model_path(task_of(args))


def run(args: argparse.Namespace) -> int:
    """Check everything, start the warm workers, then serve until Ctrl-C."""
    import uvicorn

    from knotlab.app.service.api import ServiceInfo, create_app
    from knotlab.app.service.pool import DecisionPool
    from knotlab.app.service.workers import ServiceConfig, load_agent
    from knotlab.core.parallel import default_workers
    from knotlab.core.world.observation import ObservationModel

    check_host(args.host, args.port)
    token = access_token(args)
    config = ServiceConfig(Path(library_file(args)), _model_path(args), task_of(args))
    agent = load_agent(config)  # every compatibility check here, in one line, before workers
    info = ServiceInfo(
        task=agent.task.name,
        library_hash=agent.library.content_hash(),
        segments=len(agent.library),
        observation_model=ObservationModel.of_library_metadata(agent.library.metadata).value,
        rope_nodes=agent.library.has_rope_nodes,
        model_hash=None if agent.model is None else agent.model.content_hash(),
        features=None if agent.model is None else agent.model.n_features,
        step_limit=agent.task.step_limit,
    )
    sock = _bind(args.host, args.port)  # a busy port is one line, before workers start
    port = sock.getsockname()[1]
    workers = args.workers or default_workers()
    pool = DecisionPool(config, workers)
    try:
        print(f"starting {workers} decision worker{'s' if workers > 1 else ''}...", flush=True)
        pool.warm()
        app = create_app(pool, info, token=token)
        server = uvicorn.Server(
            uvicorn.Config(
                app,
                host=args.host,
                port=port,
                log_level="warning",
                timeout_graceful_shutdown=GRACEFUL_S,
            )
        )
        host = f"[{args.host}]" if ":" in args.host else args.host
        model = "nearest neighbour" if agent.model is None else f"model {info.model_hash}"
        print(
            f"knotlab serve: http://{host}:{port}/v1 ({info.task}, {model}, "
            f"library {info.library_hash}); docs at /docs  (Ctrl-C stops)",
            flush=True,
        )
        if args.host not in LOOPBACK:
            print(
                f"warning: serving on {args.host}: requests need the bearer token",
                file=sys.stderr,
            )
        server.run(sockets=[sock])
    finally:
        pool.close()
        sock.close()
    return 0


def _bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (0: a free port), or one clear error."""
    from knotlab.core.errors import InvalidInputError

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise InvalidInputError(
            f"--port {port}: cannot listen on {host} ({exc.strerror})"
        ) from None
    sock.listen(128)
    sock.set_inheritable(True)
    return sock
