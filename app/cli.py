"""`knotlab` entry point: one sub-command group per module in app/ (`cmd_*.py`).

Errors are reported here, once, for every command: one line ``knotlab <command>: error: ...`` on
stderr, exit code 2 when the input was at fault (bad arguments, missing or corrupt files, bad
database URLs) and 1 when a run on good input failed. ``--debug`` or ``KNOTLAB_DEBUG=1`` shows the
traceback instead.

SIGTERM unwinds a command like Ctrl-C does (files close, worker pools end their workers, a bench
keeps every whole outcome line) and exits with 143, the shell's code for death by SIGTERM.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import NoReturn

# Each module exposes `register(subparsers)` and sets `func` on its parsers.
COMMAND_MODULES: tuple[str, ...] = (
    "knotlab.app.cmd_tie",
    "knotlab.app.cmd_db",
    "knotlab.app.cmd_labels",
    "knotlab.app.cmd_demos",
    "knotlab.app.cmd_tasks",
    "knotlab.app.cmd_label",
    "knotlab.app.cmd_train",
    "knotlab.app.cmd_bench",
    "knotlab.app.cmd_model",
    "knotlab.app.cmd_app",
    "knotlab.app.cmd_suggest",
    "knotlab.app.cmd_playback",
    "knotlab.app.cmd_serve",
)
DEBUG_ENV = "KNOTLAB_DEBUG"
# OS errors on a path the user named: the input is at fault, not the run.
_BAD_PATH_ERRORS = (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError)
TERMINATED_EXIT_CODE = 128 + signal.SIGTERM


class Terminated(BaseException):
    """SIGTERM arrived (unwinding the command that was running)."""

    # A BaseException, like KeyboardInterrupt: no `except Exception` that keeps a long run going
    # past one bad episode may swallow it.


def _raise_terminated(signum: int, frame: FrameType | None) -> NoReturn:
    raise Terminated(signum)


@contextmanager
def sigterm_unwinds() -> Iterator[None]:
    """While inside, SIGTERM raises :class:`Terminated` in the main thread (restored after)."""
    if threading.current_thread() is not threading.main_thread():  # only it may set handlers
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (the usage is one --help away)."""

    def error(self, message: str) -> NoReturn:
        """Print ``<prog>: error: <message>`` and exit with code 2."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def version() -> str:
    """The knotlab version: ``knotlab.__version__``, the one place it is written (pyproject's
    version is read from it too)."""
    from knotlab import __version__

    return __version__


class _VersionAction(argparse.Action):
    """``--version``: print the version and exit."""

    def __init__(self, option_strings: list[str], dest: str, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        """Print ``knotlab VERSION`` on stdout and exit 0."""
        print(f"knotlab {version()}")
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree for every knotlab sub-command."""
    parser = _Parser(
        prog="knotlab",
        description="Learn which expert demonstration to transfer to a rope, and test it.",
    )
    parser.add_argument("--version", action=_VersionAction, help="print the version and exit")
    parser.add_argument(
        "--debug",
        action="store_true",
        help=f"show the traceback of an error instead of one line (also: {DEBUG_ENV}=1)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def command_name(args: argparse.Namespace) -> str:
    """'knotlab demos info' for the parsed arguments of `knotlab demos info ...`."""
    words = [args.command]
    words += [v for k, v in vars(args).items() if k.endswith("_command") and isinstance(v, str)]
    return " ".join(["knotlab", *words])


def describe_error(exc: BaseException) -> tuple[str, int]:
    """The one-line message and exit code an error ends a command with."""
    from knotlab.core.errors import KnotlabError

    if isinstance(exc, KnotlabError):
        return str(exc), exc.exit_code
    if isinstance(exc, OSError):
        # "[Errno 2] No such file or directory: 'x'" -> "x: No such file or directory"
        text = f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc)
        return text, 2 if isinstance(exc, _BAD_PATH_ERRORS) else 1
    return f"unexpected {type(exc).__name__}: {exc} (rerun with --debug for the traceback)", 1


def main(argv: list[str] | None = None) -> int:
    """Run the knotlab command line; returns the process exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, a usage error: argparse already printed
        return exc.code if isinstance(exc.code, int) else 2
    # One BLAS thread in every command, as in the bench's workers: OpenBLAS on two threads
    # rounds some products differently, and a near tie then falls the other way (a replay that
    # misses the knot its episode tied; docs/determinism.md).
    from knotlab.core.parallel import single_thread_blas

    single_thread_blas()
    try:
        with sigterm_unwinds():
            return int(args.func(args) or 0)
    except Terminated:
        print(f"{command_name(args)}: terminated (SIGTERM)", file=sys.stderr)
        return TERMINATED_EXIT_CODE
    except KeyboardInterrupt:  # outputs are atomic: an interrupted command wrote nothing half-way
        print(f"{command_name(args)}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if args.debug or os.environ.get(DEBUG_ENV, "") not in ("", "0"):
            raise
        message, code = describe_error(exc)
        print(f"{command_name(args)}: error: {message}", file=sys.stderr)
        return code


if __name__ == "__main__":
    sys.exit(main())
