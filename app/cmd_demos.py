"""`knotlab demos`: generate the demonstration library with the scripted expert, and inspect one."""

from __future__ import annotations

import argparse
import json

from knotlab.app.options import (
    add_flag,
    add_no_progress_argument,
    add_task_argument,
    check_output,
    integer,
    number,
)
from knotlab.core.world.observation import DEFAULT_OBSERVATION, ObservationModel


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `demos generate` and `demos info` sub-commands."""
    parser = subparsers.add_parser("demos", help="generate or inspect a demonstration library")
    sub = parser.add_subparsers(dest="demos_command", required=True, metavar="ACTION")
    gen = sub.add_parser(
        "generate",
        help="run the scripted expert over seeded start ropes and write a library",
        description="Run the state-aware scripted expert over seeded start ropes in parallel "
        "processes and keep the first N demos that end in an overhand knot (3 segments each). "
        "The same seed gives a bit-identical file for any number of workers.",
    )
    gen.add_argument("--starts", type=integer(1), default=50, help="successful demos to keep (50)")
    add_task_argument(gen)
    add_flag(gen, "--seed", default=0, detail="of the generation (0)")
    add_flag(gen, "--out", required=True, detail="the library (.npz)")
    add_flag(gen, "--workers")
    gen.add_argument(
        "--bend", type=number(0.0), default=0.03, help="start-rope bend amplitude, m (0.03)"
    )
    gen.add_argument(
        "--observation",
        choices=[m.value for m in ObservationModel],
        default=DEFAULT_OBSERVATION.value,
        help="how the rope is perceived: centreline (state estimate, default), cloud (camera "
        "surface cloud), tracked (centreline estimated from the camera cloud)",
    )
    add_flag(gen, "--force", detail="here: the library --out names")
    add_no_progress_argument(gen)
    gen.set_defaults(func=run_generate)
    info = sub.add_parser("info", help="summarise a library file")
    info.add_argument("path", help="library file (.npz)")
    add_flag(info, "--json")
    info.set_defaults(func=run_info)


def run_generate(args: argparse.Namespace) -> int:
    """Generate and save a library; print a one-line summary."""
    from knotlab.core.demos.generation import GenSettings, generate_library

    check_output(args.out, force=args.force, kind="demo library")  # before minutes of simulation

    report = generate_library(
        args.starts,
        GenSettings(
            seed=args.seed,
            bend_amplitude=args.bend,
            observation=ObservationModel.parse(args.observation),
        ),
        workers=args.workers,
        progress=not args.no_progress,
    )
    path = report.library.save(args.out)
    s = report.library.summary()
    print(
        f"wrote {path}: {s['segments']} segments from {s['start_states']} start states "
        f"(per step {s['segments_per_step']}), hash {s['hash']}; expert knotted "
        f"{report.knotted}/{report.candidates} candidates "
        f"({report.knotted / report.candidates:.0%}), failed at step {report.failed_at_step}; "
        f"{report.wall_time:.1f} s"
    )
    return 0


def run_info(args: argparse.Namespace) -> int:
    """Load (validating) a library and print its summary."""
    from knotlab.core.demos.library import DemoLibrary

    lib = DemoLibrary.load(args.path)
    s = lib.summary()
    if args.json:
        print(json.dumps({"path": str(args.path), **s}, sort_keys=True))
        return 0
    print(f"{args.path}: demo library v{s['version']}, hash {s['hash']}")
    print(f"  segments:      {s['segments']}")
    print(f"  start states:  {s['start_states']}")
    meta = s["metadata"]
    per = ", ".join(f"step {k}: {v}" for k, v in s["segments_per_step"].items())
    print(f"  per step:      {per}")
    print(f"  observation:   {ObservationModel.of_library_metadata(meta).value}")
    if "expert_success_rate" in meta:
        print(
            f"  generated:     seed {meta.get('seed')}, expert success "
            f"{meta['candidates_knotted']}/{meta['candidates_tried']} "
            f"({meta['expert_success_rate']:.0%})"
        )
    return 0
