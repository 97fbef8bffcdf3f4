"""`knotlab demos`: generate, inspect, import and export demonstration libraries.

`import` and `export` move libraries to and from the original system's HDF5 layout (one group
per segment, `<demo>-seg<NN>`), so a lab's own recorded demos can be used and ours read by theirs.
"""

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
    task_of,
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
        "processes (the --task's expert) and keep the first N demos that reach its knot (one "
        "segment per expert step). "
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
    add_flag(
        gen,
        "--observation",
        default=DEFAULT_OBSERVATION.value,
        detail=f"of the library's clouds (default {DEFAULT_OBSERVATION.value})",
    )
    add_flag(gen, "--force", detail="here: the library --out names")
    add_no_progress_argument(gen)
    gen.set_defaults(func=run_generate)
    info = sub.add_parser("info", help="summarise a library file")
    info.add_argument("path", help="library file (.npz)")
    add_flag(info, "--json")
    info.set_defaults(func=run_info)
    imp = sub.add_parser(
        "import",
        help="read a demo library in the original HDF5 layout and write a knotlab library",
        description="Read an HDF5 file with one group per segment (<demo>-seg<NN>: cloud_xyz, "
        "{l,r}_gripper_tool_frame/hmat, {l,r}_gripper_joint, optional rope_nodes and stamps, "
        "description), validate every group and write a knotlab library (.npz). A file that "
        "knotlab exported re-imports to the same content hash.",
    )
    imp.add_argument("path", help="the HDF5 demo file (.h5)")
    add_flag(imp, "--out", required=True, detail="the library (.npz)")
    add_flag(
        imp,
        "--observation",
        default=None,
        detail="of the recorded clouds, so a world is observed the same way (default: cloud; "
        "a knotlab export keeps its own)",
    )
    add_task_argument(imp)
    add_flag(imp, "--force", detail="here: the library --out names")
    add_flag(imp, "--json")
    imp.set_defaults(func=run_import)
    exp = sub.add_parser(
        "export",
        help="write a knotlab library in another format (the original HDF5 layout)",
        description="Write every segment as a <demo>-seg<NN> group of the original HDF5 layout, "
        "with knotlab's additions (key, indices, metadata, rope after) so it re-imports "
        "to the same content hash.",
    )
    exp.add_argument("path", help="the library (.npz)")
    add_flag(exp, "--format", choices=("h5",), default="h5", detail="h5 only (the default)")
    add_flag(exp, "--out", required=True, detail="the HDF5 file (.h5)")
    add_flag(exp, "--force", detail="here: the file --out names")
    add_flag(exp, "--json")
    exp.set_defaults(func=run_export)


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
            task=task_of(args),
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


H5_SUFFIXES = (".h5", ".hdf5")


def run_import(args: argparse.Namespace) -> int:
    """Import an HDF5 demo file and save it as a knotlab library; print a summary."""
    from knotlab.core.interop.h5_demos import import_library_h5

    check_output(args.out, force=args.force, kind="demo library")
    report = import_library_h5(args.path, task=args.task, observation=args.observation)
    lib = report.library
    out = lib.save(args.out)
    summary = {
        "path": str(out),
        "source": str(args.path),
        "segments": len(lib),
        "start_states": len(set(lib.start_indices().tolist())),
        "hash": lib.content_hash(),
        "task": lib.task,
        "native": report.native,
        "rope_nodes": report.has_rope_nodes,
        "timed_from_path": report.timed_from_path,
    }
    if args.json:
        print(json.dumps(summary, sort_keys=True))
        return 0
    print(
        f"wrote {out}: {len(lib)} segments from {summary['start_states']} demos, "
        f"hash {lib.content_hash()}, task {lib.task}"
    )
    if not report.has_rope_nodes:
        print(
            "  no rope_nodes: nearest neighbour and greedy work (registration needs only "
            "clouds); task sets from this library, lookahead and the oracle need rope states"
        )
    if report.timed_from_path:
        print(
            f"  {report.timed_from_path} segments had no stamps: their waypoint times follow "
            "the path at the nominal gripper speed"
        )
    return 0


def run_export(args: argparse.Namespace) -> int:
    """Export a knotlab library to the original HDF5 layout."""
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.interop.h5_demos import export_library_h5

    check_output(args.out, force=args.force, kind="HDF5 demo file", suffixes=H5_SUFFIXES)
    lib = DemoLibrary.load(args.path)
    out = export_library_h5(lib, args.out)
    if args.json:
        print(json.dumps({"path": str(out), "segments": len(lib), "hash": lib.content_hash()}))
        return 0
    print(f"wrote {out}: {len(lib)} segment groups, library hash {lib.content_hash()}")
    return 0
