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
    task_of,
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
    scans = sub.add_parser(
        "scans",
        help="precompute library-scan summaries of a level's training starts (for Suggest)",
        description="Register the level's training starts in a throw-away labelling store, "
        "exactly as `knotlab app` does, scan each stored start cloud against the library and "
        "write the summaries (registration costs, grasp distances) the app's Suggest scores "
        "them from. Shipped per CPU kind as scans_<level>_train_<kind>.npz (avx512, avx2) beside "
        "the task sets: the app uses a summary only on the kind of CPU that made it.",
    )
    add_task_argument(scans)
    add_flag(scans, "--level")
    add_flag(scans, "--library", detail="default: the task's shipped library")
    add_flag(
        scans, "--model", detail="whose landmark weights to add (the shipped one unless --library)"
    )
    add_flag(scans, "--tasks", detail="a quick check of the first N starts; default: every start")
    add_flag(scans, "--out", detail="default: the task's scans_<level>_train_<this CPU's kind>.npz")
    add_flag(scans, "--force", detail="here: a scans file already at --out (a shipped one too)")
    add_no_progress_argument(scans)
    scans.set_defaults(func=run_scans)
    info = sub.add_parser("info", help="summarise a task-set file")
    info.add_argument("path", help="task-set file (.npz)")
    add_flag(info, "--json")
    info.set_defaults(func=run_info)


def run_scans(args: argparse.Namespace) -> int:
    """Scan every training start of the level as the app stores it; write the summaries."""
    import tempfile
    from pathlib import Path

    from tqdm import tqdm

    from knotlab.app import defaults
    from knotlab.app.options import check_input, task_of
    from knotlab.app.web.resources import load_resources
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.world.sim import RopeWorld
    from knotlab.labeling_db.store import open_store

    task, level = task_of(args), resolve_level(args)
    library = check_input(library_file(args), flag="--library", kind="demo library")
    # The shipped model goes with the shipped library; another library's scans get a model's
    # landmark weights only when --model names one.
    model_path = Path(args.model) if args.model else None
    if model_path is None and not args.library:
        model_path = defaults.model_path(task)
    if model_path is not None:
        check_input(model_path, flag="--model", kind="Q-model")
    out = Path(args.out) if args.out else defaults.scans_path(level, "train", task)
    check_output(out, flag="--out", force=args.force, kind="scans file")
    resources = load_resources(
        library, defaults.task_set_path(level, "train", task), top_k=1, task=task
    )
    t0 = time.perf_counter()
    with (
        tempfile.TemporaryDirectory() as tmp,
        open_store(f"sqlite:///{tmp}/starts.db", create=True) as store,
    ):
        resources.register_starts(store, level)
        starts = store.start_states_to_label()[: args.tasks]
        # Two clouds per start: the stored one (Suggest scores it) and the one a tab observes
        # from the stored rope when it shows the start (it ranks that one; the store keeps
        # clouds in float32, so the two differ in their last bits).
        clouds = [s.cloud_n3 for s in starts]
        nodes = [store.get_state(s.state_id).rope_nodes_k3 for s in starts]
    featurizer = (
        resources.agent.featurizer
        if model_path is None
        else resources.add_model(QModel.load(model_path), str(model_path)).featurizer
    )
    with RopeWorld() as world:
        for rope in nodes:
            world.reset(np.asarray(rope, dtype=float))
            clouds.append(featurizer.observe(world))
    for cloud in tqdm(clouds, desc="scanning starts", disable=args.no_progress):
        resources.start_scans.features(featurizer, cloud)
    resources.start_scans.save(out)
    print(
        f"wrote {len(resources.start_scans)} start-scan summaries of {level} to {out} "
        f"in {time.perf_counter() - t0:.0f} s"
    )
    return 0


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
            task=task_of(args),
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
