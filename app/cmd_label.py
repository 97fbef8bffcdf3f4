"""`knotlab label --oracle|--search`: label training starts in simulation, into the store."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from knotlab.app.options import (
    add_db_argument,
    add_flag,
    add_no_progress_argument,
    add_task_argument,
    add_task_set_argument,
    check_input,
    check_output,
    db_url,
    integer,
    library_file,
    load_library,
    load_task_set,
    reads,
    task_of,
    task_set_file,
    warn_of_other_kinds,
)

if TYPE_CHECKING:
    from knotlab.core.selection.labels import LabelledExecution

SEARCH_POLICIES = ("la1x10", "la2x5")  # the lookaheads of Table I


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `label` sub-command."""
    p = subparsers.add_parser(
        "label",
        help="label training starts (oracle expert or a lookahead's episodes, in simulation)",
        description="Label start states with an expert. --oracle plays the expert in simulation: "
        "candidates in registration-cost order, the first that can still reach a knot within "
        "the remaining steps is accepted (bounded search); dead ends are recorded. Results go "
        "to the labelling database; tasks already labelled there are skipped (resumable).",
    )
    expert = p.add_mutually_exclusive_group(required=True)
    expert.add_argument("--oracle", action="store_true", help="use the oracle expert")
    expert.add_argument(
        "--search",
        choices=SEARCH_POLICIES,
        default=None,
        help="label with a lookahead's own episodes (expert iteration): the search, valuing its "
        "leaves with --model, plays each start; an episode that ends in the goal with no failed "
        "step is a labelled execution (labeller search-POLICY), the others are stored without "
        "steps. With --from-policy the search plays from every state that policy reaches "
        "instead (DAgger with the search as the expert)",
    )
    add_task_argument(p)
    p.add_argument(
        "--split",
        choices=("train", "test"),
        default="train",
        help="which shipped task set of the level (default train; a test set is refused: it "
        "must stay unseen)",
    )
    add_flag(p, "--level")
    add_task_set_argument(p, "the starts to label (default: the task's shipped --split set)")
    add_flag(p, "--library", detail="default: the task's shipped library")
    add_db_argument(p)
    add_flag(p, "--tasks", detail="label only these (default: all)")
    # at least 1: a budget of 0 would simulate nothing and record every task as unsolved
    add_flag(p, "--top", default=10, detail="the oracle tries them in registration-cost order (10)")
    p.add_argument("--sim-budget", type=integer(1), default=60, help="simulated actions per task")
    p.add_argument(
        "--from-policy",
        choices=("greedy",),
        default=None,
        help="label where this policy goes (DAgger-style): roll it out with --model (with "
        "--search: --policy-model) from each start and let the expert label every state it "
        "reaches after the start; each label records the policy, model and round that reached "
        "its state",
    )
    add_flag(p, "--model", detail="with --from-policy or --search: the model the policy ranks with")
    reads(
        p.add_argument(
            "--policy-model",
            default=None,
            metavar="PATH",
            help="with --search and --from-policy: the model the rolled-out policy ranks with "
            "(default: --model, the search's)",
        )
    )
    p.add_argument(
        "--tries-out",
        default=None,
        help="with --search: a JSONL file (for `knotlab train --tries`) to append, per labelled "
        "state, the search's first-level candidates that did not advance the task (they must "
        "then lose by a margin floor); resumed when it holds this search's tries",
    )
    p.add_argument(
        "--round",
        type=integer(1, maximum=1000),
        default=1,
        help="with --from-policy: the labelling round recorded with the labels (1)",
    )
    add_flag(p, "--workers")
    add_no_progress_argument(p)
    add_flag(p, "--json", detail="a summary after the text")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Label the tasks and store every execution as soon as it is done."""
    from knotlab.core.errors import InvalidInputError
    from knotlab.core.experiments.labeller import (
        OracleParams,
        labelled_task_ids,
        oracle_label_tasks,
    )
    from knotlab.labeling_db.store import open_store

    args.db = db_url(args)
    if args.model is not None:  # a missing model is named first, whatever else is wrong
        check_input(args.model, flag="--model", kind="model")
    if args.policy_model is not None:
        check_input(args.policy_model, flag="--policy-model", kind="model")
    task_path = task_set_file(args, args.split)
    library_path = library_file(args)
    tasks = load_task_set(task_path, args)
    library = load_library(library_path, args)
    if tasks.split != "train":
        raise InvalidInputError(
            f"{task_path} is a {tasks.split!r} task set: labels train the model, so only "
            "training starts may be labelled (the test set must stay unseen)"
        )
    selected = list(tasks) if args.tasks is None else list(tasks)[: args.tasks]
    if args.search is not None:
        return _run_search(args, library_path, library, selected)
    if args.tries_out is not None:
        raise InvalidInputError("--tries-out is used with --search only")
    if args.policy_model is not None:
        raise InvalidInputError("--policy-model is used with --search and --from-policy only")
    if args.from_policy is not None:
        return _run_policy_states(args, library_path, library, selected)
    if args.model is not None:
        raise InvalidInputError("--model is used with --from-policy or --search only")
    t0 = time.perf_counter()
    solved = sims = dead = 0
    with open_store(args.db, persistent=True) as store:
        store.check_task(task_of(args))  # a store holding another task's labels is refused
        # a task is its rope: a stored id whose rope differs is refused, not skipped as labelled
        stored = store.training_executions(include_unfinished=True)
        done = labelled_task_ids(selected, stored, where=args.db)
        todo = [t for t in selected if t.task_id not in done]
        _warn_if_mixing(args.db, stored, todo)
        store.register_library(library.content_hash(), task=task_of(args))
        store.add_labeller("oracle", "oracle")
        print(
            f"{len(selected) - len(todo)} of {len(selected)} tasks already labelled in {args.db}; "
            f"labelling {len(todo)} with library {library.content_hash()}",
            file=sys.stderr,
        )
        params = OracleParams(args.top, 5, args.sim_budget)
        results = oracle_label_tasks(
            library_path, todo, params=params, workers=args.workers, progress=not args.no_progress
        )
        for result in results:
            store.add_execution(result.execution, if_exists="skip")
            solved += result.solved
            sims += result.simulations
            dead += len(result.execution.dead_ends)
    wall = time.perf_counter() - t0
    summary = {
        "tasks": len(todo),
        "skipped_already_labelled": len(selected) - len(todo),
        "solved": solved,
        "dead_ends": dead,
        "simulations": sims,
        "wall_s": round(wall, 1),
        "db": args.db,
        "library_hash": library.content_hash(),
    }
    print(
        f"labelled {len(todo)} tasks: {solved} solved, {dead} dead ends, {sims} simulations, "
        f"{wall:.0f} s"
    )
    if args.json:
        print(json.dumps(summary))
    return 0


def _run_policy_states(args: argparse.Namespace, library_path, library, selected: list) -> int:
    """One round of policy-state labels into the store (resumable: starts done are skipped)."""
    from pathlib import Path

    from knotlab.core.errors import InvalidInputError
    from knotlab.core.experiments.policy_states import (
        label_policy_state_tasks,
        policy_execution_prefix,
    )
    from knotlab.core.selection.compatibility import check_compatible
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.tasks import get_task
    from knotlab.labeling_db.store import open_store

    if args.model is None:
        raise InvalidInputError("--from-policy needs --model (the model the policy ranks with)")
    model_path = Path(args.model)
    model = QModel.load(model_path)
    check_compatible(library, model, get_task(task_of(args)))
    t0 = time.perf_counter()
    states = dead = reached_knot = 0
    with open_store(args.db, persistent=True) as store:
        store.check_task(task_of(args))
        executions = store.training_executions(include_unfinished=True)
        stored = {e.execution_id for e in executions}
        prefix = {
            t.task_id: policy_execution_prefix(args.from_policy, args.round, t.task_id)
            for t in selected
        }
        todo = [t for t in selected if not any(i.startswith(prefix[t.task_id]) for i in stored)]
        _warn_if_mixing(args.db, executions, todo)
        store.register_library(library.content_hash(), task=task_of(args))
        store.add_labeller("oracle", "oracle")
        print(
            f"round {args.round}: {len(selected) - len(todo)} of {len(selected)} starts already "
            f"done in {args.db}; rolling {args.from_policy} with model {model.content_hash()} "
            f"out on {len(todo)}",
            file=sys.stderr,
        )
        results = label_policy_state_tasks(
            library_path,
            model_path,
            todo,
            round_index=args.round,
            policy=args.from_policy,
            workers=args.workers,
            progress=not args.no_progress,
        )
        for result in results:
            store.add_executions(list(result.executions), if_exists="skip")
            states += sum(len(e.steps) > 0 for e in result.executions)
            dead += sum(len(e.dead_ends) for e in result.executions)
            reached_knot += result.rollout_knot
    wall = time.perf_counter() - t0
    print(
        f"round {args.round}: {args.from_policy} knotted {reached_knot}/{len(todo)} rollouts; "
        f"{states} reached states labelled with a way to the knot, {dead} dead ends; {wall:.0f} s"
    )
    if args.json:
        print(
            json.dumps(
                {
                    "round": args.round,
                    "starts": len(todo),
                    "rollout_knots": reached_knot,
                    "labelled_states": states,
                    "dead_ends": dead,
                    "wall_s": round(wall, 1),
                    "model_hash": model.content_hash(),
                    "db": args.db,
                }
            )
        )
    return 0


def _warn_if_mixing(db: str, executions: Sequence[LabelledExecution], todo: Sequence) -> None:
    """Warn when the labels about to be made join labels another numeric kind of CPU made."""
    from knotlab.core.machine import kind_of_record

    if todo:
        kinds = (kind_of_record(e.metadata) for e in executions)
        warn_of_other_kinds(db, kinds, "labels")


def _append_tries(path, tries) -> None:
    """Append the states' tries to the --tries-out file (if one was given)."""
    if path is None or not tries:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as fh:
        fh.writelines(json.dumps(r.to_dict()) + "\n" for r in tries)


def _run_search(args: argparse.Namespace, library_path, library, selected: list) -> int:
    """Label the starts with the search's own episodes into the store (resumable)."""
    from pathlib import Path

    from knotlab.core.errors import InvalidInputError
    from knotlab.core.experiments.search_labels import label_search_tasks, search_execution_id
    from knotlab.core.selection.compatibility import check_compatible
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.selection.tries import read_tries
    from knotlab.core.tasks import get_task
    from knotlab.labeling_db.store import open_store

    if args.model is None:
        raise InvalidInputError("--search needs --model (the model the search values with)")
    if args.policy_model is not None and args.from_policy is None:
        raise InvalidInputError("--policy-model is used with --search and --from-policy only")
    prefix = search_execution_id(args.search, "")

    def own_tries(path: Path) -> bool:  # this search's tries file, or a one-line refusal
        foreign = sorted({e for e, _ in read_tries(path) if not e.startswith(prefix)})
        if foreign:
            raise InvalidInputError(
                f"{path} holds tries of other executions ({foreign[0]}, ...): not this search's"
            )
        return True

    tries_out = None
    if args.tries_out is not None:
        tries_out = check_output(
            args.tries_out, flag="--tries-out", force=False, kind="tries file", suffixes=(),
            resume=own_tries,
        )  # fmt: skip
    model_path = Path(args.model)
    model = QModel.load(model_path)
    check_compatible(library, model, get_task(task_of(args)))
    if args.from_policy is not None:
        return _run_policy_search(args, library_path, library, selected, model, tries_out)
    t0 = time.perf_counter()
    labelled = states = 0
    with open_store(args.db, persistent=True) as store:
        store.check_task(task_of(args))
        executions = store.training_executions(include_unfinished=True)
        stored = {e.execution_id for e in executions}
        todo = [t for t in selected if search_execution_id(args.search, t.task_id) not in stored]
        _warn_if_mixing(args.db, executions, todo)
        store.register_library(library.content_hash(), task=task_of(args))
        store.add_labeller(f"search-{args.search}", "oracle")
        print(
            f"{len(selected) - len(todo)} of {len(selected)} starts already labelled by "
            f"{args.search} in {args.db}; playing it with model {model.content_hash()} on "
            f"{len(todo)}",
            file=sys.stderr,
        )
        results = label_search_tasks(
            library_path,
            model_path,
            todo,
            policy=args.search,
            workers=args.workers,
            progress=not args.no_progress,
        )
        for result in results:
            _append_tries(tries_out, result.tries)  # before the label: a resume redoes both
            store.add_execution(result.execution, if_exists="skip")
            labelled += bool(result.execution.steps)
            states += len(result.execution.steps)
    wall = time.perf_counter() - t0
    print(
        f"{args.search} reached the goal cleanly from {labelled}/{len(todo)} starts: "
        f"{states} labelled states; {wall:.0f} s"
    )
    if args.json:
        print(
            json.dumps(
                {
                    "search": args.search,
                    "starts": len(todo),
                    "skipped_already_labelled": len(selected) - len(todo),
                    "labelled_executions": labelled,
                    "labelled_states": states,
                    "wall_s": round(wall, 1),
                    "model_hash": model.content_hash(),
                    "db": args.db,
                }
            )
        )
    return 0


def _run_policy_search(
    args: argparse.Namespace, library_path, library, selected: list, model, tries_out
) -> int:
    """The search labels the states the policy reaches from each start (resumable by start)."""
    from pathlib import Path

    from knotlab.core.experiments.search_labels import (
        label_policy_state_search_tasks,
        policy_search_prefix,
    )
    from knotlab.core.selection.compatibility import check_compatible
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.tasks import get_task
    from knotlab.labeling_db.store import open_store

    policy_model_path = Path(args.policy_model or args.model)
    policy_model = QModel.load(policy_model_path)
    check_compatible(library, policy_model, get_task(task_of(args)))

    def prefix(task_id: str) -> str:
        return policy_search_prefix(args.search, args.from_policy, args.round, task_id)

    t0 = time.perf_counter()
    reached = labelled = states = knots = 0
    with open_store(args.db, persistent=True) as store:
        store.check_task(task_of(args))
        executions = store.training_executions(include_unfinished=True)
        stored = {e.execution_id for e in executions}
        todo = [t for t in selected if not any(i.startswith(prefix(t.task_id)) for i in stored)]
        _warn_if_mixing(args.db, executions, todo)
        store.register_library(library.content_hash(), task=task_of(args))
        store.add_labeller(f"search-{args.search}", "oracle")
        print(
            f"round {args.round}: {len(selected) - len(todo)} of {len(selected)} starts already "
            f"done in {args.db}; rolling {args.from_policy} with model "
            f"{policy_model.content_hash()} out on {len(todo)}, {args.search} with model "
            f"{model.content_hash()} labelling the states it reaches",
            file=sys.stderr,
        )
        results = label_policy_state_search_tasks(
            library_path,
            args.model,
            policy_model_path,
            todo,
            search=args.search,
            from_policy=args.from_policy,
            round_index=args.round,
            workers=args.workers,
            progress=not args.no_progress,
        )
        for result in results:
            _append_tries(tries_out, result.tries)  # before the labels: a resume redoes both
            store.add_executions(list(result.executions), if_exists="skip")
            reached += len(result.executions)
            labelled += sum(bool(e.steps) for e in result.executions)
            states += sum(len(e.steps) for e in result.executions)
            knots += result.rollout_knot
    wall = time.perf_counter() - t0
    print(
        f"round {args.round}: {args.from_policy} knotted {knots}/{len(todo)} rollouts; "
        f"{args.search} reached the goal cleanly from {labelled}/{reached} reached states: "
        f"{states} labelled states; {wall:.0f} s"
    )
    if args.json:
        print(
            json.dumps(
                {
                    "search": args.search,
                    "from_policy": args.from_policy,
                    "round": args.round,
                    "starts": len(todo),
                    "skipped_already_labelled": len(selected) - len(todo),
                    "rollout_knots": knots,
                    "reached_states": reached,
                    "labelled_executions": labelled,
                    "labelled_states": states,
                    "wall_s": round(wall, 1),
                    "model_hash": model.content_hash(),
                    "policy_model_hash": policy_model.content_hash(),
                    "db": args.db,
                }
            )
        )
    return 0
