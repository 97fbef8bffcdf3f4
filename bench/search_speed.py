"""Search speed: decision time per step of the search policies, and where it goes.

Runs la1x10, la2x5 and the simulation oracle (and any other policy named) on fixed training
starts of one level, in this one process (a bench worker as `knotlab bench` builds it, warm),
and splits each policy's decision time into
  simulation   `RopeWorld.execute` (rebuild, approach, drag, settle; steps/s of each),
  transfer     the exact registration of a chosen demo and the warp of its trajectory,
  scan         library scans (the step's own scan and every child's),
  features     Q features from a scan, and observing a cloud,
  knot test    the topological stage of the rope after an action,
  overhead     the rest (snapshots, restores, bookkeeping).
The components are timed by wrapping those functions in this process only (the code measured
is the shipped code). Training starts only: this is a speed bench, never a result.

Usage: .venv/bin/python bench/search_speed.py [--policies la1x10,la2x5,oracle] [--starts 4]
       [--level main] [--model results/model_main.npz] [--interactive la2x5]
       [--prefetch on|off|both] [--memo episode|cold|both] [--json]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import functools  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

from knotlab.app import defaults  # noqa: E402
from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import TaskSet  # noqa: E402
from knotlab.core.experiments.bench import BenchWorker, WorkerSpec, episode_seed  # noqa: E402
from knotlab.core.experiments.episode import run_episode  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.registration import library_scan, planner  # noqa: E402
from knotlab.core.selection import features as features_mod  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.tasks.overhand import stages  # noqa: E402
from knotlab.core.world import sim  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
COMPONENTS = ("simulation", "transfer", "scan", "features", "knot test")


class ComponentClock:
    """Exclusive wall seconds per component: time inside a nested timed call (the landmark scan
    inside features, say) is booked to the inner component only, so components sum to the
    wall time."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.phase_s: dict[str, float] = defaultdict(float)
        self.phase_steps: dict[str, int] = defaultdict(int)
        self._inner: list[float] = []  # per open timed call: seconds of timed calls inside it

    def timed(self, component: str, fn, *args, **kwargs):
        """Call fn, booking its exclusive time to component."""
        self._inner.append(0.0)
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            elapsed = time.perf_counter() - t0
            inner = self._inner.pop()
            self.seconds[component] += elapsed - inner
            self.calls[component] += 1
            if self._inner:
                self._inner[-1] += elapsed

    def wrap(self, owner: object, name: str, component: str) -> None:
        """Replace owner.name by a timed version that books its wall time under component."""
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            return self.timed(component, original, *args, **kwargs)

        setattr(owner, name, timed)

    def wrap_execute(self) -> None:
        """Time RopeWorld.execute and collect its per-phase seconds and steps."""
        original = sim.RopeWorld.execute

        @functools.wraps(original)
        def timed(world, *args, **kwargs):
            result = self.timed("simulation", original, world, *args, **kwargs)
            for phase, sec in result.phase_s.items():
                self.phase_s[phase] += sec
                self.phase_steps[phase] += result.phase_steps.get(phase, 0)
            return result

        sim.RopeWorld.execute = timed  # type: ignore[method-assign]

    def reset(self) -> None:
        """Zero every counter (between policies)."""
        self.__init__()  # type: ignore[misc]


def install(clock: ComponentClock) -> None:
    """Wrap the functions whose time the table splits out."""
    clock.wrap_execute()
    clock.wrap(planner.DemoTransferer, "plan", "transfer")
    clock.wrap(library_scan.LibraryRegistrar, "scan", "scan")
    clock.wrap(features_mod.LibraryFeaturizer, "features_from_scan", "features")
    clock.wrap(features_mod.LibraryFeaturizer, "observe", "features")
    clock.wrap(stages, "rope_stage", "knot test")


def training_episode(worker: BenchWorker, name: str, task):
    """One episode of policy ``name`` from a training start, as the bench seeds it; an
    episode that errored ends the benchmark (its times would not be a result)."""
    record = run_episode(
        worker.agent_for(name),
        worker.world,
        task.start_nodes_k3,
        task_id=task.task_id,
        seed=episode_seed(0, task.seed),
    )
    if record.error:
        raise SystemExit(f"{name} on {task.task_id} errored: {record.error}")
    return record


def run_policy(worker: BenchWorker, name: str, tasks, clock: ComponentClock) -> dict:
    """Episodes of one policy on the starts; the decision-time split per step."""
    clock.reset()
    decisions: list[float] = []
    trace: list[list] = []  # per episode: chosen demos and stages (the outcome fingerprint)
    successes = 0
    expansions = reused = 0
    t0 = time.perf_counter()
    for task in tasks:
        record = training_episode(worker, name, task)
        successes += record.success
        trace.append([[st.chosen_key for st in record.steps], [st.stage for st in record.steps]])
        decisions += record.decision_times()
        expansions += sum(int(s.info.get("expansions", 0)) for s in record.steps)
        reused += sum(int(s.info.get("reused_expansions", 0)) for s in record.steps)
    wall = time.perf_counter() - t0
    n = max(len(decisions), 1)
    split = {c: clock.seconds.get(c, 0.0) / n for c in COMPONENTS}
    mean_decision = sum(decisions) / n
    split["overhead"] = max(0.0, wall / n - sum(split.values()))
    phases = {
        ph: {
            "s_per_decision": clock.phase_s[ph] / n,
            "steps": clock.phase_steps[ph],
            "steps_per_s": clock.phase_steps[ph] / clock.phase_s[ph] if clock.phase_s[ph] else None,
        }
        for ph in sim.EXECUTION_PHASES
    }
    return {
        "policy": name,
        "episodes": len(tasks),
        "successes": successes,
        "decisions": len(decisions),
        "median_decision_s": statistics.median(decisions) if decisions else None,
        "mean_decision_s": mean_decision,
        "expansions_per_decision": expansions / n,
        "reused_per_decision": reused / n,
        "executions_per_decision": clock.calls.get("simulation", 0) / n,
        "scans_per_decision": clock.calls.get("scan", 0) / n,
        "split_s_per_decision": split,
        "execution_phases": phases,
        "wall_s": wall,
        "fingerprint": hashlib.sha1(json.dumps(trace).encode()).hexdigest()[:12],
        "trace": trace,
    }


def format_report(rows: list[dict]) -> str:
    """The two tables: decision time split, and simulator speed per phase."""
    cols = (*COMPONENTS, "overhead")
    head = (
        "| policy | successes | decisions | median s | mean s | expansions (memo) | sims | "
        "scans (lib + lm) | " + " | ".join(cols) + " | fingerprint |"
    )
    lines = [
        "Seconds per step: decision (median, mean) and the whole step split by component "
        "(components sum to the wall time per step; a search simulates inside its decision)",
        head,
    ]
    lines.append("|" + "---|" * (9 + len(cols)))
    for r in rows:
        sp = r["split_s_per_decision"]
        lines.append(
            f"| {r['policy']} | {r['successes']}/{r['episodes']} | {r['decisions']} | "
            f"{r['median_decision_s']:.2f} | {r['mean_decision_s']:.2f} | "
            f"{r['expansions_per_decision']:.1f} ({r['reused_per_decision']:.1f}) | "
            f"{r['executions_per_decision']:.1f} | {r['scans_per_decision']:.1f} | "
            + " | ".join(f"{sp[c]:.2f}" for c in cols)
            + f" | `{r['fingerprint']}` |"
        )
    lines += ["", "Simulator per execution phase (all policies' executions together)"]
    lines += ["| phase | steps | s | steps/s | share of simulation |", "|---|---|---|---|---|"]
    total: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    for r in rows:
        for ph, v in r["execution_phases"].items():
            total[ph][0] += v["steps"]
            total[ph][1] += v["s_per_decision"] * r["decisions"]
    sim_s = sum(v[1] for v in total.values()) or 1.0
    for ph in sim.EXECUTION_PHASES:
        steps, sec = total[ph]
        rate = f"{steps / sec:,.0f}" if sec and steps else "-"
        lines.append(f"| {ph} | {int(steps):,} | {sec:.1f} | {rate} | {sec / sim_s:.0%} |")
    return "\n".join(lines)


def run_interactive(worker: BenchWorker, args: argparse.Namespace, tasks, clock) -> list[dict]:
    """The app's mode: a search level's expansions side by side on the app's SimPool."""
    from knotlab.app.web.sim_pool import PoolRunner, SimPool

    pool = SimPool(str(Path(args.library).resolve()), args.pool_workers)
    rows = []
    try:
        prefetches = {"on": (True,), "off": (False,), "both": (False, True)}[args.prefetch]
        memos = {"episode": (False,), "cold": (True,), "both": (False, True)}[args.memo]
        variants = [
            (n, p, c) for n in args.interactive.split(",") for p in prefetches for c in memos
        ]
        for name, prefetch, cold in variants:
            runner = PoolRunner(pool)
            runner.speculates = prefetch  # off: each level waits for the previous one whole
            agent = worker.agent.with_policy(name, runner=runner)
            policy = agent.policy
            tags = [f"app, {args.pool_workers} workers"]
            tags += [] if prefetch else ["no prefetch"]
            tags += ["cold"] if cold else []
            policy.name = f"{name} ({', '.join(tags)})"
            worker._agents[policy.name] = agent
            # warm the workers' featurizers for this model before timing
            run_episode(
                agent, worker.world, tasks[0].start_nodes_k3, task_id="warm-up", max_steps=1
            )
            policy.memo = type(policy.memo)()  # type: ignore[attr-defined]
            if cold:
                _forget_between_decisions(policy)
            rows.append(run_policy(worker, policy.name, tasks, clock))
            print(f"{policy.name}: {rows[-1]['median_decision_s']:.2f} s median decision")
    finally:
        pool.close()
    return rows


def _forget_between_decisions(policy) -> None:
    """Give every decision of ``policy`` an empty outcome memo, as the app's Inspect panel has:
    it searches a state loaded from its rope, so nothing an earlier search simulated matches."""
    choose = policy.choose

    def cold_choose(ctx):
        policy.memo = type(policy.memo)()
        return choose(ctx)

    policy.choose = cold_choose


def _warm_up(worker: BenchWorker, task) -> None:
    """Compile (or load) the numba kernels of both presets before anything is timed."""
    worker.agent.warm_up(worker.world, task.start_nodes_k3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--policies", default="la1x10,la2x5,oracle")
    parser.add_argument("--starts", type=int, default=4, help="first N training starts")
    parser.add_argument("--level", choices=defaults.LEVELS, default="main")
    parser.add_argument("--model", default=str(ROOT / "results" / "model_main.npz"))
    parser.add_argument("--library", default=str(defaults.LIBRARY_PATH))
    parser.add_argument(
        "--interactive",
        default="la2x5",
        help="also time these policies as the app runs them: each search level's expansions "
        "on a pool of --pool-workers processes ('' to skip)",
    )
    parser.add_argument("--pool-workers", type=int, default=2)
    parser.add_argument(
        "--prefetch",
        choices=("on", "off", "both"),
        default="on",
        help="app mode with the next level's certain expansions started early, without, or both",
    )
    parser.add_argument(
        "--memo",
        choices=("episode", "cold", "both"),
        default="both",
        help="app mode with the episode's memo (a decision reuses what the previous one "
        "simulated, as a bench or Agent episode does), with none (each decision from scratch, "
        "as the app's Inspect panel searches a loaded state), or both",
    )
    parser.add_argument("--json", action="store_true", help="also print one JSON object last")
    args = parser.parse_args()
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    if args.starts < 1:
        raise SystemExit("--starts must be >= 1")
    library = DemoLibrary.load(args.library)
    tasks = list(TaskSet.load(defaults.task_set_path(args.level, "train")))[: args.starts]
    model = QModel.load(args.model)
    worker = BenchWorker(WorkerSpec(library, model))
    _warm_up(worker, tasks[0])
    clock = ComponentClock()
    install(clock)
    rows = []
    for name in args.policies.split(","):
        worker.agent_for(name)
        rows.append(run_policy(worker, name, tasks, clock))
        print(f"{name}: {rows[-1]['median_decision_s']:.2f} s median decision", flush=True)
    if args.interactive:
        rows += run_interactive(worker, args, tasks, clock)
    info = machine_info()
    print(
        f"\nmachine: {info['cpu_model']} x {info['usable_cores']} cores "
        f"(load {info['load_average_1m']}); {args.starts} {args.level} training starts; "
        "one process, one BLAS thread\n"
    )
    print(format_report(rows))
    if args.json:
        print(json.dumps({"machine": info, "rows": rows}))


if __name__ == "__main__":
    main()
