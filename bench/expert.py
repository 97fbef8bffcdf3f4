"""Success table of a task's scripted expert over seeded start ropes (3 / 6 cm bends, both hands).

Each start rope is drawn by `expert_moves.sample_start_rope` (sine bends, any orientation,
anywhere within +-0.15 m), the task's expert (`--task`, default overhand) runs with its nominal
style (chirality alternating by start), up to 3 tries of each later step from the same state and
up to 8 loops (restarts). Prints, per bend
amplitude and chirality: knots, the step at which failed demos gave up, rejected tries per step,
restarts and the median wall time per demo; `--json` prints one JSON object as the last line.

    .venv/bin/python bench/expert.py                 # 200 starts per amplitude
    .venv/bin/python bench/expert.py --starts 20 --workers 2 --json
    .venv/bin/python bench/expert.py --task figure8 --amplitudes 0.03 --workers 1
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import dataclass

import numpy as np

from knotlab.core.machine import machine_line
from knotlab.core.parallel import default_workers, imap_processes
from knotlab.core.tasks import DEFAULT_TASK, get_task, task_names
from knotlab.core.tasks.expert_moves import sample_start_rope

_WORLD: dict[str, object] = {}


@dataclass(frozen=True)
class _Job:
    task: str
    amplitude: float
    index: int
    seed: int
    chirality: int
    max_attempts: int
    max_restarts: int


def _run(job: _Job) -> dict:
    from knotlab.core.world.sim import RopeWorld

    if "w" not in _WORLD:
        _WORLD["w"] = RopeWorld()
    rng = np.random.default_rng(np.random.SeedSequence([job.seed, int(job.amplitude * 1000)]))
    start = sample_start_rope(rng, bend_amplitude=job.amplitude)
    run = get_task(job.task).run_expert(
        _WORLD["w"],
        start,
        mirrored=job.chirality == -1,
        seed=job.seed,
        max_attempts=job.max_attempts,
        max_restarts=job.max_restarts,
    )
    return {
        "amplitude": job.amplitude,
        "index": job.index,
        "chirality": job.chirality,
        "knotted": run.knotted,
        "failed_step": run.failed_step,
        "attempts": [s.attempts for s in run.steps],
        "rejected": list(run.failures_by_step),
        "restarts": run.restarts,
        "wall_s": run.wall_time,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default=DEFAULT_TASK, choices=task_names(), help="whose expert")
    ap.add_argument("--starts", type=int, default=200, help="start ropes per bend amplitude")
    ap.add_argument("--amplitudes", type=float, nargs="+", default=[0.03, 0.06])
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--max-attempts", type=int, default=3, help="tries of each later step")
    ap.add_argument("--max-restarts", type=int, default=8, help="loops laid per demo at most")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    jobs = [
        _Job(
            args.task,
            amp,
            i,
            args.seed + i,
            1 if i % 2 == 0 else -1,
            args.max_attempts,
            args.max_restarts,
        )
        for amp in args.amplitudes
        for i in range(args.starts)
    ]
    workers = args.workers or default_workers()
    wall0 = time.perf_counter()
    n_steps = get_task(args.task).expert_steps
    results = [r for _, r in imap_processes(_run, jobs, workers=workers, desc="expert demos")]
    wall = time.perf_counter() - wall0
    rows = []
    for amp in args.amplitudes:
        for chir in (1, -1, 0):
            sel = [
                r
                for r in results
                if r["amplitude"] == amp and (chir == 0 or r["chirality"] == chir)
            ]
            if not sel:
                continue
            fails = [sum(1 for r in sel if r["failed_step"] == k) for k in range(n_steps)]
            rejected = [sum(r["rejected"][k] for r in sel) for k in range(n_steps)]
            rows.append(
                {
                    "bend_m": amp,
                    "chirality": {1: "+1", -1: "-1", 0: "both"}[chir],
                    "starts": len(sel),
                    "knots": sum(r["knotted"] for r in sel),
                    "success": sum(r["knotted"] for r in sel) / len(sel),
                    "failed_at_step": fails,
                    "rejected_tries": rejected,
                    "restarts": sum(r["restarts"] for r in sel),
                    "median_demo_wall_s": float(np.median([r["wall_s"] for r in sel])),
                }
            )
    print(
        f"machine: {platform.node()} {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cpus, {workers} workers; seed {args.seed}; "
        f"task {args.task}; {args.max_attempts} tries of a step, "
        f"{args.max_restarts} loops at most; "
        f"wall {wall:.1f} s"
    )
    print(
        f"{'bend':>5} {'chir':>5} {'starts':>6} {'knots':>6} {'success':>8} "
        f"{'failed at step 1/2/..':>21} {'rejected tries 1/2/..':>21} {'restarts':>8} "
        f"{'s/demo':>7}"
    )
    for r in rows:
        print(
            f"{r['bend_m']:>5.2f} {r['chirality']:>5} {r['starts']:>6} {r['knots']:>6} "
            f"{r['success']:>8.1%} {'/'.join(map(str, r['failed_at_step'])):>21} "
            f"{'/'.join(map(str, r['rejected_tries'])):>21} "
            f"{r['restarts']:>8} {r['median_demo_wall_s']:>7.2f}"
        )
    if args.json:
        print(
            json.dumps(
                {
                    "task": args.task,
                    "rows": rows,
                    "wall_s": wall,
                    "workers": workers,
                    "seed": args.seed,
                }
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
