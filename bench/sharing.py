"""How much of a Table I's time would sharing simulations across policies save? (measured)

Table I runs every policy on the same tasks from the same start, and a demo transferred and
executed from the same simulator state, observed as the same cloud, has exactly the same
outcome whichever policy asked for it (restore-then-execute is bit-identical; the transfer is a
pure function of cloud and demo). A task-major run with one outcome memo for all policies of a
task would therefore give the same Table I with fewer simulations. This script measures how
many: it runs the policies one after another on the same starts in one process (as
`bench/search_speed.py` does), keys every `apply_demo` call (transfer + execution) by (task,
state digest, cloud digest, demo) and books its seconds as

  first     the first time this task needed it (a shared memo still simulates it);
  own       the same policy needed it earlier in this task (its own memo missed: la2x5's
            64-entry memo, or an episode re-executing what its decision simulated);
  shared    another policy needed it earlier in this task: the saving a shared memo gives.

Only the booking is added; the policies run the shipped code (their fingerprints are printed
and match `bench/search_speed.py`'s). Training starts only: a speed bench, never a result.

Usage: .venv/bin/python bench/sharing.py [--policies nn,greedy,la2x5,la1x10,oracle]
       [--starts 8] [--level main] [--json]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import functools  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from search_speed import training_episode  # noqa: E402  (bench/, this script's folder)
from tqdm import tqdm  # noqa: E402

from knotlab.app import defaults  # noqa: E402
from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import TaskSet  # noqa: E402
from knotlab.core.execution import apply as apply_mod  # noqa: E402
from knotlab.core.execution import expansion as expansion_mod  # noqa: E402
from knotlab.core.execution import memo as memo_mod  # noqa: E402
from knotlab.core.experiments.bench import BenchWorker, WorkerSpec  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("first", "own", "shared")


class SharingLedger:
    """Books each apply_demo call's seconds as first / own / shared (see the module doc)."""

    def __init__(self) -> None:
        self.task = ""
        self.policy = ""
        self._seen: dict[tuple, str] = {}  # key -> the policy that first needed it
        self.seconds: dict[str, dict[str, float]] = defaultdict(lambda: dict.fromkeys(KINDS, 0.0))
        self.calls: dict[str, dict[str, int]] = defaultdict(lambda: dict.fromkeys(KINDS, 0))
        self.key_seconds = 0.0

    def start(self, task: str, policy: str) -> None:
        """The episode about to run; a new task forgets the previous task's keys."""
        if task != self.task:
            self._seen.clear()
        self.task, self.policy = task, policy

    def wrap(self, original):
        """apply_demo with its seconds booked; the key is taken before the call, untimed."""

        @functools.wraps(original)
        def booked(world, transferer, cloud_n3, action, *args, **kwargs):
            t_key = time.perf_counter()
            state = memo_mod.snapshot_digest(world.snapshot())
            cloud = hashlib.sha1(np.ascontiguousarray(cloud_n3, dtype=np.float64)).hexdigest()
            key = (self.task, state, cloud, int(action))
            t0 = time.perf_counter()
            self.key_seconds += t0 - t_key  # the bench's own cost, taken off the episode time
            out = original(world, transferer, cloud_n3, action, *args, **kwargs)
            seconds = time.perf_counter() - t0
            first = self._seen.setdefault(key, self.policy) if key not in self._seen else None
            if first is not None:
                kind = "first"
            else:
                kind = "own" if self._seen[key] == self.policy else "shared"
            self.seconds[self.policy][kind] += seconds
            self.calls[self.policy][kind] += 1
            return out

        return booked


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--policies", default="nn,greedy,la2x5,la1x10,oracle")
    parser.add_argument("--starts", type=int, default=8, help="first N training starts")
    parser.add_argument("--level", choices=defaults.LEVELS, default="main")
    parser.add_argument("--model", default=str(ROOT / "results" / "model_main.npz"))
    parser.add_argument("--library", default=str(defaults.LIBRARY_PATH))
    parser.add_argument("--json", action="store_true", help="also print one JSON object last")
    args = parser.parse_args()
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    if args.starts < 1:
        raise SystemExit("--starts must be >= 1")
    names = args.policies.split(",")
    library = DemoLibrary.load(args.library)
    tasks = list(TaskSet.load(defaults.task_set_path(args.level, "train")))[: args.starts]
    worker = BenchWorker(WorkerSpec(library, QModel.load(args.model)))
    ledger = SharingLedger()
    booked = ledger.wrap(apply_mod.apply_demo)
    for module in (expansion_mod, memo_mod):  # every caller of apply_demo looks it up there
        module.apply_demo = booked  # type: ignore[attr-defined]

    wall: dict[str, float] = defaultdict(float)
    trace: dict[str, list] = defaultdict(list)
    # Task-major, as a shared-memo Table I would run: every policy on task 1, then task 2 ...
    for task in tqdm(tasks, desc="tasks", unit="task"):
        for name in names:
            ledger.start(task.task_id, name)
            t0, key_s = time.perf_counter(), ledger.key_seconds
            record = training_episode(worker, name, task)
            wall[name] += time.perf_counter() - t0 - (ledger.key_seconds - key_s)
            trace[name].append(
                [[s.chosen_key for s in record.steps], [s.stage for s in record.steps]]
            )

    rows = []
    for name in names:
        sec, calls = ledger.seconds[name], ledger.calls[name]
        rows.append(
            {
                "policy": name,
                "episode_s": wall[name],
                "apply_demo_s": dict(sec),
                "apply_demo_calls": dict(calls),
                "fingerprint": hashlib.sha1(json.dumps(trace[name]).encode()).hexdigest()[:12],
            }
        )
    total_wall = sum(wall.values())
    total = {k: sum(r["apply_demo_s"][k] for r in rows) for k in KINDS}
    info = machine_info()
    print(
        f"\nmachine: {info['cpu_model']} x {info['usable_cores']} cores; {args.starts} "
        f"{args.level} training starts, policies run task by task in one process\n"
    )
    print("| policy | episode s | transfer+execute s | first | own repeat | shared | fingerprint |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        s, c = r["apply_demo_s"], r["apply_demo_calls"]
        print(
            f"| {r['policy']} | {r['episode_s']:.1f} | {sum(s.values()):.1f} | "
            + " | ".join(f"{s[k]:.1f} s ({c[k]})" for k in KINDS)
            + f" | `{r['fingerprint']}` |"
        )
    saving = total["shared"] + total["own"]
    print(
        f"\nAll policies: {total_wall:.1f} s of episodes; transfer+execute "
        f"{sum(total.values()):.1f} s, "
        f"of which repeats another policy had simulated {total['shared']:.1f} s "
        f"({total['shared'] / total_wall:.1%} of the episode time) and repeats of a policy's own "
        f"{total['own']:.1f} s ({total['own'] / total_wall:.1%}).\nOne memo per task for every "
        f"policy would save {saving / total_wall:.1%} of the episode time (an upper bound: "
        "memo lookups and snapshot restores are not free)."
    )
    if args.json:
        print(json.dumps({"machine": info, "rows": rows, "total_episode_s": total_wall}))


if __name__ == "__main__":
    main()
