"""Rope simulation speed: steps/s dragged and at rest, snapshot+restore, the 3-step knot sequence.

Usage: python bench/sim_speed.py [--repeats 5] [--json]
Prints a table of medians over repeats (CPU time of this process, and wall time) with the
machine's details; with --json also the same figures as one JSON object on the last line.
Targets: >= 2,000 steps/s with the rope dragged, <= 2 s per 3-step sequence.
"""

from __future__ import annotations

import os

# One BLAS thread: the benchmark measures the simulator, not BLAS contention on shared cores.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from importlib import metadata  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.core.machine import cpu_model, machine_line  # noqa: E402
from knotlab.core.tasks.overhand.knot_sequence import overhand_sequence  # noqa: E402
from knotlab.core.world.knot import is_overhand_knot  # noqa: E402
from knotlab.core.world.rope import straight_rope  # noqa: E402
from knotlab.core.world.sim import RopeWorld  # noqa: E402
from knotlab.core.world.trajectory import GripperTrajectory, down_rotation  # noqa: E402


def _drag_trajectory() -> GripperTrajectory:
    """End B dragged in a 0.3 m/s square on the table, 4 s of motion (no settling counted)."""
    corners = np.array(
        [
            [0.4875, 0, 0.01],
            [0.4875, 0, 0.05],
            [0.2, 0.3, 0.05],
            [-0.1, 0.0, 0.05],
            [0.2, -0.3, 0.05],
        ]
    )
    n_t = len(corners)
    times = np.concatenate(
        [[0.0], np.cumsum(np.linalg.norm(np.diff(corners, axis=0), axis=1) / 0.3)]
    )
    pos = np.stack([np.tile([-0.7, 0.4, 0.3], (n_t, 1)), corners])
    closed = np.stack([np.zeros(n_t, bool), np.ones(n_t, bool)])
    return GripperTrajectory(times, pos, np.broadcast_to(down_rotation(), (2, n_t, 3, 3)), closed)


def _timed(fn) -> tuple[float, float, object]:
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn()
    return time.process_time() - c0, time.perf_counter() - w0, out


def measure(repeats: int) -> dict:
    """Run every measurement `repeats` times; medians of CPU and wall times."""
    drag_cpu, drag_wall, rest_cpu, rest_wall, snap_ms, seq_cpu, seq_wall = ([] for _ in range(7))
    knots = 0
    drag = _drag_trajectory()
    n_rest = 480
    with RopeWorld() as world:
        for _ in range(repeats):
            world.reset(_straight(world))
            cpu, wall, res = _timed(lambda: world.execute(drag, settle_time=0.0))
            drag_cpu.append(res.sim_steps / cpu)
            drag_wall.append(res.sim_steps / wall)
            world.reset(_straight(world))
            cpu, wall, _ = _timed(lambda: world.settle(n_rest * world.params.timestep))
            rest_cpu.append(n_rest / cpu)
            rest_wall.append(n_rest / wall)

            # Snapshot + restore, then the first step that has to rebuild the world from it.
            def snap_cycle() -> None:
                world.restore(world.snapshot())
                world.settle(world.params.timestep)

            _, wall, _ = _timed(snap_cycle)
            snap_ms.append(1e3 * wall)

            def sequence() -> bool:
                world.reset(_straight(world))
                for traj in overhand_sequence():
                    world.execute(traj)
                return is_overhand_knot(world.rope_nodes())

            cpu, wall, knotted = _timed(sequence)
            seq_cpu.append(cpu)
            seq_wall.append(wall)
            knots += int(knotted)
    med = statistics.median
    return {
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "pybullet": metadata.version("pybullet"),
        "numpy": np.__version__,
        "repeats": repeats,
        "dragged_steps_per_s_cpu": round(med(drag_cpu)),
        "dragged_steps_per_s_wall": round(med(drag_wall)),
        "rest_steps_per_s_cpu": round(med(rest_cpu)),
        "rest_steps_per_s_wall": round(med(rest_wall)),
        "snapshot_restore_ms_wall": round(med(snap_ms), 2),
        "knot_sequence_s_cpu": round(med(seq_cpu), 3),
        "knot_sequence_s_wall": round(med(seq_wall), 3),
        "knot_sequence_knotted": f"{knots}/{repeats}",
    }


def _straight(world: RopeWorld) -> np.ndarray:
    return straight_rope(world.params.n_links + 1, world.params.length, world.params.radius)


def main(argv: list[str] | None = None) -> int:
    """Print the speed table (and the JSON line with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    res = measure(args.repeats)
    print(
        f"machine: {res['cpu_model']}, {res['cpu_count']} cores; python {res['python']}, "
        f"pybullet {res['pybullet']}, numpy {res['numpy']}; medians of {res['repeats']} repeats"
    )
    rows = [
        (
            "steps/s, rope dragged (target >= 2000)",
            res["dragged_steps_per_s_cpu"],
            res["dragged_steps_per_s_wall"],
        ),
        ("steps/s, rope at rest", res["rest_steps_per_s_cpu"], res["rest_steps_per_s_wall"]),
        ("snapshot + restore + first step (ms)", "-", res["snapshot_restore_ms_wall"]),
        (
            "3-step knot sequence (s, target <= 2)",
            res["knot_sequence_s_cpu"],
            res["knot_sequence_s_wall"],
        ),
        ("3-step knot sequence knotted", "-", res["knot_sequence_knotted"]),
    ]
    print(f"{'measure':<42}{'CPU time':>12}{'wall time':>12}")
    for name, cpu, wall in rows:
        print(f"{name:<42}{cpu!s:>12}{wall!s:>12}")
    if args.json:
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
