"""`knotlab app`: serve the labelling web app (viser) on this machine.

With no flags it is useful at once: the SQLite file knotlab.db is created and migrated, the
shipped library, the level's training starts and the shipped model's oracle labels are
registered in it, and candidates are ranked by the store's active model (on a new store: the
shipped default model, else the newest stored model, else by registration cost).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path

from knotlab.app import defaults
from knotlab.app.options import (
    add_db_argument,
    add_flag,
    add_task_argument,
    db_url,
    integer,
    library_file,
    number,
    resolve_level,
    task_of,
)

LOOPBACK = ("127.0.0.1", "localhost", "::1")


def check_host(host: str, port: int) -> None:
    """Refuse, in one line (exit 2), an address this machine cannot serve on, before anything
    starts: viser would try 1000 ports on it, then wait forever for one to have bound."""
    import errno
    import socket

    from knotlab.core.errors import InvalidInputError

    try:
        infos = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
    except (OSError, UnicodeError) as exc:  # socket.gaierror: a name that does not resolve
        reason = getattr(exc, "strerror", None) or str(exc)
        raise InvalidInputError(f"--host {host}: no such host name or address ({reason})") from None
    problem: OSError | None = None
    for family, kind, proto, _, address in infos:
        try:
            with socket.socket(family, kind, proto) as sock:
                sock.settimeout(2.0)
                sock.bind(address)
            return
        except OSError as exc:
            if exc.errno in (errno.EADDRINUSE, errno.EACCES):
                return  # the address is ours; viser serves on the next free port
            problem = exc
    if problem is not None and problem.errno == errno.EADDRNOTAVAIL:
        raise InvalidInputError(
            f"--host {host}: this machine has no such address (give one of its own addresses, "
            "127.0.0.1 for this machine only, or 0.0.0.0 for every network)"
        )
    reason = problem.strerror if problem is not None else "no address to bind"
    raise InvalidInputError(f"--host {host}: cannot serve on it ({reason})")


def check_model_arg(model: str | None, url: str) -> None:
    """Refuse, in one line (exit 2), a --model that is neither a file nor a model version stored
    in the database, before the database is created or a start registered in it."""
    if model is None or Path(model).exists():
        return
    from knotlab.core.errors import InvalidInputError
    from knotlab.labeling_db.errors import DatabaseNotFoundError, LabelingDbError
    from knotlab.labeling_db.store import open_store

    try:
        with open_store(url, create=False, auto_upgrade=False) as store:
            versions = [m.version for m in store.list_models()]
    except DatabaseNotFoundError:
        versions = []  # no database yet: nothing stored
    except LabelingDbError:
        return  # an old schema, a server down: opening the store says so, and load_models checks
    if model not in versions:
        raise InvalidInputError(
            f"--model {model!r} is neither a model file nor a stored model version "
            f"(stored: {', '.join(versions) or 'none'})"
        )


def build_app(args: argparse.Namespace, *, lite_rendering: bool = False):
    """Open the store, load library, starts and models, and start serving; returns the app."""
    from knotlab.app.web.resources import load_resources
    from knotlab.app.web.server import LabelApp, load_models
    from knotlab.core.parallel import single_thread_blas
    from knotlab.labeling_db.store import open_store

    # One BLAS thread in the app and the workers it spawns (they inherit the environment), also
    # when the app is built without the command line (tests, bench/app_latency.py): the tabs'
    # threads call numpy's LAPACK at once, and a two-thread BLAS pool per call makes them spin
    # against each other and the browser on a 2-core box.
    single_thread_blas()

    task, level = task_of(args), resolve_level(args)
    library_path = library_file(args)
    check_model_arg(getattr(args, "model", None), db_url(args))
    resources = load_resources(
        library_path,
        defaults.task_set_path(level, "train", task),
        top_k=args.top,
        overlap=getattr(args, "overlap", 0.0),
        task=task,
    )
    print(resources.load_start_scans(defaults.scans_path(level, "train", task)))
    store = open_store(db_url(args), create=True, auto_upgrade=True, persistent=True)
    try:
        store.check_task(task)  # a store holding another task's labels is refused
    except BaseException:
        store.close()
        raise
    added = resources.register_starts(store, level)
    if added:
        print(f"registered {added} {level} training starts in {store.url}")
    ranking = load_models(resources, store, args.model, defaults.model_path(task))
    print(f"ranking candidates with {ranking}")
    print("warming up the registration kernel...", flush=True)
    resources.warm_up()
    return LabelApp(
        store,
        resources,
        library_path,
        host=args.host,
        port=args.port,
        lite_rendering=lite_rendering,
        sim_workers=args.sim_workers,
        test_tasks_path=defaults.task_set_path(level, "test", task),
        token=access_token(args),
    )


TOKEN_ENV = "KNOTLAB_TOKEN"


def access_token(args: argparse.Namespace) -> str | None:
    """The access token of the app or the service: --token, else $KNOTLAB_TOKEN, else (on a
    host other than loopback) one generated and printed; None on loopback without one."""
    import os
    import secrets

    token = args.token or os.environ.get(TOKEN_ENV) or None
    if token is None and args.host not in LOOPBACK:
        token = secrets.token_urlsafe(24)
        print(f"generated an access token (pass --token to choose one): {token}", flush=True)
    return token


def _run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    check_host(args.host, args.port)  # before the store, the resources and the server
    if args.host not in LOOPBACK:
        print(
            f"warning: serving on {args.host}: anyone on that network who has the access "
            "token can label with your database",
            file=sys.stderr,
        )
    # Ctrl-C interrupts the start-up too (exit 130), even in a process that inherited SIGINT
    # as ignored (a shell's `&`).
    main_thread = threading.current_thread() is threading.main_thread()
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler) if main_thread else None
    try:
        app = build_app(args, lite_rendering=args.lite_rendering)  # bad input: one line
    finally:
        if inherited is not None:
            signal.signal(signal.SIGINT, inherited)
    if app.server.get_port() != args.port and args.port != 0:
        print(f"note: port {args.port} was busy; serving on {app.server.get_port()}")
    stop = threading.Event()
    # Both set explicitly: a server started in the background (a shell's `&`, a test runner)
    # inherits SIGINT as ignored, and Ctrl-C must still stop it cleanly.
    previous = {
        sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)
    }
    # Only now announce the URL: whoever reads it may press Ctrl-C at once.
    asked = "; the access token is asked once per browser" if app.token else ""
    print(f"knotlab app: labelling at {app.url}  (Ctrl-C stops{asked})", flush=True)
    try:
        while not stop.is_set():
            time.sleep(0.2)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("stopping: closing tabs (no half-written labels)...", flush=True)
    app.stop()
    app.store.close()
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab app` to the command line."""
    p = subparsers.add_parser(
        "app",
        help="serve the labelling web app (experts label in a browser)",
        description=__doc__.split("\n\n")[0],
    )
    add_db_argument(p)
    add_task_argument(p)
    add_flag(p, "--library", detail="default: the task's shipped library")
    add_flag(p, "--level", detail="whose training starts to label")
    add_flag(
        p,
        "--model",
        metavar="VERSION|PATH",
        detail="a stored model version or a model file, made the active one (default: the "
        "store's active model; a new store starts with the task's shipped default)",
    )
    add_flag(p, "--host", default="127.0.0.1", detail="any other host needs an access token")
    add_flag(p, "--token", detail="each browser gives it once")
    add_flag(p, "--port", default=8080, detail="8080 unless given; a busy one: the next free")
    add_flag(
        p,
        "--top",
        type=integer(1, maximum=9),
        default=5,
        detail="shown to the labeller, 1-9: its hotkeys (5)",
    )
    p.add_argument(
        "--overlap",
        type=number(minimum=0.0, maximum=1.0),
        default=0.0,
        help="share of training starts also offered to a second labeller, for agreement "
        "statistics (seeded per start; default 0)",
    )
    p.add_argument(
        "--sim-workers",
        type=integer(0),
        default=2,
        help="processes that simulate tries for all tabs (0: in the server process)",
    )
    p.add_argument(
        "--lite-rendering",
        action="store_true",
        help="no environment map or shadows (software WebGL, e.g. headless browsers)",
    )
    p.set_defaults(func=_run)
