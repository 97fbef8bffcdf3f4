"""`knotlab playback EPISODE --out knot.gif`: re-simulate an episode and write an animation."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from knotlab.app import defaults
from knotlab.app.options import add_db_argument, db_url


def _store_episode(args: argparse.Namespace, episode_id: int):
    from knotlab.app.episodes import store_episode
    from knotlab.labeling_db.store import open_store

    with open_store(db_url(args), create=False, auto_upgrade=False) as store:
        return store_episode(store, episode_id, args.library)


def _run(args: argparse.Namespace) -> int:
    from knotlab.core.errors import InvalidInputError, KnotlabError
    from knotlab.core.experiments.playback import bench_episode, export_playback
    from knotlab.labeling_db.errors import LabelingDbError

    spec: str = args.episode
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
            levels = [
                defaults.task_set_path(lv, sp) for lv in defaults.LEVELS for sp in ("test", "train")
            ]
            episode, library = bench_episode(
                results_dir,
                policy,
                task_id,
                library_paths=[args.library, defaults.LIBRARY_PATH],
                task_set_paths=[args.task_set, *levels],
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
    p.add_argument("episode", metavar="EPISODE")
    p.add_argument("--out", required=True, help="animation file: .gif, or .mp4 (imageio-ffmpeg)")
    p.add_argument("--fps", type=float, default=20.0, help="frames per second (default 20)")
    p.add_argument(
        "--speed", type=float, default=4.0, help="simulated seconds per second (default 4)"
    )
    p.add_argument("--size", type=int, default=400, help="frame width and height, px (400)")
    p.add_argument("--library", default=None, help="demo library, if not the run's recorded one")
    p.add_argument("--task-set", default=None, help="task set, if not the run's recorded one")
    add_db_argument(p)
    p.set_defaults(func=_run)
