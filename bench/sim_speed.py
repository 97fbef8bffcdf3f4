"""Rope simulation speed: steps/s dragged and at rest, snapshot+restore, the 3-step knot sequence.

Usage: python bench/sim_speed.py [--repeats 5] [--json]
Prints a table of medians over repeats (CPU time of this process, and wall time) with the
machine's details; with --json also the same figures as one JSON object on the last line.
Targets: >= 2,000 steps/s with the rope dragged, <= 2 s per 3-step sequence, and the rope world
at >= 0.9x the steps/s of a bare PyBullet chain of the same settings doing the same drag
(`bare_chain_drag`, measured interleaved with the world in CPU time).
"""

from __future__ import annotations

import os

# One BLAS thread: the benchmark measures the simulator, not BLAS contention on shared cores.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import itertools  # noqa: E402
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


def bare_chain_drag(world: RopeWorld, traj: GripperTrajectory, n_steps: int) -> int:
    """The same drag in a bare PyBullet chain of the rope world's settings; steps taken.

    40 capsules joined end to end by point-to-point constraints (neighbours not colliding), on
    a plane, 20 solver iterations at 1/240 s; the dragged end held by one point-to-point
    constraint whose pivot moves along the trajectory's right gripper path each step. No health
    checks, no state capture, no rebuild: the engine alone, to measure the world's overhead.
    """
    from knotlab.core.world.sim import p

    prm = world.params
    cid = p.connect(p.DIRECT)
    try:
        p.setPhysicsEngineParameter(
            fixedTimeStep=prm.timestep,
            numSubSteps=0,
            numSolverIterations=prm.solver_iterations,
            deterministicOverlappingPairs=1,
            physicsClientId=cid,
        )
        p.setGravity(0, 0, -prm.gravity, physicsClientId=cid)
        plane = p.createMultiBody(
            0, p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid), physicsClientId=cid
        )
        p.changeDynamics(plane, -1, lateralFriction=prm.friction, physicsClientId=cid)
        half = 0.5 * prm.link_length
        shape = p.createCollisionShape(
            p.GEOM_CAPSULE,
            radius=prm.radius,
            height=prm.link_length - 2 * prm.radius,
            physicsClientId=cid,
        )
        links = []
        for i in range(prm.n_links):
            x = -prm.length / 2 + (i + 0.5) * prm.link_length
            body = p.createMultiBody(
                prm.mass / prm.n_links,
                shape,
                basePosition=[x, 0.0, prm.radius],
                baseOrientation=p.getQuaternionFromEuler([0, np.pi / 2, 0]),
                physicsClientId=cid,
            )
            p.changeDynamics(
                body,
                -1,
                lateralFriction=prm.friction,
                linearDamping=prm.linear_damping,
                angularDamping=prm.angular_damping,
                activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING,
                physicsClientId=cid,
            )
            links.append(body)
        for a, b in itertools.pairwise(links):
            c = p.createConstraint(
                a, -1, b, -1, p.JOINT_POINT2POINT, [0, 0, 0], [0, 0, half], [0, 0, -half],
                physicsClientId=cid,
            )  # fmt: skip
            p.changeConstraint(
                c, maxForce=prm.joint_max_force, erp=prm.joint_erp, physicsClientId=cid
            )
            p.setCollisionFilterPair(a, b, -1, -1, 0, physicsClientId=cid)
        path = traj.positions_gt3[1]
        times = np.linspace(traj.times_t[0], traj.times_t[-1], n_steps)
        xyz = np.stack([np.interp(times, traj.times_t, path[:, d]) for d in range(3)], axis=1)
        grip = p.createConstraint(
            links[-1], -1, -1, -1, p.JOINT_POINT2POINT, [0, 0, 0], [0, 0, 0], xyz[0].tolist(),
            physicsClientId=cid,
        )  # fmt: skip
        for target in xyz:
            p.changeConstraint(grip, target.tolist(), maxForce=30.0, physicsClientId=cid)
            p.stepSimulation(physicsClientId=cid)
    finally:
        p.disconnect(cid)
    return n_steps


def measure(repeats: int) -> dict:
    """Run every measurement `repeats` times; medians of CPU and wall times."""
    drag_cpu, drag_wall, rest_cpu, rest_wall, snap_ms, seq_cpu, seq_wall = ([] for _ in range(7))
    bare_cpu: list[float] = []
    knots = 0
    drag = _drag_trajectory()
    n_rest = 480
    with RopeWorld() as world:
        for _ in range(repeats):
            world.reset(_straight(world))
            cpu, wall, res = _timed(lambda: world.execute(drag, settle_time=0.0))
            drag_cpu.append(res.sim_steps / cpu)
            drag_wall.append(res.sim_steps / wall)
            # The engine alone, interleaved with the world so both meet the same machine load.
            n_drag = res.sim_steps
            cpu, _, steps = _timed(lambda: bare_chain_drag(world, drag, n_drag))  # noqa: B023
            bare_cpu.append(steps / cpu)
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
        "bare_chain_steps_per_s_cpu": round(med(bare_cpu)),
        "world_over_bare_chain": round(med(drag_cpu) / med(bare_cpu), 3),
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
        ("steps/s, bare PyBullet chain, same drag", res["bare_chain_steps_per_s_cpu"], "-"),
        ("rope world / bare chain (target >= 0.9)", res["world_over_bare_chain"], "-"),
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
