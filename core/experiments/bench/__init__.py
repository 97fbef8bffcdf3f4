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

The package by job: `identity` (what defines a results folder), `outcome_log` (the episodes
finished), `engines` (local processes or Ray actors), `report` (the table and chart), `run`
(planning and running a benchmark).
"""

from knotlab.core.experiments.bench.engines import (
    ENGINES,
    SHARED_MEMO_SIZE,
    BenchWorker,
    Engine,
    EpisodeJob,
    WorkerSpec,
    group_by_task,
)
from knotlab.core.experiments.bench.identity import (
    LINE_IDENTITY_KEY,
    RUN_FILE,
    RunIdentity,
    identity_of_lines,
    line_identity,
    own_results_dir,
    stored_identity,
)
from knotlab.core.experiments.bench.outcome_log import (
    OUTCOMES_FILE,
    BenchMismatchError,
    OutcomeLog,
)
from knotlab.core.experiments.bench.report import (
    CHART_FILE,
    PAPER_TABLE1,
    RESULTS_FILE,
    RESULTS_FORMAT,
    RESULTS_VERSION,
    Z_95,
    format_table,
    package_versions,
    plot_table,
    summarize,
    wilson_interval,
)
from knotlab.core.experiments.bench.run import (
    BenchResult,
    TaskLimits,
    check_task_limits,
    episode_seed,
    is_search_policy,
    needs_model,
    plan_jobs,
    run_bench,
    task_limit,
    validate_policies,
    wanted_pairs,
)

__all__ = [
    "CHART_FILE",
    "ENGINES",
    "LINE_IDENTITY_KEY",
    "OUTCOMES_FILE",
    "PAPER_TABLE1",
    "RESULTS_FILE",
    "RESULTS_FORMAT",
    "RESULTS_VERSION",
    "RUN_FILE",
    "SHARED_MEMO_SIZE",
    "Z_95",
    "BenchMismatchError",
    "BenchResult",
    "BenchWorker",
    "Engine",
    "EpisodeJob",
    "OutcomeLog",
    "RunIdentity",
    "TaskLimits",
    "WorkerSpec",
    "check_task_limits",
    "episode_seed",
    "format_table",
    "group_by_task",
    "identity_of_lines",
    "is_search_policy",
    "line_identity",
    "needs_model",
    "own_results_dir",
    "package_versions",
    "plan_jobs",
    "plot_table",
    "run_bench",
    "stored_identity",
    "summarize",
    "task_limit",
    "validate_policies",
    "wanted_pairs",
    "wilson_interval",
]
