"""`knotlab` entry point: one sub-command group per module in app/ (`cmd_*.py`)."""

from __future__ import annotations

import argparse
import importlib
import sys

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
    "knotlab.app.cmd_app",
    "knotlab.app.cmd_suggest",
    "knotlab.app.cmd_playback",
)


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree for every knotlab sub-command."""
    parser = argparse.ArgumentParser(
        prog="knotlab",
        description="Learn which expert demonstration to transfer to a rope, and test it.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the knotlab command line; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
