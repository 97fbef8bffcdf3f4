"""One-step outcomes of the cheapest candidates in every labelled state (richer labels, issue 12).

The oracle's label says "the first demo in registration-cost order that still leads to a knot":
the candidates before it failed, the ones after it were never tried. This script tries the
``--top`` cheapest candidates of every labelled state once in simulation (from the rope the
label stored, at rest) and records, per candidate, the stage reached, a knot, or the failure.
`bench/greedy_lever.py --variants ...,outcomes` then trains with them: no margin row against an
alternative that advances as well as the label's demo, and at least one value unit of margin
against one that does not. Training starts only (the labels file); resumable (states already in
OUT are skipped).

Usage: .venv/bin/python bench/candidate_outcomes.py [--labels results/labels_oracle_main.jsonl]
       [--top 5] [--out runs/candidate_outcomes.jsonl] [--workers 2]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.parallel import PerProcess, imap_processes  # noqa: E402
from knotlab.labeling_db.interchange import read_labels  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True, eq=False)
class StateJob:
    """One labelled state and the demos to try from it."""

    execution_id: str
    step_index: int
    nodes_k3: np.ndarray
    cloud_n3: np.ndarray
    candidates: tuple[str, ...]


class _Worker:
    def __init__(self, library: DemoLibrary) -> None:
        from knotlab.core.parallel import single_thread_blas
        from knotlab.core.registration.planner import DemoTransferer
        from knotlab.core.world.sim import RopeWorld

        single_thread_blas()
        self.library = library
        self.world = RopeWorld()
        self.transferer = DemoTransferer(library)

    def run(self, job: StateJob) -> dict:
        from knotlab.core.registration.planner import apply_demo
        from knotlab.core.world.stages import rope_stage

        self.world.reset(job.nodes_k3)
        start = self.world.snapshot()
        before = int(rope_stage(self.world.rope_nodes())[0])
        tried = []
        for key in job.candidates:
            self.world.restore(start)
            out = apply_demo(self.world, self.transferer, job.cloud_n3, self.library.index_of(key))
            tried.append(
                {"demo": key, "stage": int(out.stage), "knot": bool(out.knot),
                 "failure": out.failure}
            )  # fmt: skip
        return {
            "execution_id": job.execution_id,
            "step_index": job.step_index,
            "stage_before": before,
            "tried": tried,
        }


_WORKER: PerProcess[_Worker] = PerProcess(_Worker)


def _init(library: DemoLibrary) -> None:
    _WORKER.reset()
    _WORKER.get(library)


def _run(job: StateJob) -> dict:
    return _WORKER.current().run(job)


def advanced(record: dict, tried: dict) -> bool:
    """Did this try make progress from the state: a knot, or a higher stage without failure?"""
    if tried["knot"]:
        return True
    return tried["failure"] is None and tried["stage"] > record["stage_before"]


def main() -> int:
    """Try the candidates of every labelled state; append one JSON line per state."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--labels", default=str(ROOT / "results/labels_oracle_main.jsonl"))
    ap.add_argument("--library", default=str(ROOT / "static/demos_default.npz"))
    ap.add_argument("--top", type=int, default=5)
    ap.add_argument("--out", default="runs/candidate_outcomes.jsonl")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    library = DemoLibrary.load(args.library)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = set()
    if out.exists():
        for line in out.read_text().splitlines():
            r = json.loads(line)
            done.add((r["execution_id"], r["step_index"]))
    jobs = []
    for item in read_labels(args.labels):
        ex = item.execution
        for step in ex.steps:
            if (ex.execution_id, step.step_index) in done or step.rope_nodes_k3 is None:
                continue
            shown = tuple(step.candidates[: args.top]) if step.candidates else ()
            if not shown:
                continue
            jobs.append(
                StateJob(ex.execution_id, step.step_index, step.rope_nodes_k3, step.cloud_n3, shown)
            )
    with out.open("a") as fh:
        for _, rec in imap_processes(
            _run, jobs, workers=args.workers, initializer=partial(_init, library),
            desc="candidate outcomes",
        ):  # fmt: skip
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
