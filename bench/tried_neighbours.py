"""Greedy with a state-conditioned prior from the tried candidates: does "how often did this demo
advance in the labelled states most like this one" help where a per-demo average did not?

`bench/demo_prior.py` adds ``lam * logit(rate_a)`` to greedy's Q with ``rate_a`` one demo's
advance rate over every labelled state it was tried in. Whether a demo transfers depends on this
rope's shape against that demo's, which an average over all states blurs. Here each state is
described by its registration costs to the whole library (``log(cost_a / min cost)``, capped: a
rope's place among the demos, computed by the same scan greedy uses), and a demo's prior in a new
state is its advance rate over the ``k`` tried states nearest in that description where it was
tried, shrunk towards its per-demo rate: ``(advanced + m * rate_a) / (k' + m)``.

Subcommands (outputs resumable or refused when present; nothing in the test sets is read):
  scan     every tried state's cost vector: the labels' stored clouds, scanned on this machine
  offline  leave-one-execution-out: how well each estimator orders the tried candidates of a
           state (pairs of one advancing and one not) and its log-loss, against the per-demo
           rate and greedy's own Q (in-sample for Q: an optimistic reference)
  play     greedy with ``Q + lam * logit(prior)`` on `bench/greedy_validation.py`'s fresh
           validation starts (or, with --test, a level's test tasks once chosen), paired

Usage: .venv/bin/python bench/tried_neighbours.py scan --task figure8
           --labels results/figure8/labels_oracle_main.jsonl,...labels_oracle_hard.jsonl
           --tries results/figure8/tries_main.jsonl,results/figure8/tries_hard.jsonl --out F.npz
       .venv/bin/python bench/tried_neighbours.py offline --task figure8 --scans F.npz
           --tries ... --model M --ks 5,10,20,40
       .venv/bin/python bench/tried_neighbours.py play --task figure8 --level main --starts 200
           --model M --scans F.npz --tries ... --k 20 --lams 0,0.5,1 --out-dir DIR [--test]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from demo_prior import advance_rates  # noqa: E402
from greedy_validation import play_weight_arms  # noqa: E402

from knotlab.core.demos.library import DemoLibrary  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.parallel import PerProcess  # noqa: E402
from knotlab.core.selection.decision import Decision, Policy, StepContext  # noqa: E402
from knotlab.core.selection.qmodel import QModel  # noqa: E402
from knotlab.core.selection.ranking import rank_order  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402

DESCRIPTOR_CAP = 3.0  # log cost ratio: a demo e^3 = 20x the nearest's cost is simply "far"
SHRINK = 2.0  # pseudo-tries of the demo's own rate added to its neighbours' tries


def describe(nn_cost_a: np.ndarray) -> np.ndarray:
    """A state's place among the demos: log(cost_a / min cost), capped; failed demos capped."""
    cost = np.asarray(nn_cost_a, dtype=float)
    finite = np.isfinite(cost) & (cost > 0)
    out = np.full(cost.shape, DESCRIPTOR_CAP)
    if finite.any():
        out[finite] = np.minimum(np.log(cost[finite] / cost[finite].min()), DESCRIPTOR_CAP)
    return out


@dataclass(frozen=True)
class TriedStates:
    """Every tried state's descriptor and, per demo, the states it was tried in and whether it
    advanced there (arrays indexed like ``states``)."""

    keys: tuple[tuple[str, int], ...]  # (execution_id, step_index) per state
    descriptors_sd: np.ndarray  # (states, demos)
    tried_states: dict[int, np.ndarray]  # demo -> indices of the states it was tried in
    tried_advanced: dict[int, np.ndarray]  # demo -> advanced (bool) in those states
    rate_a: np.ndarray  # per-demo smoothed rate (the shrinkage target)

    def prior(
        self, desc_d: np.ndarray, demos: np.ndarray, k: int, exclude: np.ndarray | None = None
    ) -> np.ndarray:
        """Each demo's advance rate over its k nearest tried states, shrunk to its own rate."""
        dist = np.sqrt(((self.descriptors_sd - desc_d) ** 2).sum(axis=1))
        if exclude is not None:
            dist = np.where(exclude, np.inf, dist)
        out = np.empty(len(demos))
        for i, a in enumerate(demos):
            states = self.tried_states.get(int(a))
            prior = self.rate_a[a]
            if states is None or not len(states):
                out[i] = prior
                continue
            d = dist[states]
            order = np.argsort(d, kind="stable")[:k]
            order = order[np.isfinite(d[order])]
            hits = self.tried_advanced[int(a)][order].sum()
            out[i] = (hits + SHRINK * prior) / (len(order) + SHRINK)
        return out


def _advanced(tried: dict, line: dict) -> bool:
    return bool(tried["knot"] or tried["stage"] > line["stage_before"])


def _read_lines(paths: str) -> list[dict]:
    return [json.loads(x) for p in paths.split(",") for x in Path(p).read_text().splitlines() if x]


def load_tried_states(scans_path: Path, tries: str, keys: tuple[str, ...]) -> TriedStates:
    """The scanned states joined with their tries (states without a scan are skipped)."""
    with np.load(scans_path, allow_pickle=False) as f:
        ids = [str(x) for x in f["execution_id"]]
        steps = [int(x) for x in f["step_index"]]
        cost_sa = f["nn_cost_sa"]
    index = {(e, s): i for i, (e, s) in enumerate(zip(ids, steps, strict=True))}
    lines = _read_lines(tries)
    col = {k: a for a, k in enumerate(keys)}
    per_state: dict[int, list[tuple[int, bool]]] = {}
    for line in lines:
        i = index.get((line["execution_id"], line["step_index"]))
        if i is None:
            continue
        for t in line["tried"]:
            adv = _advanced(t, line)
            per_state.setdefault(col[t["demo"]], []).append((i, adv))
    return TriedStates(
        tuple(zip(ids, steps, strict=True)),
        np.stack([describe(c) for c in cost_sa]),
        {a: np.array([i for i, _ in v]) for a, v in per_state.items()},
        {a: np.array([x for _, x in v]) for a, v in per_state.items()},
        advance_rates(lines, list(keys)),
    )


# ----------------------------------------------------------------------------------------- scan


def cmd_scan(args: argparse.Namespace) -> int:
    """Scan every tried state's stored cloud against the library; write the cost vectors."""
    from knotlab.core.selection.features import LibraryFeaturizer
    from knotlab.labeling_db.interchange import read_labels

    print(machine_line())
    if args.out.exists() and not args.force:
        raise SystemExit(f"{args.out} exists (written by an earlier scan); --force to replace it")
    task = get_task(args.task)
    library = DemoLibrary.load(str(task.files.library_path))
    tried = {(ln["execution_id"], ln["step_index"]) for ln in _read_lines(args.tries)}
    clouds = []
    for path in args.labels.split(","):
        for item in read_labels(path):
            ex = item.execution
            for step in ex.steps:
                if (ex.execution_id, step.step_index) in tried:
                    clouds.append((ex.execution_id, step.step_index, step.cloud_n3))
    featurizer = LibraryFeaturizer(library)
    costs = []
    for _, _, cloud in tqdm(clouds, desc="scan tried states", dynamic_ncols=True):
        costs.append(np.asarray(featurizer.scan(cloud).nn_cost_a, dtype=float))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        args.out,
        execution_id=np.array([c[0] for c in clouds]),
        step_index=np.array([c[1] for c in clouds]),
        nn_cost_sa=np.array(costs),
        library_hash=np.array(library.content_hash()),
        vector_width=np.array(machine_info()["vector_width"]),
    )
    print(f"{len(clouds)} tried states scanned -> {args.out}")
    return 0


# -------------------------------------------------------------------------------------- offline


def _pair_accuracy(groups: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Of the (advanced, not advanced) pairs within a state, the share the score orders right
    (ties count a half)."""
    right = total = 0.0
    for score, adv in groups:
        pos, neg = score[adv], score[~adv]
        if not len(pos) or not len(neg):
            continue
        diff = pos[:, None] - neg[None, :]
        right += (diff > 0).sum() + 0.5 * (diff == 0).sum()
        total += diff.size
    return right / max(total, 1.0)


def _log_loss(p: np.ndarray, y: np.ndarray) -> float:
    p = np.clip(p, 1e-4, 1 - 1e-4)
    return float(-np.mean(y * np.log(p) + (1 - y) * np.log(1 - p)))


def cmd_offline(args: argparse.Namespace) -> int:
    """Leave-one-execution-out: each estimator's pair accuracy and log-loss on the tries."""
    task = get_task(args.task)
    library = DemoLibrary.load(str(task.files.library_path))
    keys = tuple(library.keys)
    ts = load_tried_states(args.scans, args.tries, keys)
    col = {k: a for a, k in enumerate(keys)}
    execution = np.array([e for e, _ in ts.keys])
    index = {key: i for i, key in enumerate(ts.keys)}
    ks = [int(x) for x in args.ks.split(",")]
    arms: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"per-demo rate": [], "-cost": []}
    probs: dict[str, list[float]] = {"per-demo rate": []}
    for k in ks:
        arms[f"k={k}"] = []
        probs[f"k={k}"] = []
    ys: list[float] = []
    with np.load(args.scans) as f:
        cost_sa = f["nn_cost_sa"]
    lines = _read_lines(args.tries)
    for line in tqdm(lines, desc="states", dynamic_ncols=True):
        i = index.get((line["execution_id"], line["step_index"]))
        if i is None:
            continue
        demos = np.array([col[t["demo"]] for t in line["tried"]])
        adv = np.array(
            [bool(t["knot"] or t["stage"] > line["stage_before"]) for t in line["tried"]]
        )
        ys.extend(adv.astype(float))
        held = execution == execution[i]
        rate = _rate_without(ts, demos, held)
        arms["per-demo rate"].append((rate, adv))
        probs["per-demo rate"].extend(rate)
        arms["-cost"].append((-cost_sa[i][demos], adv))
        for k in ks:
            p = _prior_without(ts, i, demos, k, held)
            arms[f"k={k}"].append((p, adv))
            probs[f"k={k}"].extend(p)
    y = np.array(ys)
    print(machine_line())
    print(
        f"{args.task}: {len(arms['-cost'])} tried states, {len(y)} tries, "
        f"{int(y.sum())} advanced ({y.mean():.1%})"
    )
    print("| estimator | pair accuracy | log-loss |")
    print("|---|---|---|")
    for name, groups in arms.items():
        ll = _log_loss(np.array(probs[name]), y) if name in probs else float("nan")
        print(f"| {name} | {_pair_accuracy(groups):.3f} | {ll:.3f} |")
    return 0


def _rate_without(ts: TriedStates, demos: np.ndarray, held: np.ndarray) -> np.ndarray:
    """Each demo's smoothed advance rate over the tried states outside ``held``."""
    out = np.empty(len(demos))
    for j, a in enumerate(demos):
        states = ts.tried_states.get(int(a))
        if states is None:
            out[j] = ts.rate_a[a]
            continue
        keep = ~held[states]
        adv = ts.tried_advanced[int(a)][keep]
        out[j] = (adv.sum() + 1) / (len(adv) + 2)
    return out


def _prior_without(
    ts: TriedStates, i: int, demos: np.ndarray, k: int, held: np.ndarray
) -> np.ndarray:
    """The neighbour prior of state i's demos from states outside ``held``, shrunk to the
    rate outside ``held`` as well."""
    shrunk = TriedStates(
        ts.keys, ts.descriptors_sd, ts.tried_states, ts.tried_advanced, ts.rate_a.copy()
    )
    shrunk.rate_a[demos] = _rate_without(ts, demos, held)
    return shrunk.prior(ts.descriptors_sd[i], demos, k, exclude=held)


# ----------------------------------------------------------------------------------------- play


class NeighbourPriorPolicy(Policy):
    """Greedy on Q(s, a) + lam * logit(prior_a(s)), the prior from the k nearest tried states."""

    def __init__(self, inner: Policy, tried: TriedStates, k: int, lam: float) -> None:
        self.inner, self.tried, self.k, self.lam = inner, tried, k, lam
        self.name = f"{inner.name}+nbr{k}x{lam:g}"

    def choose(self, ctx: StepContext) -> Decision:
        """The best demo by the shifted score (unusable demos keep -inf)."""
        decision = self.inner.choose(ctx)
        scores = np.asarray(decision.scores_a, dtype=float).copy()
        usable = np.flatnonzero(np.isfinite(scores))
        prior = self.tried.prior(describe(ctx.scan.nn_cost_a), usable, self.k)
        scores[usable] += self.lam * np.log(prior / (1.0 - prior))
        return Decision(int(rank_order(scores)[0]), scores)


def _build(key: tuple[str, str, str, str, str, int, float]):
    from knotlab.core.agent import Agent
    from knotlab.core.world.sim import RopeWorld

    task_name, library_path, model_path, scans, tries, k, lam = key
    library = DemoLibrary.load(library_path)
    agent = Agent(library, QModel.load(model_path), "greedy", task=task_name)
    if lam:
        tried = load_tried_states(Path(scans), tries, tuple(library.keys))
        agent.policy = NeighbourPriorPolicy(agent.policy, tried, k, lam)
    return RopeWorld(), agent


_AGENTS = PerProcess(_build)


def _episode(job: tuple) -> dict:
    *key, start = job
    world, agent = _AGENTS.get(tuple(key))
    result = agent.run_episode(world, start)
    return {
        "lam": key[-1],
        "task_id": start.task_id,
        "success": bool(result.success),
        "error": result.error,
        "chosen": [s.chosen_key for s in result.steps],
        "stages": [int(s.stage) for s in result.steps],
    }


def cmd_play(args: argparse.Namespace) -> int:
    """Play every lam on the validation starts (or the test tasks), print the paired table."""
    library_path = str(get_task(args.task).files.library_path)
    scans, tries, k, model = str(args.scans), args.tries, args.k, str(args.model)
    return play_weight_arms(
        args,
        inputs=[args.model, args.scans, *map(Path, args.tries.split(","))],
        identity={"tries": tries, "scans": scans, "k": k},
        job_of=lambda a, s: (args.task, library_path, model, scans, tries, k, a, s),
        episode=_episode,
    )


def main() -> int:
    """Parse the subcommand and run it."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("scan")
    s.add_argument("--task", default="overhand")
    s.add_argument("--labels", required=True, help="labels files, comma-separated")
    s.add_argument("--tries", required=True, help="tries files, comma-separated")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--force", action="store_true")
    o = sub.add_parser("offline")
    o.add_argument("--task", default="overhand")
    o.add_argument("--scans", type=Path, required=True)
    o.add_argument("--tries", required=True)
    o.add_argument("--ks", default="5,10,20,40")
    p = sub.add_parser("play")
    p.add_argument("--task", default="overhand")
    p.add_argument("--level", default="main")
    p.add_argument("--starts", type=int, default=200)
    p.add_argument("--model", type=Path, required=True)
    p.add_argument("--scans", type=Path, required=True)
    p.add_argument("--tries", required=True)
    p.add_argument("--k", type=int, default=20)
    p.add_argument("--lams", default="0,0.5,1", help="prior weights; the first is the reference")
    p.add_argument("--test", action="store_true", help="the level's test tasks, not validation")
    p.add_argument("--out-dir", type=Path, required=True)
    p.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    return {"scan": cmd_scan, "offline": cmd_offline, "play": cmd_play}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
