"""Run (or resume) a benchmark: plan the (policy, task) jobs still to do, run them on an engine,
write outcomes, results.json and the chart.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.demos.tasks import RopeTask, TaskSet
from knotlab.core.errors import InvalidInputError
from knotlab.core.experiments.bench.engines import (
    ENGINES,
    Engine,
    EpisodeJob,
    WorkerSpec,
    _run_local,
    _run_ray,
    log,
)
from knotlab.core.experiments.bench.identity import (
    LINE_IDENTITY_KEY,
    RUN_FILE,
    RunIdentity,
    _without_identity,
    _write_json_atomic,
    line_identity,
    stored_identity,
)
from knotlab.core.experiments.bench.outcome_log import OUTCOMES_FILE, OutcomeLog
from knotlab.core.experiments.bench.report import (
    CHART_FILE,
    RESULTS_FILE,
    RESULTS_FORMAT,
    RESULTS_VERSION,
    package_versions,
    plot_table,
    summarize,
)
from knotlab.core.machine import (
    kind_of_record,
    machine_info,
    numeric_kinds,
    other_kinds_warning,
)
from knotlab.core.seeds import derive_seed
from knotlab.core.selection.policies import policy_config
from knotlab.core.selection.qmodel import QModel
from knotlab.core.tasks import check_task_of, get_task
from knotlab.core.world.estimate import EstimatorKind
from knotlab.core.world.mismatch import NOMINAL_SETTING, PhysicsSetting
from knotlab.core.world.observation import ObservationModel


def needs_model(policy: str) -> bool:
    """True for policies that rank demos with a learned QModel (greedy, la<D>x<W>)."""
    return policy_config(policy).needs_model


def is_search_policy(policy: str) -> bool:
    """True for policies that simulate candidates at every step (lookahead, oracle): slow."""
    return policy_config(policy).simulates


def episode_seed(bench_seed: int, task_seed: int) -> int:
    """Observation-noise seed of one task: the same for every policy, so they see the same noise."""
    return derive_seed(bench_seed, task_seed)


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
    max_steps: int = 0  # the step limit the episodes ran under (the task's unless set)


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


def _warn_of_other_kinds(out: Path, finished: Iterable[Mapping]) -> None:
    """Say so when the episodes about to run join ones another kind of CPU made."""
    warning = other_kinds_warning(str(out), map(kind_of_record, finished), "episodes")
    if warning is not None:
        log.warning("%s: results.json counts the episodes of each kind", warning)


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
    world: PhysicsSetting = NOMINAL_SETTING,
    agent_model: PhysicsSetting = NOMINAL_SETTING,
    estimator: EstimatorKind = EstimatorKind.PERFECT,
) -> BenchResult:
    """Run (or resume) ``policies`` on the first ``n_tasks`` tasks; write outcomes and results.

    Table I runs on test sets only; ``training_study=True`` allows a training set instead, for
    diagnostic studies that choose settings (never a reported success rate).
    ``share_simulations``: run each task's policies on one worker with one outcome memo (the
    same outcomes, ~30 % less episode time on the main set; the decision times and expansion
    counts recorded are then those of a policy that found some simulations done).
    ``world``, ``agent_model``, ``estimator``: the physics of the world that executes, the physics
    the agent simulates with, and how it estimates the rope's state (default: the nominal world,
    simulated in itself); a combined setting draws each task's world with ``seed``.
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
    finished = outcome_log.load(strict=True)  # another file's lines are refused, not skipped
    identity = RunIdentity(
        lib_hash,
        task_set.content_hash(),
        int(seed),
        float(noise),
        int(max_steps),
        model.content_hash() if learned and model is not None else None,
        task.name,
        world.name,
        agent_model.name,
        estimator.value,
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
        _warn_of_other_kinds(out, finished.values())
        spec = WorkerSpec(library, model if learned else None, None, world, agent_model, estimator)
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
    reference = get_task(identity.task).reference_rates
    rows = [summarize(p, outcomes[p], reference) for p in policies]
    common_rows = None
    if len({r["n"] for r in rows}) > 1:
        n_common = min(r["n"] for r in rows)
        common_ids = {t.task_id for t in tasks[:n_common]}
        common_rows = [
            summarize(p, [r for r in outcomes[p] if r["task_id"] in common_ids], reference)
            for p in policies
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
        # What every task's world and the agent's model were (a combined setting's per-task
        # draws are on each outcome line, "world_scales").
        "physics": {
            "world": world.record(),
            "agent_model": agent_model.record(),
            "estimator": estimator.value,
        },
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
        # Which CPU kinds ran the episodes of this table (one, unless the folder was resumed on
        # another kind of machine or ran on a mixed cluster).
        "numeric_kinds": numeric_kinds(r for recs in outcomes.values() for r in recs),
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
    level = task_set.metadata.get("level", "")
    chart = plot_table(
        rows,
        out / CHART_FILE,
        title=f"{task.name}: {level} test, within {int(max_steps)} steps",
    )
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
        int(max_steps),
    )


def validate_policies(policies: Sequence[str]) -> None:
    """Raise InvalidInputError naming the first policy name the registry does not know."""
    for p in policies:
        policy_config(p)
