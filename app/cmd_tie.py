"""`knotlab tie`: tie an overhand knot in a straight simulated rope and draw the result."""

from __future__ import annotations

import argparse
import json
import time

from knotlab.app.options import add_flag, check_output


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `tie` sub-command."""
    parser = subparsers.add_parser(
        "tie",
        help="tie an overhand knot in simulation (fixed 3-step sequence) and write a top-down PNG",
        description="Run the fixed 3-step gripper sequence on a straight rope, check the knot "
        "with the knot invariant, and write a top-down picture. Exit code 0 if knotted.",
    )
    add_flag(parser, "--out", default="knot.png", detail="the PNG (default: knot.png)")
    add_flag(parser, "--force", detail="here: the PNG --out names")
    add_flag(parser, "--json", detail="a summary instead of the text")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Tie the knot; 0 if the final rope is an overhand knot, 1 otherwise."""
    from knotlab.core.atomic import atomic_path
    from knotlab.core.tasks.overhand.knot_sequence import overhand_sequence
    from knotlab.core.world.knot import analyse_knot
    from knotlab.core.world.render import render_topdown
    from knotlab.core.world.rope import straight_rope
    from knotlab.core.world.sim import RopeParams, RopeWorld

    # before the simulation runs
    out = check_output(args.out, force=args.force, kind="picture", suffixes=(".png",))
    params = RopeParams()
    wall0 = time.perf_counter()
    steps = []
    with RopeWorld(params) as world:
        world.reset(straight_rope(params.n_links + 1, params.length, params.radius))
        for i, traj in enumerate(overhand_sequence(params.length, params.radius), start=1):
            result = world.execute(traj)
            knot = analyse_knot(world.rope_nodes())
            steps.append(
                {
                    "step": i,
                    "ok": result.ok,
                    "failure": result.failure,
                    "sim_steps": result.sim_steps,
                    "sim_time_s": round(result.sim_time, 3),
                    "wall_s": round(result.wall_time, 3),
                    "max_stretch": round(result.max_stretch, 4),
                    "crossings": knot.gauss_code,
                }
            )
            if not args.json:
                print(
                    f"step {i}/3: {'ok' if result.ok else result.failure}, "
                    f"{result.sim_steps} steps ({result.sim_time:.1f} s simulated) in "
                    f"{result.wall_time:.2f} s; crossings: {knot.gauss_code or '-'}",
                    flush=True,
                )
        final = analyse_knot(world.rope_nodes())
        verdict = "overhand knot" if final.is_overhand else "no knot"
        with atomic_path(out) as tmp:  # a failed render leaves no half-written picture
            render_topdown(
                world.rope_nodes(), tmp, radius=params.radius, title=f"knotlab tie: {verdict}"
            )
    summary = {
        "knot": final.is_overhand,
        "determinants": list(final.determinants),
        "gauss_code": final.gauss_code,
        "png": str(out),
        "wall_s": round(time.perf_counter() - wall0, 3),
        "steps": steps,
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"{verdict} (knot determinant {final.determinants[0]} over, "
            f"{final.determinants[1]} under) in {summary['wall_s']:.2f} s; wrote {out}"
        )
    return 0 if final.is_overhand else 1
