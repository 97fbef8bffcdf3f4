"""`knotlab playback EPISODE --out knot.gif`: re-simulate an episode and write an animation."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from knotlab.app import defaults
from knotlab.app.options import (
    add_db_argument,
    add_flag,
    add_task_argument,
    add_task_set_argument,
    check_input,
    check_output,
    db_url,
    integer,
    number,
    reads,
    task_levels,
)


def _store_episode(args: argparse.Namespace, episode_id: int):
    from knotlab.app.episodes import store_episode
    from knotlab.labeling_db.store import open_store

    with open_store(db_url(args), create=False, auto_upgrade=False) as store:
        return store_episode(store, episode_id, args.library or defaults.library_path(args.task))


def _run(args: argparse.Namespace) -> int:
    from knotlab.core.errors import InvalidInputError, KnotlabError
    from knotlab.core.experiments.playback import bench_episode, export_playback
    from knotlab.labeling_db.errors import LabelingDbError

    spec: str = args.episode
    check_output(args.out, force=args.force, kind="animation", suffixes=(".gif", ".mp4"))
    # a --library or --task-set that is not there is refused, not passed over for the run's own
    if args.library is not None:
        check_input(args.library, flag="--library", kind="demo library")
    if args.task_set is not None:
        check_input(args.task_set, flag="--task-set", kind="task set")
    try:
        if spec.startswith("db:"):
            try:
                episode_id = int(spec[3:])
            except ValueError:
                raise InvalidInputError(
                    f"EPISODE {spec!r}: expected db:EPISODE_ID with an integer id"
                ) from None
            episode, library = _store_episode(args, episode_id)
        else:
            parts = spec.rsplit(":", 2)
            if len(parts) != 3 or not all(parts):
                raise InvalidInputError(
                    f"EPISODE {spec!r}: expected RESULTS_DIR:POLICY:TASK_ID or db:ID"
                )
            results_dir, policy, task_id = parts
            shipped_sets = [
                defaults.task_set_path(lv, sp, args.task)
                for lv in task_levels(args.task)
                for sp in ("test", "train")
            ]
            episode, library = bench_episode(
                results_dir,
                policy,
                task_id,
                library_paths=[args.library, defaults.library_path(args.task)],
                task_set_paths=[args.task_set, *shipped_sets],
            )
        out, replay = export_playback(
            episode, library, args.out, fps=args.fps, speed=args.speed, size=args.size
        )
    except (KnotlabError, LabelingDbError, LookupError, OSError) as exc:
        if isinstance(exc, KnotlabError):
            raise
        raise InvalidInputError(str(exc)) from exc
    for w in replay.warnings:
        print(f"knotlab playback: warning: {w}", file=sys.stderr)
    size_kb = Path(out).stat().st_size / 1024
    end = "knot" if replay.knot else "no knot"
    print(f"wrote {out}: {len(replay)} frames at {args.fps:g} fps, {size_kb:.0f} KiB ({end})")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab playback` to the command line."""
    p = subparsers.add_parser(
        "playback",
        help="re-simulate a bench or labelled episode and write a GIF or MP4",
        description=(
            "EPISODE is RESULTS_DIR:POLICY:TASK_ID (a `knotlab bench` results directory) or "
            "db:EPISODE_ID (an episode of the labelling database, see --db). The episode is "
            "re-simulated from its start with the recorded choices and drawn top-down."
        ),
    )
    reads(p.add_argument("episode", metavar="EPISODE"))  # a results folder or a database
    add_flag(p, "--out", required=True, detail="the animation: .gif, or .mp4 (imageio-ffmpeg)")
    add_flag(p, "--force", detail="here: the animation --out names")
    p.add_argument(
        "--fps", type=integer(1, maximum=60), default=20, help="frames per second, 1-60 (20)"
    )
    p.add_argument(
        "--speed",
        type=number(0.0, above=True, maximum=1000.0),
        default=4.0,
        help="simulated seconds per second (default 4)",
    )
    p.add_argument(
        "--size",
        type=integer(64, maximum=2048),
        default=400,
        help="frame width and height, px, 64-2048 (400)",
    )
    add_task_argument(p)
    add_flag(
        p,
        "--library",
        detail="if not the run's recorded one (looked for: the task's shipped library)",
    )
    add_task_set_argument(
        p, "if not the run's recorded one (looked for: the task's shipped sets of every level)"
    )
    add_db_argument(p)
    p.set_defaults(func=_run)
