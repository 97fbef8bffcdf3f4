"""Table I: many episodes of many policies in parallel, resumable, with Wilson intervals.

One *job* is one (policy, task) episode. Jobs run on local worker processes (default) or Ray
actors; each worker builds its simulator, featurizer (registration cache warm), transferer,
model and policies once (:class:`BenchWorker`) and reuses them for every job it gets.

Resumability: every finished episode is appended to ``out/outcomes.jsonl`` (one JSON line per
(policy, task), flushed and fsynced), and ``out/run.json`` keeps the identity of the run (library,
task set, model, seed, observation noise, steps). Each outcome line carries that identity too
(under ``"run"``; the model hash only on lines of learned policies), so outcomes whose run.json was
lost can still be checked. A rerun with the same ``out`` skips the (policy, task) pairs already
there and refuses to mix results if the identity differs, or if it cannot tell (outcome lines
without an identity and no run.json). More tasks or other policies may be added to an existing
run; the model hash is only pinned once a learned policy has run. A model and a library that do
not belong together are refused before anything is written.

Success rates carry Wilson score 95 % intervals:
    centre = (k + z^2/2) / (n + z^2),  half = z sqrt(k (n - k) / n + z^2 / 4) / (n + z^2).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TextIO, get_args

import numpy as np

from knotlab.core.atomic import atomic_open, atomic_path
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.demos.tasks import RopeTask, TaskSet
from knotlab.core.errors import InvalidInputError, KnotlabError
from knotlab.core.execution.memo import OutcomeMemo
from knotlab.core.machine import machine_info
from knotlab.core.parallel import PerProcess
from knotlab.core.seeds import derive_seed
from knotlab.core.selection.policies import policy_config
from knotlab.core.selection.qmodel import QModel
from knotlab.core.tasks import check_task_of, get_task
from knotlab.core.world.observation import ObservationModel

if TYPE_CHECKING:  # the agent imports the simulator's records: only for the checker
    from knotlab.core.agent import Agent

log = logging.getLogger(__name__)

RESULTS_FORMAT = "knotlab-bench-results"
RESULTS_VERSION = 1
OUTCOMES_FILE = "outcomes.jsonl"
RUN_FILE = "run.json"
LINE_IDENTITY_KEY = "run"  # the key under which each outcome line records its run's identity
RESULTS_FILE = "results.json"
CHART_FILE = "table1.png"
Z_95 = 1.959963984540054
Engine = Literal["local", "ray"]  # where episodes run: worker processes here, or Ray actors
ENGINES: tuple[Engine, ...] = get_args(Engine)
# Outcomes one task's policies may share: ~70 simulations a task on the main set (measured,
# bench/sharing.py), each a few hundred kB with its trajectory, so a task never evicts.
SHARED_MEMO_SIZE = 512
# The paper's Table I (success within 5 steps); no oracle row there.
PAPER_TABLE1: dict[str, float] = {"nn": 0.688, "greedy": 0.856, "la1x10": 0.936, "la2x5": 0.952}


class BenchMismatchError(KnotlabError):
    """An output directory holds results made with different defining arguments."""


def needs_model(policy: str) -> bool:
    """True for policies that rank demos with a learned QModel (greedy, la<D>x<W>)."""
    return policy_config(policy).needs_model


def is_search_policy(policy: str) -> bool:
    """True for policies that simulate candidates at every step (lookahead, oracle): slow."""
    return policy_config(policy).simulates


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (scipy's; (nan, nan) for n = 0)."""
    from scipy.stats import binomtest, norm

    if n < 0 or not 0 <= successes <= n:
        raise InvalidInputError(f"need 0 <= successes <= n, got {successes} of {n}")
    if n == 0:
        return (math.nan, math.nan)
    ci = binomtest(int(successes), int(n)).proportion_ci(
        confidence_level=float(2 * norm.cdf(z) - 1), method="wilson"
    )
    return (float(ci.low), float(ci.high))


def episode_seed(bench_seed: int, task_seed: int) -> int:
    """Observation-noise seed of one task: the same for every policy, so they see the same noise."""
    return derive_seed(bench_seed, task_seed)


# ---------------------------------------------------------------------------- run identity


@dataclass(frozen=True)
class RunIdentity:
    """What defines the numbers in a results directory; a rerun must match it."""

    library_hash: str
    task_set_hash: str
    seed: int
    noise: float
    max_steps: int
    model_hash: str | None = None  # None until a learned policy ran
    task: str = "overhand"  # results made before tasks were named are the overhand knot's

    def differences(self, stored: RunIdentity) -> list[str]:
        """'name: stored X, now Y' for every field that differs (a model hash not yet pinned on
        either side does not)."""
        diffs = [
            f"{name}: stored {getattr(stored, name)!r}, now {getattr(self, name)!r}"
            for name in ("library_hash", "task_set_hash", "seed", "noise", "max_steps", "task")
            if getattr(stored, name) != getattr(self, name)
        ]
        if (
            stored.model_hash is not None
            and self.model_hash is not None
            and stored.model_hash != self.model_hash
        ):
            diffs.append(f"model_hash: stored {stored.model_hash!r}, now {self.model_hash!r}")
        return diffs

    def merged(self, stored: RunIdentity | None) -> RunIdentity:
        """This identity checked against ``stored`` (raises BenchMismatchError on a difference)."""
        if stored is None:
            return self
        diffs = self.differences(stored)
        if diffs:
            raise BenchMismatchError(
                "the output directory holds results made with different arguments ("
                + "; ".join(diffs)
                + "); use a new --out directory or the original arguments"
            )
        return RunIdentity(**{**asdict(self), "model_hash": self.model_hash or stored.model_hash})


def _read_identity(path: Path) -> RunIdentity | None:
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return RunIdentity(**data["identity"])
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise BenchMismatchError(f"{path}: unreadable run identity ({exc})") from exc


def line_identity(identity: RunIdentity, policy: str) -> dict:
    """The run identity an outcome line records (its model only where ``policy`` uses one)."""
    return {**asdict(identity), "model_hash": identity.model_hash if needs_model(policy) else None}


def _line_identity_of(made: object, where: Path) -> RunIdentity:
    try:
        return RunIdentity(**made)  # type: ignore[arg-type]
    except TypeError as exc:  # not a dict, or other fields
        raise BenchMismatchError(f"{where}: unreadable run identity in a line ({exc})") from exc


def identity_of_lines(finished: dict[tuple[str, str], dict], where: Path) -> RunIdentity | None:
    """The one run identity the outcome lines record; None when there are no lines.

    Raises BenchMismatchError when a line records none (written before lines carried it) or when
    lines record different identities (outcomes of two runs in one file).
    """
    if not finished:
        return None
    found: set[RunIdentity] = set()
    models: set[str] = set()
    for (policy, task_id), rec in finished.items():
        made = rec.get(LINE_IDENTITY_KEY)
        if not isinstance(made, dict):
            raise BenchMismatchError(
                f"{where}: the outcome of {policy} on {task_id} does not record the run that made "
                f"it and there is no {RUN_FILE} beside it, so it cannot be checked against this "
                "run; use a new --out directory"
            )
        line = _line_identity_of(made, where)
        if line.model_hash is not None:
            models.add(line.model_hash)
        found.add(RunIdentity(**{**asdict(line), "model_hash": None}))
    if len(found) > 1 or len(models) > 1:
        raise BenchMismatchError(
            f"{where}: holds the outcomes of {max(len(found), len(models))} different runs; "
            "use a new --out directory"
        )
    return RunIdentity(**{**asdict(found.pop()), "model_hash": next(iter(models), None)})


def stored_identity(out: Path, finished: dict[tuple[str, str], dict]) -> RunIdentity | None:
    """What made the results in ``out``: run.json, checked against the outcome lines' identity."""
    from_file = _read_identity(out / RUN_FILE)
    if from_file is None:
        return identity_of_lines(finished, out / OUTCOMES_FILE)
    for (policy, task_id), rec in finished.items():
        made = rec.get(LINE_IDENTITY_KEY)
        if made is None:  # a line from before lines carried the identity: run.json vouches
            continue
        made_by = _line_identity_of(made, out / OUTCOMES_FILE)
        diffs = made_by.differences(RunIdentity(**line_identity(from_file, policy)))
        if diffs:
            raise BenchMismatchError(
                f"{out / OUTCOMES_FILE}: the outcome of {policy} on {task_id} was made by another "
                f"run than {out / RUN_FILE} records ({'; '.join(diffs)}); use a new --out directory"
            )
    return from_file


def _without_identity(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k != LINE_IDENTITY_KEY}


def _write_json_atomic(path: Path, data: dict) -> None:
    with atomic_open(path) as fh:
        json.dump(data, fh, indent=1, sort_keys=False, allow_nan=True)
        fh.write("\n")


# ---------------------------------------------------------------------------- outcome log


class OutcomeLog:
    """Append-only JSONL of finished episodes; a torn last line (crash mid-write) is dropped."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def load(self) -> dict[tuple[str, str], dict]:
        """Finished episodes by (policy, task_id); later lines win."""
        out: dict[tuple[str, str], dict] = {}
        if not self.path.exists():
            return out
        with open(self.path, encoding="utf-8") as fh:
            for n, line in enumerate(fh, start=1):
                if not line.endswith("\n"):
                    log.warning("%s:%d: ignoring a torn last line", self.path, n)
                    break
                try:
                    rec = json.loads(line)
                    out[(rec["policy"], rec["task_id"])] = rec
                except (json.JSONDecodeError, KeyError, TypeError):
                    log.warning("%s:%d: ignoring an unreadable line", self.path, n)
        return out

    def _repair_tail(self) -> None:
        """Cut a torn last line so the next append starts on a fresh line."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return
        with open(self.path, "rb+") as fh:
            data = fh.read()
            if data.endswith(b"\n"):
                return
            fh.truncate(data.rfind(b"\n") + 1)

    def open(self) -> TextIO:
        """A line-appending handle (repairs the tail first)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._repair_tail()
        return open(self.path, "a", encoding="utf-8")

    @staticmethod
    def append(fh: TextIO, record: dict) -> None:
        """Write one record as a line, flushed and fsynced (survives a crash right after)."""
        fh.write(json.dumps(record, allow_nan=True) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


# ---------------------------------------------------------------------------- workers


@dataclass(frozen=True, eq=False)
class EpisodeJob:
    """One episode to run: a policy on a task."""

    policy: str
    task_index: int
    task_id: str
    start_nodes_k3: np.ndarray
    seed: int
    max_steps: int
    noise: float


@dataclass(frozen=True, eq=False)
class WorkerSpec:
    """What every worker needs to build its warm state (pickled once per worker)."""

    library: DemoLibrary
    model: QModel | None = None
    task: str | None = None  # None: the task the library records


class BenchWorker:
    """A worker's warm state: a world and one agent per policy, all on one warm featurizer."""

    def __init__(self, spec: WorkerSpec) -> None:
        from knotlab.core.agent import Agent
        from knotlab.core.parallel import single_thread_blas
        from knotlab.core.world.sim import RopeWorld

        single_thread_blas()
        self.spec = spec
        self.world = RopeWorld()
        # The base agent (nearest neighbour) checks the library and model once and warms the
        # registrar; every policy's agent shares its caches.
        self.agent = Agent(spec.library, spec.model, "nn", task=spec.task)
        self._agents: dict[str, Agent] = {"nn": self.agent}
        self.node = _ray_node_id()

    def agent_for(self, name: str) -> Agent:
        """The agent of policy ``name``, built on first use."""
        if name not in self._agents:
            self._agents[name] = self.agent.with_policy(name)
        return self._agents[name]

    def run_group(self, jobs: Sequence[EpisodeJob]) -> list[dict]:
        """Run one task's episodes (one per policy) with one outcome memo shared between them.

        An execution one policy simulated is restored, not simulated, when another asks for it
        from the same state and cloud: the same episodes (bit-identical), less simulation. The
        memo lives for this task only.
        """
        memo = OutcomeMemo(size=SHARED_MEMO_SIZE)
        return [self.run(job, memo) for job in jobs]

    def run(self, job: EpisodeJob, memo: OutcomeMemo | None = None) -> dict:
        """Run one episode; never raises (an unexpected error is a failure of kind "error")."""
        from knotlab.core.experiments.episode import run_episode
        from knotlab.core.world.sim import RopeWorld

        t0 = time.perf_counter()
        try:
            record = run_episode(
                self.agent_for(job.policy),
                self.world,
                job.start_nodes_k3,
                task_id=job.task_id,
                seed=job.seed,
                max_steps=job.max_steps,
                observe_noise=job.noise,
                memo=memo,
            )
            out = record.summary()
        except Exception as exc:  # a long benchmark must outlive one bad task
            log.error("%s on %s crashed: %s", job.policy, job.task_id, traceback.format_exc())
            out = _error_record(job, f"{type(exc).__name__}: {exc}")
            out["wall_s"] = round(time.perf_counter() - t0, 4)
            with contextlib.suppress(Exception):  # the world may be broken: start afresh
                self.world.close()
            self.world = RopeWorld()
        out.update(task_index=job.task_index, seed=job.seed, pid=os.getpid())
        if self.node is not None:
            out["node"] = self.node  # which Ray node ran it: per-node throughput
        return out

    def close(self) -> None:
        """Release the simulator."""
        self.world.close()


def _ray_node_id() -> str | None:
    """The Ray node this process runs on, when it is a Ray worker (else None)."""
    import sys

    ray = sys.modules.get("ray")  # imported only where Ray runs us: never import it here
    if ray is None or not ray.is_initialized():
        return None
    try:
        return str(ray.get_runtime_context().get_node_id())
    except Exception:  # an old or partial Ray: the node is only a label
        return None


# This process's warm state (pool worker or in-process); Ray actors hold a BenchWorker instead.
_WORKER: PerProcess[BenchWorker] = PerProcess(BenchWorker)


def _init_process(spec: WorkerSpec) -> None:
    _WORKER.reset()
    _WORKER.get(spec)


def _run_in_process(job: EpisodeJob) -> dict:
    return _WORKER.current().run(job)


def _run_group_in_process(jobs: list[EpisodeJob]) -> list[dict]:
    return _WORKER.current().run_group(jobs)


def group_by_task(jobs: Sequence[EpisodeJob]) -> list[list[EpisodeJob]]:
    """The jobs of each task together (task-major order kept): a shared-memo unit of work."""
    groups: dict[str, list[EpisodeJob]] = {}
    for job in jobs:
        groups.setdefault(job.task_id, []).append(job)
    return list(groups.values())


def _run_local(
    jobs: list[EpisodeJob],
    spec: WorkerSpec,
    workers: int | None,
    on_result: Callable[[dict], None],
    progress: bool,
    share: bool = False,
) -> None:
    """Jobs on local worker processes; with ``share``, a task's jobs on one worker together."""
    from knotlab.core.parallel import imap_processes

    if share:
        for _, results in imap_processes(
            _run_group_in_process,
            group_by_task(jobs),
            workers=workers,
            initializer=partial(_init_process, spec),
            desc="bench tasks (shared simulations)",
            progress=progress,
        ):
            for result in results:
                on_result(result)
        return
    for _, result in imap_processes(
        _run_in_process,
        jobs,
        workers=workers,
        initializer=partial(_init_process, spec),
        desc="bench episodes",
        progress=progress,
    ):
        on_result(result)


def _run_ray(
    jobs: list[EpisodeJob],
    spec: WorkerSpec,
    workers: int | None,
    on_result: Callable[[dict], None],
    progress: bool,
    address: str | None = None,
    share: bool = False,
) -> None:
    """Same jobs on Ray actors (one per worker, each holding a BenchWorker); one job at a time
    (with ``share``: one task's jobs at a time, see `BenchWorker.run_group`)."""
    try:
        import ray
    except ImportError as exc:
        raise InvalidInputError(
            "--engine ray needs the ray package: pip install 'ray[default]'"
        ) from exc
    from tqdm import tqdm

    started = False
    if not ray.is_initialized():
        blas = {v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
        kwargs: dict = {"runtime_env": {"env_vars": blas}, "include_dashboard": False}
        if address is None and workers is not None:
            kwargs["num_cpus"] = workers
        # No address: a private local instance ("local"), never an already running cluster
        # that ray.init would otherwise join (and refuse num_cpus for).
        ray.init(address=address or "local", **kwargs)
        started = True
    n_actors = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
    units = group_by_task(jobs) if share else [[job] for job in jobs]
    n_actors = max(1, min(n_actors, len(units)))
    actor_cls = ray.remote(num_cpus=1)(BenchWorker)
    spec_ref = ray.put(spec)
    actors = [actor_cls.remote(spec_ref) for _ in range(n_actors)]
    queue = list(reversed(units))
    pending: dict = {}

    def submit(actor: Any) -> None:  # a Ray actor handle
        if queue:
            unit = queue.pop()
            ref = actor.run_group.remote(unit) if share else actor.run.remote(unit[0])
            pending[ref] = (actor, unit)

    bar = tqdm(total=len(jobs), desc="bench episodes (ray)", disable=not progress)
    try:
        for actor in actors:
            submit(actor)
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            actor, unit = pending.pop(done[0])
            try:
                got = ray.get(done[0])
                results = got if share else [got]
            except ray.exceptions.RayError as exc:  # the actor died: record, replace, go on
                log.error("ray actor failed on %s/%s: %s", unit[0].policy, unit[0].task_id, exc)
                results = [_error_record(job, f"ray: {type(exc).__name__}: {exc}") for job in unit]
                actor = actor_cls.remote(spec_ref)
            for result in results:
                on_result(result)
            bar.update(len(results))
            submit(actor)
    finally:
        bar.close()
        for actor in actors:
            ray.kill(actor)  # type: ignore[arg-type]
        if started:
            ray.shutdown()


def _error_record(job: EpisodeJob, message: str) -> dict:
    from knotlab.core.experiments.episode import EpisodeOutcome

    row = EpisodeOutcome.errored(job.task_id, job.policy, message).to_dict()
    return {**row, "task_index": job.task_index, "seed": job.seed}


# ---------------------------------------------------------------------------- the table


def summarize(policy: str, records: Sequence[dict]) -> dict:
    """One Table I row: successes, rate, Wilson 95 %, decision time per step, steps, failures."""
    n = len(records)
    k = sum(bool(r["success"]) for r in records)
    lo, hi = wilson_interval(k, n)
    decide = [t for r in records for t in r.get("decision_s", []) if t is not None]
    decide = [t for t in decide if math.isfinite(t)]
    failures = Counter(r["failure_kind"] for r in records if not r["success"])
    return {
        "policy": policy,
        "n": n,
        "successes": k,
        "rate": k / n if n else math.nan,
        "wilson_low": lo,
        "wilson_high": hi,
        "paper_rate": PAPER_TABLE1.get(policy),
        "mean_decision_s_per_step": float(np.mean(decide)) if decide else math.nan,
        "mean_steps": float(np.mean([r["n_steps"] for r in records])) if n else math.nan,
        "mean_steps_success": (
            float(np.mean([r["n_steps"] for r in records if r["success"]])) if k else math.nan
        ),
        "mean_episode_wall_s": float(np.mean([r["wall_s"] for r in records])) if n else math.nan,
        "failures": dict(sorted(failures.items())),
    }


def format_table(rows: Sequence[dict], title: str = "Table I") -> str:
    """Plain-text Table I: ours next to the paper's figure."""
    head = (
        f"{'policy':<8} {'success':>9} {'rate':>7} {'95% Wilson':>15} {'paper':>7} "
        f"{'decide s/step':>13} {'steps':>6}  failures"
    )
    lines = [title, head, "-" * len(head)]
    for r in rows:
        paper = f"{100 * r['paper_rate']:.1f}%" if r["paper_rate"] is not None else "-"
        interval = f"[{100 * r['wilson_low']:.1f}, {100 * r['wilson_high']:.1f}]"
        fails = ", ".join(f"{k} {v}" for k, v in r["failures"].items()) or "-"
        lines.append(
            f"{r['policy']:<8} {r['successes']:>4}/{r['n']:<4} {100 * r['rate']:>6.1f}% "
            f"{interval:>15} {paper:>7} {r['mean_decision_s_per_step']:>13.3f} "
            f"{r['mean_steps']:>6.2f}  {fails}"
        )
    return "\n".join(lines)


def plot_table(rows: Sequence[dict], path: str | Path, title: str = "") -> Path:
    """Bar chart of success rates with Wilson 95 % error bars and the paper's figures (Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    fig = Figure(figsize=(1.6 + 1.3 * len(rows), 4.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(rows))
    rate = np.array([100 * r["rate"] for r in rows])
    err = np.array(
        [
            [100 * (r["rate"] - r["wilson_low"]) for r in rows],
            [100 * (r["wilson_high"] - r["rate"]) for r in rows],
        ]
    )
    ax.bar(x, rate, width=0.6, color="#4C72B0", label="knotlab", yerr=err, capsize=5)
    paper = [(i, 100 * r["paper_rate"]) for i, r in enumerate(rows) if r["paper_rate"] is not None]
    if paper:
        ax.scatter(*zip(*paper, strict=True), marker="D", color="#DD8452", zorder=3, label="paper")
    for i, r in enumerate(rows):
        top = 100 * r["wilson_high"] if math.isfinite(r["wilson_high"]) else 0.0
        ax.annotate(f"{r['successes']}/{r['n']}", (i, top + 2), ha="center", fontsize=8)
    ax.set_xticks(x, [r["policy"] for r in rows])
    ax.set_ylim(0, 110)
    ax.set_ylabel("success rate (%)  [Wilson 95 %]")
    ax.set_title(title or "Overhand knot within 5 steps")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    return path


def package_versions() -> dict[str, str | None]:
    """Versions of the packages that decide the numbers."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for name in ("numpy", "scipy", "pybullet", "cvxpy", "clarabel", "knotlab", "ray"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


# ---------------------------------------------------------------------------- orchestration


@dataclass
class BenchResult:
    """What a bench run produced: the table, every outcome used, and where files went."""

    rows: list[dict]
    common_rows: list[dict] | None
    outcomes: dict[str, list[dict]]
    ran: int
    skipped: int
    wall_s: float
    paths: dict[str, str] = field(default_factory=dict)
    results: dict = field(default_factory=dict)


TaskLimits = int | Mapping[str, int] | None


def task_limit(policy: str, first: TaskLimits) -> int | None:
    """How many of the first tasks ``policy`` runs under ``first`` (None: all of them).

    ``first`` is None (every policy runs every task), an int K (the search policies run the first
    K tasks, the others all) or a mapping policy -> K (those policies the first K, the rest all).
    """
    if first is None:
        return None
    if isinstance(first, int):
        return first if is_search_policy(policy) else None
    return first.get(policy)


def check_task_limits(first: TaskLimits, policies: Sequence[str]) -> None:
    """Raise InvalidInputError for a limit below 1 or one naming a policy not being run."""
    if first is None:
        return
    if isinstance(first, int):
        if first < 1:
            raise InvalidInputError(f"--first must be >= 1, got {first}")
        return
    for name, k in first.items():
        if name not in policies:
            raise InvalidInputError(
                f"--first names {name!r}, which is not among the policies run "
                f"({', '.join(policies)})"
            )
        if k < 1:
            raise InvalidInputError(f"--first must be >= 1, got {k} for {name}")


def wanted_pairs(
    tasks: Sequence[RopeTask], policies: Sequence[str], first: TaskLimits = None
) -> list[tuple[int, RopeTask, str]]:
    """(task index, task, policy) of every episode a table asks for, task-major."""
    limits = {policy: task_limit(policy, first) for policy in policies}
    return [
        (i, task, policy)
        for i, task in enumerate(tasks)
        for policy in policies
        if limits[policy] is None or i < limits[policy]  # type: ignore[operator]
    ]


def plan_jobs(
    tasks: Sequence,
    policies: Sequence[str],
    done: Iterable[tuple[str, str]],
    *,
    seed: int,
    max_steps: int,
    noise: float,
    first: TaskLimits = None,
) -> list[EpisodeJob]:
    """Jobs still to run, task-major (all policies of task 0, then task 1, ...)."""
    done = set(done)
    return [
        EpisodeJob(
            policy,
            i,
            task.task_id,
            task.start_nodes_k3,
            episode_seed(seed, task.seed),
            max_steps,
            noise,
        )
        for i, task, policy in wanted_pairs(tasks, policies, first)
        if (policy, task.task_id) not in done
    ]


def run_bench(
    out_dir: str | Path,
    *,
    library: DemoLibrary,
    task_set: TaskSet,
    policies: Sequence[str],
    n_tasks: int,
    model: QModel | None = None,
    seed: int = 0,
    noise: float = 0.0,
    max_steps: int | None = None,
    first: TaskLimits = None,
    workers: int | None = None,
    engine: Engine = "local",
    ray_address: str | None = None,
    progress: bool = True,
    arguments: dict | None = None,
    training_study: bool = False,
    share_simulations: bool = False,
) -> BenchResult:
    """Run (or resume) ``policies`` on the first ``n_tasks`` tasks; write outcomes and results.

    Table I runs on test sets only; ``training_study=True`` allows a training set instead, for
    diagnostic studies that choose settings (never a reported success rate).
    ``share_simulations``: run each task's policies on one worker with one outcome memo (the
    same outcomes, ~30 % less episode time on the main set; the decision times and expansion
    counts recorded are then those of a policy that found some simulations done).
    """
    t0 = time.perf_counter()
    policies = list(dict.fromkeys(policies))
    if not policies:
        raise InvalidInputError("no policies given")
    if engine not in ENGINES:
        raise InvalidInputError(f"engine must be one of {ENGINES}, got {engine!r}")
    if n_tasks < 1:
        raise InvalidInputError(f"the number of tasks must be >= 1, got {n_tasks}")
    if n_tasks > len(task_set):
        raise InvalidInputError(f"asked for {n_tasks} tasks, the task set has {len(task_set)}")
    if task_set.split != "test" and not training_study:
        raise InvalidInputError(f"benchmarks run on a test set, got a {task_set.split!r} set")
    check_task_limits(first, policies)
    if not (math.isfinite(noise) and noise >= 0):
        raise InvalidInputError(f"observation noise must be finite and >= 0, got {noise}")
    learned = [p for p in policies if needs_model(p)]
    validate_policies(policies)
    if learned and model is None:
        raise InvalidInputError(f"policies {learned} need a trained model")
    lib_hash = library.content_hash()
    task = get_task(library.task)
    check_task_of("task set", task_set.metadata.get("task"), task)
    max_steps = task.step_limit if max_steps is None else max_steps
    if learned and model is not None:
        from knotlab.core.selection.compatibility import check_compatible
        from knotlab.core.selection.features import LibraryFeaturizer

        # Every worker builds an Agent that checks this again; a mismatch found there would
        # surface as a broken pool after run.json was written. Found here, nothing is.
        check_compatible(library, model, task)
        LibraryFeaturizer.for_model(library, model)  # its feature columns match the model's
    observation = ObservationModel.of_library_metadata(library.metadata)

    out = Path(out_dir)
    outcome_log = OutcomeLog(out / OUTCOMES_FILE)
    finished = outcome_log.load()
    identity = RunIdentity(
        lib_hash,
        task_set.content_hash(),
        int(seed),
        float(noise),
        int(max_steps),
        model.content_hash() if learned and model is not None else None,
        task.name,
    ).merged(stored_identity(out, finished))
    out.mkdir(parents=True, exist_ok=True)
    _write_json_atomic(out / RUN_FILE, {"identity": asdict(identity)})

    tasks = list(task_set)[:n_tasks]
    jobs = plan_jobs(
        tasks, policies, finished, seed=seed, max_steps=max_steps, noise=noise, first=first
    )
    skipped = len(wanted_pairs(tasks, policies, first)) - len(jobs)
    log.info("%d episodes to run, %d already finished", len(jobs), skipped)
    ran = 0
    if jobs:
        spec = WorkerSpec(library, model if learned else None)
        with outcome_log.open() as fh:

            def on_result(rec: dict) -> None:
                nonlocal ran
                rec = {**rec, LINE_IDENTITY_KEY: line_identity(identity, rec["policy"])}
                OutcomeLog.append(fh, rec)
                finished[(rec["policy"], rec["task_id"])] = rec
                ran += 1

            share = share_simulations
            if engine == "ray":
                _run_ray(jobs, spec, workers, on_result, progress, ray_address, share)
            else:
                _run_local(jobs, spec, workers, on_result, progress, share)

    outcomes: dict[str, list[dict]] = {p: [] for p in policies}
    for _, t, p in wanted_pairs(tasks, policies, first):
        if (p, t.task_id) in finished:
            outcomes[p].append(_without_identity(finished[(p, t.task_id)]))
    rows = [summarize(p, outcomes[p]) for p in policies]
    common_rows = None
    if len({r["n"] for r in rows}) > 1:
        n_common = min(r["n"] for r in rows)
        common_ids = {t.task_id for t in tasks[:n_common]}
        common_rows = [
            summarize(p, [r for r in outcomes[p] if r["task_id"] in common_ids]) for p in policies
        ]
    wall = time.perf_counter() - t0
    results = {
        "format": RESULTS_FORMAT,
        "version": RESULTS_VERSION,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "arguments": dict(arguments or {}),
        "identity": asdict(identity),
        "library_hash": lib_hash,
        "task": library.task,
        "observation_model": observation.value,
        "model_hash": model.content_hash() if model is not None else None,
        "model_hyperparameters": model.hyperparameters if model is not None else None,
        "task_set_hash": identity.task_set_hash,
        "training_study": training_study,
        "task_set": {"metadata": task_set.metadata, "n_total": len(task_set), "n_used": n_tasks},
        "policies": policies,
        "first": first if first is None or isinstance(first, int) else dict(first),
        "seeds": {
            "bench_seed": int(seed),
            "task_seeds": {t.task_id: int(t.seed) for t in tasks},
            "episode_seeds": {t.task_id: episode_seed(seed, t.seed) for t in tasks},
        },
        "packages": package_versions(),
        "machine": machine_info(),
        "engine": engine,
        "workers": workers,
        "episodes_run": ran,
        "episodes_resumed": skipped,
        "wall_s": round(wall, 3),
        "table": rows,
        "table_common_tasks": common_rows,
        "outcomes": outcomes,
    }
    _write_json_atomic(out / RESULTS_FILE, results)
    chart = plot_table(rows, out / CHART_FILE, title=f"{task_set.metadata.get('level', '')} test")
    return BenchResult(
        rows,
        common_rows,
        outcomes,
        ran,
        skipped,
        wall,
        {
            "results": str(out / RESULTS_FILE),
            "chart": str(chart),
            "outcomes": str(out / OUTCOMES_FILE),
        },
        results,
    )


def validate_policies(policies: Sequence[str]) -> None:
    """Raise InvalidInputError naming the first policy name the registry does not know."""
    for p in policies:
        policy_config(p)
