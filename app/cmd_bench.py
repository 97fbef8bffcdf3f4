"""`knotlab bench`: Table I — run policies on a level's test tasks, resumably, in parallel."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from knotlab.app import defaults
from knotlab.app.options import (
    add_flag,
    add_no_progress_argument,
    add_task_argument,
    add_task_set_argument,
    bounded,
    check_output,
    integer,
    library_file,
    load_library,
    load_task_set,
    number,
    reads,
    task_set_file,
)
from knotlab.core.jsonsafe import json_safe
from knotlab.core.tasks import DEFAULT_TASK

if TYPE_CHECKING:  # core.experiments.bench loads the simulator: imported when a bench runs
    from knotlab.core.experiments.bench import Engine

# core.experiments.bench.ENGINES, spelled out so that building the parser stays light.
_ENGINE_CHOICES: tuple[Engine, ...] = ("local", "ray")

# Lookahead policies la<D>x<W> beyond these simulate width**depth candidates per step: a typo
# like la99x99 would run for ever, so it is refused when the command line is read.
MAX_LOOKAHEAD_DEPTH = 5
MAX_LOOKAHEAD_WIDTH = 50


@bounded("K >= 1 tasks, or POLICY=K with K >= 1")
def task_limits(text: str) -> int | dict[str, int]:
    """argparse type of --first: K, or POLICY=K[,POLICY=K...] (one-line message otherwise)."""
    if "=" not in text:
        return integer(1)(text)
    limits: dict[str, int] = {}
    for part in text.split(","):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or not name:
            raise argparse.ArgumentTypeError(f"expected K or POLICY=K[,POLICY=K...], got {text!r}")
        if name in limits:
            raise argparse.ArgumentTypeError(f"--first names {name!r} twice")
        limits[name] = integer(1)(value.strip())
    return limits


@bounded(f"lookahead depth 1-{MAX_LOOKAHEAD_DEPTH}, width 1-{MAX_LOOKAHEAD_WIDTH}")
def policy_list(text: str) -> list[str]:
    """argparse type of --policies: known policy names, lookahead within the bounds above."""
    from knotlab.core.errors import KnotlabError
    from knotlab.core.selection.policies import policy_config

    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected comma-separated policy names, got {text!r}")
    for name in names:
        try:
            config = policy_config(name)
        except KnotlabError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        if config.kind in ("lookahead", "robust", "adaptive") and not (
            config.depth <= MAX_LOOKAHEAD_DEPTH and config.width <= MAX_LOOKAHEAD_WIDTH
        ):
            raise argparse.ArgumentTypeError(
                f"{name}: lookahead depth must be 1-{MAX_LOOKAHEAD_DEPTH} and width "
                f"1-{MAX_LOOKAHEAD_WIDTH}, got depth {config.depth}, width {config.width}"
            )
    return names


def physics_setting(text: str) -> str:
    """argparse type of --world-params/--model-params: a setting name or a .json file, checked
    now (the combined setting's draws are seeded with --seed when the bench runs)."""
    from knotlab.core.errors import KnotlabError
    from knotlab.core.world.mismatch import parse_setting

    try:
        parse_setting(text)
    except KnotlabError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def world_setting(text: str) -> str:
    """argparse type of --world-params: a physics setting that is a world ("measured" names an
    agent's model that measures the rope, not a world)."""
    if text.strip() == "measured":
        raise argparse.ArgumentTypeError(
            "'measured' is an agent model (--model-params), not a world; the world it measures "
            "is nominal"
        )
    return physics_setting(text)


DEFAULT_POLICIES = "nn,greedy,la1x10,la2x5,oracle"


def resolve_model_path(arg: str | None, out_dir: Path, task: str = DEFAULT_TASK) -> Path | None:
    """--model, else OUT/model.npz, else the task's shipped default model; None when neither
    exists."""
    if arg is not None:
        return Path(arg)
    for candidate in (out_dir / "model.npz", defaults.model_path(task)):
        if candidate.exists():
            return candidate
    return None


def _run(args: argparse.Namespace) -> int:
    from knotlab.core.errors import InvalidInputError
    from knotlab.core.experiments.bench import (
        CHART_FILE,
        OUTCOMES_FILE,
        RESULTS_FILE,
        RUN_FILE,
        format_table,
        needs_model,
        own_results_dir,
        run_bench,
        validate_policies,
    )
    from knotlab.core.selection.qmodel import QModel

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    policies: list[str] = args.policies
    engine: Engine = args.engine
    validate_policies(policies)
    out_dir = check_output(  # its own results folder resumes; another folder needs --force
        args.out_dir,
        flag="--out-dir",
        force=args.force,
        kind="results folder",
        folder=True,
        writes=(OUTCOMES_FILE, RUN_FILE, RESULTS_FILE, CHART_FILE),
        resume=own_results_dir,
    )
    library_path = library_file(args)
    task_path = task_set_file(args, "test")
    try:
        library = load_library(library_path, args)
        task_set = load_task_set(task_path, args)
    except FileNotFoundError as exc:
        hint = "make it with `knotlab demos` / `knotlab tasks`, or pass a path"
        raise FileNotFoundError(f"{exc} ({hint})") from exc
    model = None
    model_path: Path | None = None
    learned = [p for p in policies if needs_model(p)]
    if learned:
        model_path = resolve_model_path(args.model, out_dir, args.task)
        if model_path is None or not model_path.exists():
            where = model_path or f"{out_dir / 'model.npz'} or {defaults.model_path(args.task)}"
            raise InvalidInputError(
                f"policies {', '.join(learned)} need a trained model and there is none at "
                f"{where}: run `knotlab train --out PATH` first (on the TRAIN labels), "
                "then pass --model PATH"
            )
        model = QModel.load(model_path)
    arguments = {
        "policies": policies,
        "task": args.task,
        "tasks": args.tasks,
        "level": args.level,
        "out": str(out_dir),
        "library": str(library_path),
        "task_set": str(task_path),
        "model": str(model_path) if model_path else None,
        "workers": args.workers,
        "engine": engine,
        "seed": args.seed,
        "noise": args.noise,
        "first": args.first,
        "max_steps": args.max_steps,
        "share_simulations": args.share_simulations,
        "argv": sys.argv,
    }
    from knotlab.core.world.estimate import EstimatorKind
    from knotlab.core.world.mismatch import parse_setting

    world = parse_setting(args.world_params, seed=args.seed)
    agent_model = parse_setting(args.model_params, seed=args.seed)
    estimator = EstimatorKind.parse(args.estimator)
    arguments.update(
        world_params=args.world_params, model_params=args.model_params, estimator=args.estimator
    )
    n_tasks = min(args.tasks, len(task_set))
    result = run_bench(
        out_dir,
        library=library,
        task_set=task_set,
        policies=policies,
        n_tasks=n_tasks,
        model=model,
        seed=args.seed,
        noise=args.noise,
        max_steps=args.max_steps,
        first=args.first,
        workers=args.workers,
        engine=engine,
        ray_address=args.ray_address,
        progress=not args.no_progress,
        arguments=arguments,
        share_simulations=args.share_simulations,
        world=world,
        agent_model=agent_model,
        estimator=estimator,
    )
    level = task_set.metadata.get("level", args.level)
    print(
        f"knotlab bench: {level} test, {n_tasks} tasks, {result.ran} episodes run, "
        f"{result.skipped} resumed from {result.paths['outcomes']}, {result.wall_s:.1f} s"
    )
    print(
        format_table(
            result.rows, f"Table I ({level} level, success = knot within {result.max_steps} steps)"
        )
    )
    if result.common_rows is not None:
        n_common = min(r["n"] for r in result.rows)
        print()
        print(format_table(result.common_rows, f"Table I on the first {n_common} tasks only"))
    print(f"results: {result.paths['results']}   chart: {result.paths['chart']}")
    if args.json:
        summary = {
            "results": result.paths["results"],
            "chart": result.paths["chart"],
            "ran": result.ran,
            "resumed": result.skipped,
            "wall_s": round(result.wall_s, 3),
            "table": result.rows,
        }
        print(json.dumps(json_safe(summary)))
    errored = {
        p: sum(r["failure_kind"] == "error" for r in recs) for p, recs in result.outcomes.items()
    }
    if any(errored.values()):
        first_error = next(
            r["error"]
            for recs in result.outcomes.values()
            for r in recs
            if r["failure_kind"] == "error"
        )
        print(
            "knotlab bench: error: episodes errored, so this is not a result "
            f"({', '.join(f'{p}: {n}' for p, n in errored.items() if n)}); first: {first_error}",
            file=sys.stderr,
        )
        return 1
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `knotlab bench` to the command line."""
    p = subparsers.add_parser(
        "bench",
        help="Table I: success rates of demo-selection policies on the test tasks",
        description=(
            "Run each policy on the first --tasks tasks of a level's TEST set and print Table I. "
            "Resumable: rerunning with the same --out-dir skips finished (policy, task) episodes."
        ),
    )
    p.add_argument(
        "--policies",
        type=policy_list,
        default=DEFAULT_POLICIES,
        help=f"comma-separated: nn, greedy, la<D>x<W> (D <= {MAX_LOOKAHEAD_DEPTH}, "
        f"W <= {MAX_LOOKAHEAD_WIDTH}), oracle; in a world unlike the model also the robust "
        "rla<D>x<W>k<K>[min][s<P>] and the adaptive ala<D>x<W>k<K>[s<P>] (P: the members' "
        "spread in %%, default 25) "
        f"(default {DEFAULT_POLICIES})",
    )
    add_flag(p, "--tasks", default=500, detail="the test set's (default 500)")
    add_task_argument(p)
    add_flag(p, "--level")
    # `--out DIR`, the spelling before output folders were --out-dir, still works: argparse
    # takes a unique prefix of a flag for the flag (tests/app/test_cli_flags.py holds it)
    add_flag(
        p, "--out-dir", required=True, detail="the results (resumed if it is a run's own folder)"
    )
    add_flag(p, "--force", detail="here: the --out-dir folder (needed to resume one in results/)")
    add_flag(
        p,
        "--model",
        detail="greedy's and lookahead's (default OUT_DIR/model.npz, else the task's shipped one)",
    )
    add_flag(p, "--library", detail="default: the task's shipped library")
    add_task_set_argument(p, "the test starts (default: the task's shipped set of the level)")
    add_flag(p, "--workers", detail="or Ray actors")
    p.add_argument("--engine", choices=_ENGINE_CHOICES, default="local")
    p.add_argument(
        "--share-simulations",
        action="store_true",
        help="run each task's policies on one worker and simulate an execution once for all of "
        "them (the same outcomes, ~30%% less time; decision times then reflect the sharing)",
    )
    p.add_argument(
        "--ray-address", default=None, help="Ray cluster address (default: start a local Ray)"
    )
    add_flag(p, "--seed", default=0, detail="of the observation noise (0)")
    p.add_argument(
        "--noise", type=number(0.0), default=0.0, help="observation noise sigma, metres (default 0)"
    )
    p.add_argument(
        "--first",
        type=task_limits,
        default=None,
        metavar="K | POLICY=K,...",
        help="K: run the search policies (la*, oracle) on the first K tasks only; "
        "POLICY=K,...: those policies on their first K, the others on all (default: all)",
    )
    p.add_argument(
        "--max-steps",
        type=integer(1),
        default=None,
        help="steps per episode (default: the task's step limit; the overhand knot's 5, the "
        "paper's)",
    )
    reads(
        p.add_argument(
            "--world-params",
            type=world_setting,
            default="nominal",
            metavar="NAME|FILE.json",
            help="the physics of the world that executes: nominal, FACTOR+PCT or FACTOR-PCT (e.g. "
            "mass+25, table_friction-50), combinedPCT (every factor drawn per task within +-PCT, "
            "seeded by --seed and the task), or a JSON file of rope/gripper values "
            "(default nominal)",
        )
    )
    reads(
        p.add_argument(
            "--model-params",
            type=physics_setting,
            default="nominal",
            metavar="NAME|FILE.json",
            help="the physics the agent simulates with (lookahead, oracle, the tracker's "
            "prediction), same forms (default nominal)",
        )
    )
    p.add_argument(
        "--estimator",
        choices=(
            "perfect",
            "tracker",
            "video",
            "tracker_ends",
            "video_ends",
            "tracker_marked",
            "video_marked",
        ),
        default="perfect",
        help="how the agent knows the rope's state: perfect (the world's own state), tracker "
        "(its previous estimate carried through each executed step and pulled to the camera "
        "cloud once a step), video (the same tracker following the camera at 30 frames a "
        "second during each motion), or either with _ends (its chain also slid along the rope "
        "to the cloud's two visible ends at each decision) or with _marked (on a rope marked every "
        "5 cm: its chain also moved to the marks in view at each decision); the "
        "trackers need a centreline library (default perfect)",
    )
    add_no_progress_argument(p)
    add_flag(p, "--json", detail="a summary after the text")
    p.set_defaults(func=_run)
