"""`knotlab tasks`: generate train / test start states by perturbing demo starts, and inspect."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from knotlab.app.options import (
    add_flag,
    add_no_progress_argument,
    add_task_argument,
    check_output,
    integer,
    library_file,
    load_library,
    number,
    resolve_level,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `tasks generate` and `tasks info` sub-commands."""
    parser = subparsers.add_parser("tasks", help="generate or inspect train/test task sets")
    sub = parser.add_subparsers(dest="tasks_command", required=True, metavar="ACTION")
    gen = sub.add_parser(
        "generate",
        help="perturb the library's start ropes (tent model), settle, write train and test sets",
        description="Make start states by tent-perturbing demo start ropes at evenly spaced "
        "centres, settling them in simulation and rejecting self-intersecting ones. Writes "
        "tasks_<level>_train.npz and tasks_<level>_test.npz; train and test seeds are disjoint.",
    )
    gen.add_argument("--train", type=integer(0), default=300, help="train tasks (300)")
    gen.add_argument("--test", type=integer(0), default=500, help="test tasks (500)")
    gen.add_argument(
        "--rho",
        type=number(0.0, above=True),
        default=0.05,
        help="tent peak displacement, m (0.05)",
    )
    add_flag(gen, "--seed", required=True, detail="of the generation")
    gen.add_argument(
        "--centres", type=integer(1), default=7, help="tent centres along the rope (7)"
    )
    add_task_argument(gen)
    add_flag(gen, "--level", detail="here it may name a new level: it goes into the file names")
    add_flag(gen, "--library", detail="whose start ropes to perturb (default: the task's)")
    add_flag(gen, "--out-dir", default=".", detail="the task sets (.)")
    add_flag(gen, "--workers")
    add_flag(gen, "--force", detail="here: task sets already at --out-dir (shipped ones too)")
    add_no_progress_argument(gen)
    gen.set_defaults(func=run_generate)
    info = sub.add_parser("info", help="summarise a task-set file")
    info.add_argument("path", help="task-set file (.npz)")
    add_flag(info, "--json")
    info.set_defaults(func=run_info)


def run_generate(args: argparse.Namespace) -> int:
    """Generate both splits and save them."""
    from knotlab.core.atomic import check_output_dir
    from knotlab.core.demos.tasks import generate_tasks
    from knotlab.core.errors import InvalidInputError

    splits = [(split, n) for split, n in (("train", args.train), ("test", args.test)) if n > 0]
    if not splits:
        raise InvalidInputError("--train and --test are both 0: there is nothing to generate")
    level = resolve_level(args, shipped=False)
    out_dir = check_output_dir(args.out_dir, flag="--out-dir")
    names = [f"tasks_{level}_{split}.npz" for split, _ in splits]
    for name in names:  # every output is checked before the first simulation
        check_output(out_dir / name, flag="--out-dir", force=args.force, kind="task set")
    # and no new file goes into a shipped folder (a task's data) without --force either
    check_output(
        out_dir, flag="--out-dir", force=args.force, kind="folder", folder=True, writes=names
    )
    lib = load_library(library_file(args), args)
    starts = lib.start_states()
    extra = {"library_hash": lib.content_hash()}
    for split, n in splits:
        t0 = time.perf_counter()
        ts = generate_tasks(
            starts,
            n,
            split=split,
            rho=args.rho,
            seed=args.seed,
            n_centres=args.centres,
            level=level,
            workers=args.workers,
            progress=not args.no_progress,
            extra_metadata=extra,
        )
        path = ts.save(out_dir / f"tasks_{level}_{split}.npz")
        print(
            f"wrote {path}: {len(ts)} {split} tasks, rho {args.rho} m, {args.centres} centres, "
            f"hash {ts.content_hash()}; {time.perf_counter() - t0:.1f} s"
        )
    return 0


def summary(ts) -> dict:
    """Counts and settings of a task set (the `tasks info --json` keys)."""
    sources = np.array([t.source_start for t in ts])
    return {
        "tasks": len(ts),
        "split": ts.split,
        "level": ts.metadata.get("level"),
        "rho": ts.metadata.get("rho"),
        "n_centres": ts.metadata.get("n_centres"),
        "seed": ts.metadata.get("seed"),
        "source_starts": int(np.unique(sources).size),
        "rope_nodes": int(ts[0].start_nodes_k3.shape[0]),
        "hash": ts.content_hash(),
        "metadata": ts.metadata,
    }


def run_info(args: argparse.Namespace) -> int:
    """Load (validating) a task set and print its summary."""
    from knotlab.core.demos.tasks import TaskSet

    s = summary(TaskSet.load(args.path))
    if args.json:
        print(json.dumps({"path": str(args.path), **s}, sort_keys=True))
        return 0
    print(f"{args.path}: {s['tasks']} {s['split']} tasks, level {s['level']}, hash {s['hash']}")
    print(
        f"  rho {s['rho']} m, {s['n_centres']} centres, seed {s['seed']}, "
        f"from {s['source_starts']} demo start states, {s['rope_nodes']} rope nodes"
    )
    return 0
