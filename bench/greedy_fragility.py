"""Why greedy loses under a rope tracker: how fragile its choice is on the true rope.

Reads a tracker setting's episodes and its matched world (``bench/robustness.py`` folders, the
same CPU kind) and, for greedy, prints: where its lost episodes first choose another demo than
the matched world; at the decision ``--decision`` (0-based) of the tracker's episodes, how often
greedy's choice from the true rope (the episode's recorded ``nodes_before``) is the demo it chose
from the tracker's estimate; how often a slide of the true chain along itself (``--slide`` m, both
ways) or Gaussian noise on its nodes (``--noise`` m) changes greedy's choice; and whether averaging
Q over five slides or five noise draws of a synthetic estimate (the true chain slid by
U(-2, 2) cm plus 3 mm noise) recovers the true rope's choice more often than the estimate alone.
Where the setting's rows record the estimates themselves (``estimate_nodes``), it also splits
the estimates' effect into their shape error alone and their error along the rope alone, beside
a slid and a noisy true rope, with the Q each choice gives up on the true rope. No episode is
played: every figure is a scan of a recorded rope (seeded draws).

Usage: .venv/bin/python bench/greedy_fragility.py \\
         --setting results/robustness_families_avx2/video \\
         --matched results/robustness_families_avx2/nominal [--states 100] [--seed 0]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robustness import _outcomes  # noqa: E402

from knotlab.core.machine import machine_line  # noqa: E402
from knotlab.core.world.rope import segment_feet, slide_along  # noqa: E402

SYNTHETIC_SLIDE = 0.02  # m: a synthetic estimate's slide along the rope, drawn from U(-x, x)
SYNTHETIC_NOISE = 0.003  # m: and the noise on each of its node coordinates
AVERAGED_SLIDES = (-0.02, -0.01, 0.01, 0.02)  # m: the slides Q is averaged over (with 0)
AVERAGED_NOISE = 0.004  # m: the noise of the four draws Q is averaged over (with none)


def on_curve(points_n3: np.ndarray, curve_k3: np.ndarray) -> np.ndarray:
    """Each point moved to its nearest place on the polyline ``curve_k3`` (3-D), the curve
    running on past its two ends along their own directions.

    A chain put on another chain's curve keeps its own places along the rope and takes the
    other's shape: the true nodes on an estimate's curve are the estimate's shape error alone,
    the estimate's nodes on the true curve its error along the rope alone (past an end they
    continue the curve, as `slide_along` does, rather than pile up on the end).
    """
    points = np.asarray(points_n3, dtype=float)
    n_segments = len(curve_k3) - 1
    low_m, high_m = np.zeros(n_segments), np.ones(n_segments)
    low_m[0], high_m[-1] = -np.inf, np.inf
    _, foot_nm3, dist_nm = segment_feet(points, curve_k3, low_m=low_m, high_m=high_m)
    return foot_nm3[np.arange(len(points)), np.argmin(dist_nm, axis=1)]


def first_other_choice(a: list[str], b: list[str]) -> int | None:
    """The first step at which two episodes chose other demos (None: never, in both's steps)."""
    return next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), None)


class GreedyChooser:
    """Greedy's choice and Q for a rope given by its nodes (its centreline, as the tracker's
    estimate is seen)."""

    def __init__(self) -> None:
        from knotlab.app import defaults
        from knotlab.core.agent import Agent
        from knotlab.core.demos.library import DemoLibrary
        from knotlab.core.selection.qmodel import QModel

        self.model = QModel.load(defaults.MODEL_PATH)
        library = DemoLibrary.load(defaults.LIBRARY_PATH)
        self.keys = library.keys
        self.featurizer = Agent(library).with_model(self.model).featurizer

    def q(self, nodes_k3: np.ndarray) -> np.ndarray:
        """Every demo's Q (-inf where unusable)."""
        from knotlab.core.selection.ranking import demo_scores
        from knotlab.core.world.observation import centreline_points

        cloud = centreline_points(nodes_k3)
        phi, scan = self.featurizer.features(cloud)
        return np.asarray(demo_scores(scan, phi, self.model))

    def choice(self, nodes_k3: np.ndarray) -> int:
        """argmax Q."""
        return int(np.argmax(self.q(nodes_k3)))


def _run_model_hash(folder: Path) -> str | None:
    """The model a bench folder's episodes ranked with (its run.json identity), if it says."""
    import json

    run = folder / "run.json"
    if not run.exists():
        return None
    return json.loads(run.read_text()).get("identity", {}).get("model_hash")


def _averaged_choice(qs: list[np.ndarray]) -> int:
    stacked = np.where(np.isfinite(qs), qs, -1e9)  # a demo unusable in any draw ranks last
    return int(np.argmax(np.mean(stacked, axis=0)))


def main() -> int:
    """Print the tables."""
    from tqdm import tqdm

    from knotlab.core.experiments.episode import decode_nodes

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--setting", type=Path, required=True, help="a tracker setting's folder")
    ap.add_argument("--matched", type=Path, required=True, help="its matched world's folder")
    ap.add_argument("--decision", type=int, default=1, help="0-based decision to probe")
    ap.add_argument("--states", type=int, default=100, help="ropes probed (first task ids)")
    ap.add_argument("--slide", type=float, default=0.015)
    ap.add_argument("--noise", type=float, default=0.004)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(machine_line())
    tracked = _outcomes(args.setting / "outcomes.jsonl").get("greedy", {})
    matched = _outcomes(args.matched / "outcomes.jsonl").get("greedy", {})
    both = sorted(t for t in tracked if t in matched)
    if not both:
        raise SystemExit(f"no greedy task in both {args.setting} and {args.matched}")
    lost = [t for t in both if matched[t]["success"] and not tracked[t]["success"]]
    firsts = Counter(first_other_choice(tracked[t]["chosen"], matched[t]["chosen"]) for t in lost)
    print(f"\ngreedy: {len(both)} tasks in both, {len(lost)} lost with the tracker")
    print("| first other choice than the matched world, at decision | lost episodes |")
    print("|---|---:|")
    for k, n in sorted(firsts.items(), key=lambda kv: (kv[0] is None, kv[0] or 0)):
        print(f"| {'never (same demos)' if k is None else k} | {n} |")

    d = args.decision
    ropes = [
        (t, decode_nodes(tracked[t]["nodes_before"][d]))
        for t in both
        if len(tracked[t]["chosen"]) > d and tracked[t]["nodes_before"][d] is not None
    ][: args.states]
    chooser = GreedyChooser()
    ran_with = _run_model_hash(args.setting)
    if ran_with is not None and ran_with != chooser.model.content_hash():
        raise SystemExit(
            f"{args.setting} ran greedy with model {ran_with}; the shipped model this probes with "
            f"is {chooser.model.content_hash()}"
        )
    rng = np.random.default_rng(args.seed)
    tally: Counter[str] = Counter()
    for t, nodes in tqdm(ropes, desc="probing ropes"):
        true_choice = chooser.choice(nodes)
        agrees = chooser.keys[true_choice] == tracked[t]["chosen"][d]
        tally["agrees"] += agrees
        tally["lost"] += t in lost
        tally["agrees, lost"] += agrees and t in lost
        for s in (-args.slide, args.slide):
            tally["slide flips"] += chooser.choice(slide_along(nodes, s)) != true_choice
        noisy = nodes + rng.normal(0.0, args.noise, size=nodes.shape)
        tally["noise flips"] += chooser.choice(noisy) != true_choice
        estimate = slide_along(nodes, rng.uniform(-SYNTHETIC_SLIDE, SYNTHETIC_SLIDE))
        estimate = estimate + rng.normal(0.0, SYNTHETIC_NOISE, size=nodes.shape)
        q_est = chooser.q(estimate)
        tally["estimate recovers"] += int(np.argmax(q_est)) == true_choice
        slid = [q_est] + [chooser.q(slide_along(estimate, s)) for s in AVERAGED_SLIDES]
        tally["slides recover"] += _averaged_choice(slid) == true_choice
        draws = [q_est] + [
            chooser.q(estimate + rng.normal(0.0, AVERAGED_NOISE, size=nodes.shape))
            for _ in range(4)
        ]
        tally["draws recover"] += _averaged_choice(draws) == true_choice
    n = len(ropes)
    print(
        f"\ngreedy at decision {d} on {n} true ropes of the tracker's episodes (seed {args.seed}):"
    )
    print("| measure | count | share |")
    print("|---|---:|---:|")
    rows = [
        ("the tracker's choice is the true rope's", tally["agrees"], n),
        ("the same, in lost episodes", tally["agrees, lost"], tally["lost"]),
        (
            f"a {100 * args.slide:g} cm slide (each way) changes the choice",
            tally["slide flips"],
            2 * n,
        ),
        (f"{1000 * args.noise:g} mm node noise changes the choice", tally["noise flips"], n),
        ("a synthetic estimate's argmax is the true rope's", tally["estimate recovers"], n),
        ("  Q averaged over 5 slides (-2 to +2 cm)", tally["slides recover"], n),
        ("  Q averaged over 5 noise draws (4 mm)", tally["draws recover"], n),
    ]
    for label, got, total in rows:
        share = f"{100 * got / total:.0f} %" if total else "-"
        print(f"| {label} | {got} / {total} | {share} |")
    estimated = [(t, r, tracked[t].get("estimate_nodes", [])) for t, r in ropes]
    estimated = [(t, r, e[d]) for t, r, e in estimated if len(e) > d and e[d] is not None]
    if estimated:
        _decompose(chooser, [(r, decode_nodes(e)) for _, r, e in estimated], args, d)
    return 0


def _decompose(
    chooser: GreedyChooser,
    pairs: list[tuple[np.ndarray, np.ndarray]],
    args: argparse.Namespace,
    d: int,
) -> None:
    """Greedy's choice from the recorded estimates, from their shape error alone and from their
    error along the rope alone, against its choice from the true rope: how often the same, and
    the Q (on the true rope) given up."""
    from tqdm import tqdm

    from knotlab.core.errors import SolverError

    rng = np.random.default_rng(args.seed + 1)
    variants = {
        "the tracker's estimate": lambda true, est: est,
        "  its shape error alone (true nodes on its curve)": lambda true, est: on_curve(true, est),
        "  its error along the rope alone (its nodes on the true curve)": (
            lambda true, est: on_curve(est, true)
        ),
        f"the true rope slid {100 * args.slide:g} cm (either way)": (
            lambda true, est: slide_along(true, args.slide * rng.choice([-1.0, 1.0]))
        ),
        f"the true rope with {1000 * args.noise:g} mm node noise": (
            lambda true, est: true + rng.normal(0.0, args.noise, size=true.shape)
        ),
    }
    same = dict.fromkeys(variants, 0)
    unscannable = dict.fromkeys(variants, 0)
    regret: dict[str, list[float]] = {name: [] for name in variants}
    for true, est in tqdm(pairs, desc="decomposing estimates"):
        q_true = chooser.q(true)
        best = int(np.argmax(q_true))
        for name, make in variants.items():
            try:
                chosen = chooser.choice(make(true, est))
            except SolverError:  # a chain put on another's curve can fold into a degenerate cloud
                unscannable[name] += 1
                continue
            same[name] += chosen == best
            regret[name].append(float(q_true[best] - q_true[chosen]))
    n = len(pairs)
    print(f"\nwhere the recorded estimates' error comes from, decision {d}, {n} estimates:")
    print(
        "| greedy decides from | its choice is the true rope's | mean Q given up on the true rope |"
    )
    print("|---|---:|---:|")
    for name in variants:
        lost = np.asarray(regret[name])
        finite = lost[np.isfinite(lost)]
        unusable = len(lost) - len(finite)
        tail = f" ({unusable} unusable on the true rope)" if unusable else ""
        mean = f"{finite.mean():.3f}" if len(finite) else "-"
        m = n - unscannable[name]
        share = f"{same[name]} / {m} ({100 * same[name] / m:.0f} %)" if m else "-"
        skipped = f"; {unscannable[name]} could not be scanned" if unscannable[name] else ""
        print(f"| {name} | {share}{skipped} | {mean}{tail} |")


if __name__ == "__main__":
    raise SystemExit(main())
