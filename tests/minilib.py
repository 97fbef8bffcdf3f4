"""A tiny but real demo library and task sets, built in the simulator once per test session.

The library holds rigid copies of the fixed overhand sequence (`knot_sequence`): the straight
rope, a copy shifted 5 cm in y and (with ``n_demos=3``) a copy turned 10 degrees about z. Each
segment is executed in a `RopeWorld` to record its pre/post rope and observed cloud, so every demo
is a real, knot-tying demonstration. Tasks are small seeded perturbations of the demo starts,
settled. Everything is cached (``lru_cache``) so test files share one build per process.

Use::

    from tests.minilib import mini_library, mini_tasks, mini_executions
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from knotlab.core.demos.library import DemoLibrary, DemoSegment, segment_key
from knotlab.core.demos.tasks import RopeTask, TaskSet, task_seed
from knotlab.core.selection.labels import DeadEndState, LabelledExecution, LabelledStep
from knotlab.core.tasks.overhand.knot_sequence import overhand_sequence
from knotlab.core.world.rope import straight_rope

# (shift in metres, turn about z in degrees) of each demonstration, in start-index order.
_POSES: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.0, 0.0, 0.0), 0.0),
    ((0.0, 0.05, 0.0), 0.0),
    ((0.02, -0.03, 0.0), 10.0),
)


def _rot_z(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@lru_cache(maxsize=4)
def mini_library(n_demos: int = 2) -> DemoLibrary:
    """``n_demos`` (1-3) rigid copies of the 3-step overhand demo, executed in simulation."""
    from knotlab.core.world.sim import RopeWorld

    if not 1 <= n_demos <= len(_POSES):
        raise ValueError(f"n_demos must be 1..{len(_POSES)}, got {n_demos}")
    segments = []
    with RopeWorld() as world:
        for start in range(n_demos):
            shift, turn = _POSES[start]
            rot = _rot_z(turn)
            nodes = straight_rope() @ rot.T + np.asarray(shift)
            world.reset(nodes)
            for step, traj in enumerate(overhand_sequence()):
                moved = traj.with_positions(
                    traj.positions_gt3 @ rot.T + np.asarray(shift),
                    np.einsum("ij,gtjk->gtik", rot, traj.rotations_gt33),
                )
                pre = world.rope_nodes()
                cloud = world.observe()
                world.reset(pre)  # what the library records is what a replay starts from
                world.execute(moved)
                segments.append(
                    DemoSegment(
                        segment_key(start, step),
                        start,
                        step,
                        pre,
                        cloud,
                        moved,
                        world.rope_nodes(),
                        {"shift": list(shift), "turn_deg": turn},
                    )
                )
    return DemoLibrary(segments, {"source": "tests.minilib", "n_demos": n_demos})


@lru_cache(maxsize=8)
def mini_tasks(
    n_tasks: int = 3, split: str = "test", rho: float = 0.02, n_demos: int = 2
) -> TaskSet:
    """``n_tasks`` settled starts perturbing the mini library's demo starts (seeded, small rho)."""
    from knotlab.core.world.rope import perturb_rope
    from knotlab.core.world.sim import RopeWorld

    starts = mini_library(n_demos).start_states()
    keys = sorted(starts)
    tasks = []
    with RopeWorld() as world:
        for i in range(n_tasks):
            seed = task_seed(7, split, i)
            source = keys[i % len(keys)]
            world.reset(perturb_rope(starts[source], rho, n_centres=3, seed=seed))
            world.settle(0.5)
            tasks.append(RopeTask(f"mini-{split}-{i:04d}", world.rope_nodes(), source, seed))
    meta = {"split": split, "level": "mini", "rho": rho, "seed": 7, "n_demos": n_demos}
    return TaskSet(tasks, meta)


def mini_executions(n_demos: int = 2, *, dead_ends: bool = False) -> list[LabelledExecution]:
    """Expert executions replaying each demo on its own start: t0, t1 progress, t2 ties the knot.

    With ``dead_ends`` each execution also records, as dead ends, copies of its three states
    shifted 1-3 cm in y: hard to tell from the expert states, so how well values separate them
    (the validation value AUC) depends on the regularisation (C, D).
    """
    lib = mini_library(n_demos)
    out = []
    for start in sorted(lib.start_states()):
        segs = sorted((s for s in lib if s.start_index == start), key=lambda s: s.step_index)
        steps = tuple(
            LabelledStep(
                step_index=i,
                cloud_n3=seg.pre_cloud_n3,
                chosen_demo=seg.key,
                outcome="knot" if i == len(segs) - 1 else "progressed",
                rope_nodes_k3=seg.pre_nodes_k3,
            )
            for i, seg in enumerate(segs)
        )
        shifts = [np.array([0.0, 0.01 * k, 0.0]) for k in range(1, len(steps) + 1)]
        dead = tuple(
            DeadEndState(step.cloud_n3 + d, step.rope_nodes_k3 + d)
            for step, d in zip(steps, shifts, strict=True)
            if dead_ends
        )
        out.append(
            LabelledExecution(
                f"mini-exec-{start}",
                "oracle",
                "minilib",
                steps,
                ended_in_knot=True,
                dead_ends=dead,
                task_id=f"mini-demo-{start}",
                library_hash=lib.content_hash(),
            )
        )
    return out


def write_mini_files(
    directory: Path, n_tasks: int = 3, n_demos: int = 2, split: str = "test"
) -> tuple[Path, Path]:
    """Save the mini library and a task set of ``split`` under ``directory``; their paths."""
    directory = Path(directory)
    lib_path = mini_library(n_demos).save(directory / "mini_demos.npz")
    tasks = mini_tasks(n_tasks, split, n_demos=n_demos)
    tasks_path = tasks.save(directory / f"mini_tasks_{split}.npz")
    return lib_path, tasks_path


def write_mini_labels(path: Path, n_demos: int = 2, *, dead_ends: bool = False) -> Path:
    """The mini executions as a `knotlab labels export` JSONL file (what `knotlab train` reads)."""
    from datetime import UTC, datetime

    from knotlab.labeling_db.interchange import write_labels
    from knotlab.labeling_db.store import StoredExecution

    when = datetime(2024, 1, 1, tzinfo=UTC)
    items = [
        StoredExecution(e, started_at=when, finished_at=when)
        for e in mini_executions(n_demos, dead_ends=dead_ends)
    ]
    path = Path(path)
    with open(path, "w", encoding="utf-8") as fh:
        write_labels(items, fh, "jsonl")
    return path


def mini_train_args(directory: Path, *, dead_ends: bool = False) -> tuple[list[str], Path]:
    """`knotlab train` arguments on the mini library and labels (half held out); model path."""
    directory = Path(directory)
    lib = mini_library(2).save(directory / "lib.npz")
    labels = write_mini_labels(directory / "labels.jsonl", dead_ends=dead_ends)
    out = directory / "model.npz"
    args = ["train", "--labels", str(labels), "--library", str(lib), "--out", str(out)]
    args += ["--validation-fraction", "0.5", "--workers", "1", "--no-progress", "--json"]
    return args, out
