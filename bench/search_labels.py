"""Labels from the search: does greedy learn more from lookahead(2, 5)'s choices than the oracle's?

The oracle labels a state with the *cheapest* demo (registration-cost order) that can still reach
a knot, which says little about which demo leaves the easiest next state; lookahead(2, 5) ranks
demos by simulating them and valuing what follows, and ends in a knot far more often than the
oracle (Table I). This study rolls lookahead(2, 5) with the committed model out from each level's
*training* starts (the held-out fifth that `bench/level_models.py` scores on is never rolled
out), turns every episode that ends in a knot into a labelled execution (the search's choice in
each state is the expert's choice; source ``oracle``, labeller ``search-la2x5``, the model's hash
in its metadata), fits models on them with the committed settings, and scores each on both
levels' held-out starts exactly as `bench/level_models.py` does, so the rows are comparable with
its table (whose scores it prints beside them). An expert-iteration step: the search improves on
the model's one-step choice; the new model imitates the search.

Subcommands (resumable, same seeds, same files):
  rollout   lookahead episodes on the training starts -> <out>/rollouts_<level>.jsonl
  starts    the training starts outside the held-out fifth as a task-set file
            (<out>/starts_<level>.npz), for `knotlab label --task-set`
  fit       models from them, scored on held-out starts -> <out>/search.json, models, table
            (--arms A,B fits only those; --C X another slack weight, as arms named A-CX;
            --margin-scale M another margin scale, as arms named A-mM)

A second step (DAgger with the search as the expert): `knotlab label --search la2x5 --from-policy
greedy --policy-model <out>/model_search-both+floor.npz --task-set <out>/starts_main.npz
--tries-out <out>/tries_dagger_main.jsonl` labels the states greedy reaches with the search's
own episodes from there; `knotlab labels export` writes them to <out>/labels_dagger_main.jsonl,
and `fit` then adds the arm that trains on them too. A second round (`--round 2`, greedy with
that arm's model) goes to <out>/labels_dagger_main_r2.jsonl and <out>/tries_dagger_main_r2.jsonl.

Usage: .venv/bin/python bench/search_labels.py rollout --out-dir results/search_labels
       .venv/bin/python bench/search_labels.py fit --out-dir results/search_labels
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from level_models import (  # noqa: E402
    LEVELS,
    held_out_ranking,
    level_split,
    margin_weight,
    results_dir,
    slack_weight,
)
from policy_states import fit, greedy_success  # noqa: E402

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.demos.tasks import RopeTask, TaskSet  # noqa: E402
from knotlab.core.experiments.search_labels import (  # noqa: E402
    execution_from_episode,
    floor_tries,
    root_tries,
)
from knotlab.core.machine import machine_info  # noqa: E402
from knotlab.core.parallel import PerProcess, imap_processes  # noqa: E402
from knotlab.core.selection.labels import LabelledExecution  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.tries import TriedDemo, read_tries  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402
from knotlab.labeling_db.interchange import (  # noqa: E402
    FORMAT_NAME,
    FORMAT_VERSION,
    execution_to_dict,
    read_labels,
)
from knotlab.labeling_db.records import StoredExecution  # noqa: E402

SEARCH = "la2x5"
LABELLER = f"search-{SEARCH}"


@dataclass(frozen=True)
class RolloutJob:
    """One training start to roll the search out from."""

    library_path: str
    model_path: str
    level: str
    start: RopeTask


@dataclass(frozen=True)
class Rollout:
    """What the search did from one start, and its execution when it knotted cleanly."""

    level: str
    task_id: str
    knot: bool
    chosen: tuple[str, ...]
    outcomes: tuple[str, ...]
    stages: tuple[int, ...]
    root_tries: tuple[tuple[TriedDemo, ...], ...]  # per step: the search's first level
    wall_s: float
    execution: LabelledExecution | None


def _build(key: tuple[str, str]):
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    library_path, model_path = key
    return RopeWorld(), Agent(DemoLibrary.load(library_path), QModel.load(model_path), SEARCH)


_AGENTS = PerProcess(_build)


def rollout(job: RolloutJob) -> Rollout:
    """Play the search from the start; its steps become a labelled execution if it knotted
    with no failed step (a failed step is no choice to imitate)."""
    world, agent = _AGENTS.get((job.library_path, job.model_path))
    t0 = time.perf_counter()
    record = agent.run_episode(world, job.start)
    keys = agent.library.keys
    model_hash = agent.model.content_hash()
    execution = execution_from_episode(
        record,
        keys,
        execution_id=f"{LABELLER}-{job.start.task_id}",
        labeller=LABELLER,
        model_hash=model_hash,
        library_hash=agent.library.content_hash(),
        metadata={"labelled_by": {"policy": SEARCH, "model": model_hash}, "level": job.level},
    )
    return Rollout(
        job.level,
        job.start.task_id,
        bool(record.success),
        tuple(s.chosen_key for s in record.steps),
        tuple(str(s.outcome.value) for s in record.steps),
        tuple(int(s.stage) for s in record.steps),
        tuple(root_tries(s.info, keys) for s in record.steps),
        time.perf_counter() - t0,
        execution,
    )


def _rollouts_path(out: Path, level: str) -> Path:
    return out / f"rollouts_{level}.jsonl"


def _read_rollouts(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def cmd_rollout(args: argparse.Namespace) -> int:
    """Roll the search out from every level's training part (held-out starts excluded)."""
    task = get_task(args.task)
    files = results_dir(args.task)
    model = args.model or files / "level_models/model_hard.npz"
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for level in LEVELS:
        split = level_split(task, level, files / f"labels_oracle_{level}.jsonl")
        held = {s.task_id for s in split.held_out_starts}
        path = _rollouts_path(args.out_dir, level)
        done = {r["task_id"] for r in _read_rollouts(path)}
        starts = [s for s in task.files.load_task_set(level, "train") if s.task_id not in held]
        todo = [s for s in starts if s.task_id not in done][: args.limit]
        print(f"{level}: {len(done)} of {len(starts)} starts done; rolling {len(todo)}", flush=True)
        jobs = [RolloutJob(str(task.files.library_path), str(model), level, s) for s in todo]
        with path.open("a") as fh:
            for _, r in imap_processes(
                rollout, jobs, workers=args.workers, desc=f"{SEARCH} on {level} training starts"
            ):
                now = datetime.now(UTC)
                line = {
                    "task_id": r.task_id,
                    "level": r.level,
                    "knot": r.knot,
                    "chosen": list(r.chosen),
                    "outcomes": list(r.outcomes),
                    "stages": list(r.stages),
                    "root_tries": [[dataclasses.asdict(t) for t in ts] for ts in r.root_tries],
                    "wall_s": round(r.wall_s, 2),
                    "model": str(model),
                    "machine": machine_info()["cpu_model"],
                    "execution": None
                    if r.execution is None
                    else execution_to_dict(
                        StoredExecution(r.execution, started_at=now, finished_at=now)
                    ),
                }
                fh.write(json.dumps(line, sort_keys=True) + "\n")
                fh.flush()
    return 0


def search_executions(out: Path, level: str) -> list[LabelledExecution]:
    """The level's search executions (episodes that knotted cleanly), in start order."""
    import tempfile

    rows = sorted(
        (r for r in _read_rollouts(_rollouts_path(out, level)) if r["execution"]),
        key=lambda r: r["task_id"],
    )
    with tempfile.NamedTemporaryFile("w", suffix=".jsonl", delete=False) as fh:
        fh.write(json.dumps({"format": FORMAT_NAME, "version": FORMAT_VERSION}) + "\n")
        for r in rows:
            fh.write(json.dumps(r["execution"]) + "\n")
    try:
        return [item.execution for item in read_labels(fh.name)]
    finally:
        os.unlink(fh.name)


def dagger_files(out: Path, level: str, round_index: int = 1) -> tuple[Path, Path]:
    """A round's policy states of the level labelled by the search (`knotlab labels export`) and
    their floor tries (`knotlab label --tries-out`)."""
    tag = level if round_index == 1 else f"{level}_r{round_index}"
    return out / f"labels_dagger_{tag}.jsonl", out / f"tries_dagger_{tag}.jsonl"


def dagger_part(part: str) -> tuple[str, int]:
    """A policy-state part's level and round: "dagger-main" is round 1, "dagger2-main" round 2."""
    head, level = part.split("-", 1)
    return level, int(head.removeprefix("dagger") or 1)


def dagger_executions(out: Path, level: str, round_index: int = 1) -> list[LabelledExecution]:
    """A round's policy states of the level that the search labelled (knotted from), by id."""
    labels, _ = dagger_files(out, level, round_index)
    if not labels.exists():
        return []
    found = [item.execution for item in read_labels(labels) if item.execution.steps]
    return sorted(found, key=lambda e: e.execution_id)


def cmd_starts(args: argparse.Namespace) -> int:
    """Write each level's training starts outside the held-out fifth as a task-set file."""
    task = get_task(args.task)
    files = results_dir(args.task)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for level in LEVELS:
        split = level_split(task, level, files / f"labels_oracle_{level}.jsonl")
        held = {s.task_id for s in split.held_out_starts}
        full = task.files.load_task_set(level, "train")
        kept = TaskSet([s for s in full if s.task_id not in held], dict(full.metadata))
        path = args.out_dir / f"starts_{level}.npz"
        if path.exists() and TaskSet.load(path).content_hash() == kept.content_hash():
            print(f"{path}: {len(kept)} starts (already written)")
            continue
        kept.save(path)
        print(f"{path}: {len(kept)} of {len(full)} training starts (held-out fifth left out)")
    return 0


ARMS: dict[str, tuple[str, ...]] = {
    # parts: "search-<level>" the search's executions, "oracle-hard" the committed model's labels
    "search-hard": ("search-hard",),
    "search-both": ("search-main", "search-hard"),
    "search-both+floor": ("search-main", "search-hard", "floor"),
    "oracle-hard+search-both": ("oracle-hard", "search-main", "search-hard"),
    # the second step: + the states greedy (the model above) reached, labelled by the search
    "search-both+dagger-main+floor": ("search-main", "search-hard", "dagger-main", "floor"),
    "search-both+dagger-both+floor": (
        "search-main",
        "search-hard",
        "dagger-main",
        "dagger-hard",
        "floor",
    ),
    # a second round: greedy with the model just above, its reached states labelled likewise
    "search-both+dagger-both+dagger2-main+floor": (
        "search-main",
        "search-hard",
        "dagger-main",
        "dagger-hard",
        "dagger2-main",
        "floor",
    ),
}


def search_floor_tries(out: Path, level: str, task) -> dict:
    """The level's search states' root candidates that did not advance, as tries
    (`floor_tries`: they must lose by the state's median margin; the ones that advanced stay
    ordinary margin rows). A state's stage is the task's stage of its stored rope."""
    tries = {}
    by_id = {e.execution_id: e for e in search_executions(out, level)}
    for r in _read_rollouts(_rollouts_path(out, level)):
        if not r["execution"]:
            continue
        ex = by_id[r["execution"]["execution_id"]]
        before = [task.stage(s.rope_nodes_k3).stage for s in ex.steps]
        roots = [tuple(TriedDemo(**t) for t in step) for step in r["root_tries"]]
        for rec in floor_tries(ex.execution_id, before, roots):
            tries[(rec.execution_id, rec.step_index)] = rec
    return tries


def cmd_fit(args: argparse.Namespace) -> int:
    """Fit every arm with the committed settings; score it as bench/level_models.py does."""
    task = get_task(args.task)
    files = results_dir(args.task)
    shipped = QModel.load(task.files.model_path).hyperparameters
    D = float(shipped["D"])
    C, suffix = slack_weight(shipped, args.C)  # another C is its own arm: "<arm>-C<value>"
    margin_scale, m_suffix = margin_weight(shipped, args.margin_scale)  # "<arm>...-m<value>"
    suffix += m_suffix
    wanted = list(ARMS) if args.arms is None else args.arms.split(",")
    unknown = sorted(set(wanted) - set(ARMS))
    if unknown:
        raise SystemExit(f"--arms: unknown arm(s) {', '.join(unknown)}; known: {', '.join(ARMS)}")
    library_path = task.files.library_path
    library = DemoLibrary.load(library_path)
    out = args.out_dir
    path = out / "search.json"
    report = json.loads(path.read_text()) if path.exists() else {"models": {}}
    splits = {lv: level_split(task, lv, files / f"labels_oracle_{lv}.jsonl") for lv in LEVELS}
    held_ids = frozenset(e.execution_id for s in splits.values() for e in s.held_out)
    held_tasks = {e.task_id for s in splits.values() for e in s.held_out}
    parts: dict[str, list[LabelledExecution]] = {
        "oracle-hard": list(splits["hard"].train),
        **{f"search-{lv}": search_executions(out, lv) for lv in LEVELS},
        **{
            part: dagger_executions(out, *dagger_part(part))
            for arm in ARMS.values()
            for part in arm
            if part.startswith("dagger")
        },
    }
    for lv in LEVELS:
        leaked = [e.task_id for e in parts[f"search-{lv}"] if e.task_id in held_tasks]
        assert not leaked, f"search executions from held-out starts: {leaked[:3]}"
    for part, executions in parts.items():
        if part.startswith("dagger"):
            starts = {e.metadata["reached_by"]["start_task_id"] for e in executions}
            assert not starts & held_tasks, f"policy states from held-out starts: {part}"
    oracle_tries = read_tries(files / "tries_hard.jsonl")
    for arm_name in wanted:
        arm, name = ARMS[arm_name], arm_name + suffix
        rec = report["models"].get(name, {})
        model_path = out / f"model_{name}.npz"
        if model_path.exists() and rec.get("scores", {}).keys() >= set(LEVELS):
            print(f"{name}: {json.dumps(rec['scores'])}", flush=True)
            continue
        missing = [p for p in arm if p.startswith("dagger") and not parts[p]]
        if missing:
            print(f"{name}: not fitted, no labels for {', '.join(missing)} yet", flush=True)
            continue
        t0 = time.perf_counter()
        executions = [e for p in arm if p != "floor" for e in parts[p]]
        tries = dict(oracle_tries) if "oracle-hard" in arm else {}
        if "floor" in arm:
            for lv in LEVELS:
                tries.update(search_floor_tries(out, lv, task))
            for part in arm:
                if part.startswith("dagger"):
                    tries.update(read_tries(dagger_files(out, *dagger_part(part))[1]))
        fit(
            executions,
            library,
            held_ids,
            tries,
            model_path,
            args.workers,
            C=C,
            D=D,
            margin_scale=margin_scale,
        )
        rec = {
            "parts": list(arm),
            "C": C,
            "D": D,
            "margin_scale": margin_scale,
            "model": str(model_path),
            "model_hash": QModel.load(model_path).content_hash(),
            "train_executions": len(executions),
            "train_states": sum(len(e.steps) for e in executions),
            "scores": {},
        }
        for lv in LEVELS:
            s = splits[lv]
            success = greedy_success(
                library_path, model_path, list(s.held_out_starts), args.workers
            )
            rec["scores"][lv] = {
                "greedy_success": success,
                "starts": len(s.held_out_starts),
                **held_out_ranking(model_path, s, library),
            }
        rec["wall_s"] = round(time.perf_counter() - t0, 1)
        report["models"][name] = rec
        report["machine"] = machine_info()
        path.write_text(json.dumps(report, indent=1, sort_keys=True))
        print(f"{name}: {json.dumps(rec['scores'])}", flush=True)
    _table(report, files / "level_models/levels.json")
    return 0


def _table(report: dict, baseline: Path) -> None:
    rows = dict(report["models"])
    if baseline.exists():  # level_models' oracle-label rows: the same held-out starts
        for name, rec in json.loads(baseline.read_text())["models"].items():
            rows[f"oracle-{name} (level_models)"] = rec
    print(
        "| model | training states | "
        + " | ".join(f"{lv} greedy | {lv} top-1 | {lv} V-AUC" for lv in LEVELS)
        + " |"
    )
    print("|---|---|" + "---|" * (3 * len(LEVELS)))
    for name, rec in rows.items():
        cells = []
        for lv in LEVELS:
            sc = rec["scores"][lv]
            k, n = round(sc["greedy_success"] * sc["starts"]), sc["starts"]
            cells += [f"{k}/{n} = {k / n:.3f}", f"{sc['top1']:.3f}", f"{sc['value_auc']:.3f}"]
        print(f"| {name} | {rec['train_states']} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("rollout")
    r.add_argument("--out-dir", type=Path, required=True)
    r.add_argument("--task", default="overhand")
    r.add_argument("--model", type=Path, default=None)
    r.add_argument("--workers", type=int, default=2)
    r.add_argument("--limit", type=int, default=None, help="at most this many starts a level")
    r.set_defaults(func=cmd_rollout)
    st = sub.add_parser("starts")
    st.add_argument("--out-dir", type=Path, required=True)
    st.add_argument("--task", default="overhand")
    st.set_defaults(func=cmd_starts)
    f = sub.add_parser("fit")
    f.add_argument("--out-dir", type=Path, required=True)
    f.add_argument("--task", default="overhand")
    f.add_argument("--workers", type=int, default=2)
    f.add_argument("--arms", default=None, help="ARM,ARM,... (default: every arm)")
    f.add_argument(
        "--C", type=float, default=None, help="slack weight (default: the shipped model's)"
    )
    f.add_argument(
        "--margin-scale",
        type=float,
        default=None,
        help="how many value units the typical wrong demo must lose by (default: the shipped "
        "model's); another scale is its own arm, named A-m<value>",
    )
    f.set_defaults(func=cmd_fit)
    args = ap.parse_args()
    raise SystemExit(args.func(args))
