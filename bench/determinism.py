"""Fingerprints of one fixed scan and one fixed episode, to compare two machines bit for bit.

Prints the CPU, the BLAS libraries and their kernels, a hash of the registration costs of the
shipped library against the start of a shipped test task, the gap between the two best demos
(how near a tie the nearest-neighbour choice is), and the demos a nearest-neighbour episode on
that task chooses with a hash of them. Equal hashes on two machines: same numbers. Different
scan hashes: the costs differ in late bits (see docs/determinism.md); ``--save`` the costs on one
machine and ``--compare`` them on the other to see by how much.

Usage: .venv/bin/python bench/determinism.py [--task 0] [--level main] [--steps 5]
       [--save costs.npz] [--compare costs.npz] [--json]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # one thread, as the bench's workers run: sums in one order

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.app import defaults  # noqa: E402
from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import TaskSet  # noqa: E402
from knotlab.core.experiments.bench import episode_seed, package_versions  # noqa: E402
from knotlab.core.machine import blas_kernels, cpu_model  # noqa: E402


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def fingerprint(task_index: int, level: str, steps: int) -> tuple[dict, np.ndarray]:
    """The fingerprint as a JSON-able dict, and the scan's cost array (demos x cost terms)."""
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    library = DemoLibrary.load(defaults.LIBRARY_PATH)
    task = list(TaskSet.load(defaults.task_set_path(level, "test")))[task_index]
    agent = Agent(library)  # nearest neighbour
    with RopeWorld() as world:
        world.reset(task.start_nodes_k3)
        cloud_n3 = agent.observe(world)
        scan = agent.scan(cloud_n3)
        nn_a = np.where(scan.ok_a, scan.nn_cost_a, np.inf)
        best, second = np.sort(nn_a)[:2]
        record = agent.run_episode(world, task, seed=episode_seed(0, task.seed), max_steps=steps)
    chosen = list(record.summary()["chosen"])
    out = {
        "cpu": cpu_model(),
        "blas": blas_kernels(),  # after the scan: numba has loaded scipy's LAPACK
        "packages": package_versions(),
        "library_hash": library.content_hash(),
        "task": task.task_id,
        "cloud_hash": _digest(np.ascontiguousarray(cloud_n3, dtype="<f8").tobytes()),
        "scan_cost_hash": _digest(np.ascontiguousarray(scan.costs_ac, dtype="<f8").tobytes()),
        "nn_best": library.keys[int(np.argmin(nn_a))],
        "nn_gap_to_second": float(second - best),
        "episode_chosen": chosen,
        "episode_hash": _digest(json.dumps(chosen).encode()),
    }
    return out, np.asarray(scan.costs_ac, dtype=np.float64)


def main() -> None:
    """Print the fingerprint (a table, or one JSON line with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", type=int, default=0, help="index in the test set (default 0)")
    parser.add_argument("--level", default="main", choices=defaults.LEVELS)
    parser.add_argument("--steps", type=int, default=5, help="episode steps (default 5)")
    parser.add_argument("--save", default=None, help="write the scan costs to this .npz")
    parser.add_argument("--compare", default=None, help="a --save file from another machine")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    out, costs_ac = fingerprint(args.task, args.level, args.steps)
    if args.save:
        np.savez(args.save, costs_ac=costs_ac)
    if args.compare:
        with np.load(args.compare) as data:
            theirs = data["costs_ac"]
        finite = np.isfinite(costs_ac) & np.isfinite(theirs)
        out["compare_max_abs_diff"] = float(np.max(np.abs(costs_ac - theirs)[finite], initial=0))
        out["compare_same_inf"] = bool(np.array_equal(np.isinf(costs_ac), np.isinf(theirs)))
        out["compare_same_nn_order"] = bool(
            np.array_equal(np.argsort(costs_ac[:, :4].sum(1)), np.argsort(theirs[:, :4].sum(1)))
        )
    if args.json:
        print(json.dumps(out))
        return
    for key, value in out.items():
        if isinstance(value, list) and key == "blas":
            print(
                f"{key:<22} " + "\n".join(f"{'':<22} {v}" if i else v for i, v in enumerate(value))
            )
        else:
            print(f"{key:<22} {value}")


if __name__ == "__main__":
    main()
