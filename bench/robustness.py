"""The robot's model is not the world: policies on worlds that differ from their model.

Runs each study setting (a world, and the agent's state estimator; the agent always simulates
with the nominal physics its library and model were made in) as a resumable bench run in
``OUT/<setting>/`` (`knotlab bench --world-params ... --estimator ...`, the same files), then
compares every policy with its own matched-world outcomes on the same tasks (default: the
committed whole Table I run on an AVX-512 EPYC, ``results/table1_shared_main``, and the matched
world run on an AVX2 one, ``results/robustness_families_avx2/nominal``): success with
Wilson 95 % intervals, the tasks the mismatch lost and gained, an exact sign test, which single
factor hurts which policy most, and the trackers' errors per step. Writes ``OUT/summary.json`` and
``OUT/robustness.png`` and prints a markdown table. CPUs of two numeric kinds (AVX-512, AVX2) can
choose other demos at near-ties, so ``--matched`` takes one folder per kind (comma-separated) and
each setting pairs with the matched world its own kind ran; a setting paired across kinds is
named in a note.

Usage:
  .venv/bin/python bench/robustness.py run --out-dir results/robustness_main \\
      --settings combined25,combined50,tracker --policies nn,greedy,la2x5 --tasks 200
  .venv/bin/python bench/robustness.py report --out-dir results/robustness_main

Settings: nominal, tracker, video, tracker_ends, video_ends, tracker_marked, video_marked (the
trackers), combinedPCT, FACTOR+PCT / FACTOR-PCT, familiesPCT (every factor at +-PCT), and
WORLD:known (a control: that world with an agent model that is its own physics, so what is left
of a loss is the world being unlike the demos'). Rerun the same command to resume; a setting's
folder refuses other arguments.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from knotlab.core.experiments.robustness import (
    PairedRow,
    paired_row,
    parse_study_settings,
    worst_factors,
)
from knotlab.core.machine import machine_line, recorded_numeric_kind

ROOT = Path(__file__).resolve().parents[1]
ORDER = ("nn", "greedy", "la1x10", "la2x5", "oracle")


def _outcomes(path: Path) -> dict[str, dict[str, dict]]:
    """policy -> task id -> outcome line, from an outcomes.jsonl (empty if absent)."""
    out: dict[str, dict[str, dict]] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                rec = json.loads(line)
                out.setdefault(rec["policy"], {})[rec["task_id"]] = rec
    return out


@dataclass(frozen=True)
class _Matched:
    """One matched world: its folder, outcomes and the CPU kinds that ran them."""

    folder: Path
    outcomes: dict[str, dict[str, dict]]
    kinds: frozenset[str]


@dataclass(frozen=True)
class _Pairing:
    """Which matched world a setting was paired with, and the CPU kinds on either side."""

    matched: _Matched
    kinds: frozenset[str]

    @property
    def across_kinds(self) -> bool:
        """Paired with another kind's episodes (their pairs also differ where the kinds do)."""
        return self.kinds != self.matched.kinds

    def describe(self) -> str:
        """'FOLDER (avx2)', or 'FOLDER (avx2 against avx512: not one CPU kind)'."""
        text = f"{self.matched.folder} ({', '.join(sorted(self.kinds))}"
        if self.across_kinds:
            text += f" against {', '.join(sorted(self.matched.kinds))}: not one CPU kind"
        return text + ")"


def _cpu_kinds(folder: Path, outcomes: dict[str, dict[str, dict]]) -> frozenset[str]:
    """The numeric kinds of CPU that ran a bench folder's episodes (``outcomes``, as `_outcomes`
    read them); lines from before they named it count as the kind its results.json names."""
    results = folder / "results.json"
    machine = json.loads(results.read_text()).get("machine", {}) if results.exists() else {}
    fallback = recorded_numeric_kind(machine)
    recs = (r for by_task in outcomes.values() for r in by_task.values())
    return frozenset(r.get("numeric_kind", fallback) for r in recs)


def _matched_worlds(args: argparse.Namespace) -> list[_Matched]:
    """The --matched folders, read once, with the CPU kinds that ran each."""
    worlds = []
    for folder in (Path(p) for p in str(args.matched).split(",") if p):
        outcomes = _outcomes(folder / "outcomes.jsonl")
        worlds.append(_Matched(folder, outcomes, _cpu_kinds(folder, outcomes)))
    return worlds


def _pair(kinds: frozenset[str], worlds: list[_Matched]) -> _Pairing:
    """The matched world a setting pairs with: the one run on the setting's own CPU kind, else
    the first (two CPU kinds can choose other demos at near-ties)."""
    own = next((w for w in worlds if w.kinds == kinds), worlds[0])
    return _Pairing(own, kinds)


def run(args: argparse.Namespace) -> int:
    """Run (or resume) every setting, one after the other."""
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.demos.tasks import TaskSet
    from knotlab.core.experiments.bench import run_bench
    from knotlab.core.selection.qmodel import QModel
    from knotlab.core.tasks import get_task
    from knotlab.core.world.mismatch import parse_setting

    spec = get_task(args.task)
    library = DemoLibrary.load(spec.files.library_path)
    model = QModel.load(spec.files.model_path)
    task_set = TaskSet.load(spec.files.task_set_path(args.level, "test"))
    policies = [p for p in args.policies.split(",") if p]
    for setting in parse_study_settings(args.settings):
        t0 = time.perf_counter()
        out = Path(args.out_dir) / setting.name
        print(f"== {setting.name}: {', '.join(policies)} on {args.tasks} tasks -> {out}")
        result = run_bench(
            out,
            library=library,
            task_set=task_set,
            policies=policies,
            n_tasks=args.tasks,
            model=model,
            seed=args.seed,
            workers=args.workers,
            progress=not args.no_progress,
            arguments={"study": "robustness", "setting": setting.name, "argv": sys.argv},
            share_simulations=True,
            world=parse_setting(setting.world, seed=args.seed),
            agent_model=parse_setting(setting.agent_model, seed=args.seed),
            estimator=setting.estimator,
        )
        print(
            f"   {result.ran} run, {result.skipped} resumed, {time.perf_counter() - t0:.0f} s: "
            + ", ".join(f"{r['policy']} {r['successes']}/{r['n']}" for r in result.rows)
        )
    return report(args)


def _rows(
    args: argparse.Namespace,
) -> tuple[list[PairedRow], dict[str, dict], list[str], dict[str, _Pairing]]:
    """The paired rows, the trackers' errors, the settings, and which matched world (and CPU
    kinds) each setting was paired with."""
    worlds = _matched_worlds(args)
    rows: list[PairedRow] = []
    tracker: dict[str, dict] = {}
    names = []
    pairing: dict[str, _Pairing] = {}
    baselines = {w.folder.resolve() for w in worlds}
    for folder in sorted(p for p in Path(args.out_dir).iterdir() if p.is_dir()):
        here = _outcomes(folder / "outcomes.jsonl")
        if not here or folder.resolve() in baselines:  # a matched world is not a setting
            continue
        names.append(folder.name)
        pairing[folder.name] = _pair(_cpu_kinds(folder, here), worlds)
        matched = pairing[folder.name].matched.outcomes
        for policy in sorted(here, key=lambda p: ORDER.index(p) if p in ORDER else 99):
            recs = list(here[policy].values())
            rows.append(paired_row(folder.name, policy, recs, matched.get(policy, {})))
            summary = _estimate_errors(recs)
            if summary:
                tracker[f"{folder.name}/{policy}"] = summary
    return rows, tracker, names, pairing


def _estimate_errors(recs: list[dict]) -> dict:
    """The estimates' node and shape errors (mm) and the share of them with the rope's crossing
    code: mean and mean by step (empty: no estimates)."""
    out: dict = {}
    for key, name in (
        ("estimate_error_mm", "mean_mm"),
        ("estimate_shape_mm", "shape_mean_mm"),
        ("estimate_crossings_right", "crossings_right"),  # a share: booleans average to one
    ):
        by_step: dict[int, list[float]] = {}
        for r in recs:
            for i, e in enumerate(r.get(key, [])):
                by_step.setdefault(i, []).append(e)
        if by_step:
            values = [e for v in by_step.values() for e in v]
            out[name] = sum(values) / len(values)
            out[f"by_step_{name}"] = {i + 1: sum(v) / len(v) for i, v in sorted(by_step.items())}
    return out


def _model_error_rows(args: argparse.Namespace) -> list[PairedRow]:
    """Each world run with the nominal model, paired with its ``<world>_known`` control."""
    out = Path(args.out_dir)
    rows = []
    for control in sorted(out.glob("*_known")):
        world = out / control.name.removesuffix("_known")
        here, known = _outcomes(world / "outcomes.jsonl"), _outcomes(control / "outcomes.jsonl")
        for policy in sorted(known, key=lambda p: ORDER.index(p) if p in ORDER else 99):
            if policy in here:
                recs = list(here[policy].values())
                rows.append(paired_row(world.name, policy, recs, known[policy]))
    return rows


def _robust_rows(args: argparse.Namespace) -> list[PairedRow]:
    """Each robust (rla<D>x<W>k..) or adaptive (ala<D>x<W>k..) lookahead in
    ``--robust-dir/<setting>`` against the plain lookahead la<D>x<W> in ``--out-dir/<setting>``,
    on the tasks both ran."""
    import re

    rows: list[PairedRow] = []
    robust_dir = getattr(args, "robust_dir", None)  # `run` reports without it
    if not robust_dir or not Path(robust_dir).is_dir():
        return rows
    for folder in sorted(p for p in Path(robust_dir).iterdir() if p.is_dir()):
        robust = _outcomes(folder / "outcomes.jsonl")
        plain = _outcomes(Path(args.out_dir) / folder.name / "outcomes.jsonl")
        for policy, recs in robust.items():
            match = re.fullmatch(r"[ra]la(\d+)x(\d+)k\d+(min)?(s\d+)?", policy)
            if match and f"la{match[1]}x{match[2]}" in plain:
                base = plain[f"la{match[1]}x{match[2]}"]
                rows.append(paired_row(folder.name, policy, list(recs.values()), base))
    return rows


def _member_use(args: argparse.Namespace) -> dict[str, dict]:
    """Per setting and adaptive lookahead: how many decisions it planned in a member other than
    the agent's own model, overall and by step (from the outcomes' ``planned_in``)."""
    use: dict[str, dict] = {}
    roots = [Path(args.out_dir), Path(getattr(args, "robust_dir", None) or args.out_dir)]
    for root in dict.fromkeys(roots):
        if not root.is_dir():
            continue
        for folder in sorted(p for p in root.iterdir() if p.is_dir()):
            for policy, recs in _outcomes(folder / "outcomes.jsonl").items():
                planned = [r.get("planned_in", []) for r in recs.values()]
                if not any(planned):
                    continue
                by_step: dict[int, list[int]] = {}
                for members in planned:
                    for i, m in enumerate(members):
                        by_step.setdefault(i + 1, []).append(int(m))
                flat = [m for ms in by_step.values() for m in ms]
                use[f"{folder.name}/{policy}"] = {
                    "decisions": len(flat),
                    "other_member": sum(m != 0 for m in flat),
                    "other_by_step": {
                        s: sum(m != 0 for m in v) / len(v) for s, v in by_step.items()
                    },
                }
    return use


def report(args: argparse.Namespace) -> int:
    """Print the comparison table, write summary.json and the plot."""
    rows, tracker, names, pairing = _rows(args)
    if not rows:
        print(f"no results under {args.out_dir}")
        return 1
    print(f"\nAgainst the matched world ({args.matched}), each policy on the tasks both ran:\n")
    for name in names:
        if pairing[name].across_kinds:
            print(f"note: {name} is paired with {pairing[name].describe()}")
    print("| setting | policy | n | success | 95 % Wilson | matched | change | lost | gained | p |")
    print("|---|---|---:|---:|---|---:|---:|---:|---:|---:|")
    for r in rows:
        lo, hi = r.wilson
        err = f" ({r.errored} errored: not a result)" if r.errored else ""
        print(
            f"| {r.setting} | {r.policy} | {r.n} | {100 * r.rate:.1f} %{err} | "
            f"[{100 * lo:.1f}, {100 * hi:.1f}] | {100 * r.matched_rate:.1f} % | "
            f"{r.change_points:+.1f} | {r.lost} | {r.gained} | {r.p_value:.3g} |"
        )
    controls = _model_error_rows(args)
    if controls:
        print(
            "\nModel error alone: each world with the nominal model against the same world with "
            "a model that knows it (the control), on the tasks both ran:\n"
        )
        print(
            "| world | policy | n | nominal model | model that knows it | change | lost | gained "
            "| p |"
        )
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
        for r in controls:
            print(
                f"| {r.setting} | {r.policy} | {r.n} | {100 * r.rate:.1f} % | "
                f"{100 * r.matched_rate:.1f} % | {r.change_points:+.1f} | {r.lost} | {r.gained} | "
                f"{r.p_value:.3g} |"
            )
    robust = _robust_rows(args)
    if robust:
        print("\nThe robust lookahead against the plain one, same world, same tasks:\n")
        print("| world | policy | n | robust | plain | change | lost | gained | p |")
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
        for r in robust:
            print(
                f"| {r.setting} | {r.policy} | {r.n} | {100 * r.rate:.1f} % | "
                f"{100 * r.matched_rate:.1f} % | {r.change_points:+.1f} | {r.lost} | {r.gained} | "
                f"{r.p_value:.3g} |"
            )
    members = _member_use(args)
    for key, u in members.items():
        steps = ", ".join(f"step {k}: {100 * v:.0f} %" for k, v in u["other_by_step"].items())
        print(
            f"\nAdaptive lookahead {key}: {u['other_member']} of {u['decisions']} decisions "
            f"planned in a member other than the agent's own model ({steps})"
        )
    worst = worst_factors(rows)
    if worst:
        print("\nThe single factor that costs each policy most:")
        for policy, (setting, points) in worst.items():
            print(f"- {policy}: {setting} ({points:+.1f} points)")
    for key, t in tracker.items():
        steps = ", ".join(f"step {s}: {v:.1f}" for s, v in t["by_step_mean_mm"].items())
        print(f"\nTracker error, {key}: mean {t['mean_mm']:.1f} mm ({steps})")
        if "shape_mean_mm" in t:
            steps = ", ".join(f"step {s}: {v:.1f}" for s, v in t["by_step_shape_mean_mm"].items())
            print(f"  shape error: mean {t['shape_mean_mm']:.1f} mm ({steps})")
        if "crossings_right" in t:
            steps = ", ".join(
                f"step {s}: {100 * v:.0f} %" for s, v in t["by_step_crossings_right"].items()
            )
            print(f"  the rope's crossings: {100 * t['crossings_right']:.0f} % ({steps})")
    out = Path(args.out_dir)
    summary = {
        "matched": str(args.matched),
        "matched_by_setting": {name: p.describe() for name, p in pairing.items()},
        "settings": names,
        "rows": [
            {
                **r.__dict__,
                "rate": r.rate,
                "matched_rate": r.matched_rate,
                "wilson": r.wilson,
                "change_points": r.change_points,
            }
            for r in rows
        ],
        "model_error": [
            {**r.__dict__, "rate": r.rate, "control_rate": r.matched_rate} for r in controls
        ],
        "robust_vs_plain": [
            {**r.__dict__, "rate": r.rate, "plain_rate": r.matched_rate} for r in robust
        ],
        "worst_factor": {p: {"setting": s, "points": v} for p, (s, v) in worst.items()},
        "tracker_error": tracker,
        "adaptive_members": members,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    if not rows:  # e.g. a folder of robust runs alone: they pair with plain runs, not the matched
        print(f"\nwrote {out / 'summary.json'} (no setting pairs with the matched world: no plot)")
        return 0
    _plot(rows, out / "robustness.png")
    print(f"\nwrote {out / 'summary.json'} and {out / 'robustness.png'}")
    return 0


def _plot(rows: list[PairedRow], path: Path) -> None:
    """Success (with Wilson bars) per setting and policy, the matched rate as a tick."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settings = list(dict.fromkeys(r.setting for r in rows))
    policies = [p for p in ORDER if any(r.policy == p for r in rows)]
    policies += sorted({r.policy for r in rows} - set(ORDER))  # e.g. a robust lookahead
    width = 0.8 / max(len(policies), 1)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(settings) + 2), 4.2), dpi=120)
    for j, policy in enumerate(policies):
        xs, ys, lo, hi, ms = [], [], [], [], []
        for i, setting in enumerate(settings):
            row = next((r for r in rows if r.setting == setting and r.policy == policy), None)
            if row is None or row.n == 0:
                continue
            a, b = row.wilson
            xs.append(i + (j - (len(policies) - 1) / 2) * width)
            ys.append(100 * row.rate)
            lo.append(100 * (row.rate - a))
            hi.append(100 * (b - row.rate))
            ms.append(100 * row.matched_rate)
        ax.bar(xs, ys, width, yerr=[lo, hi], capsize=2, label=policy)
        ax.scatter(xs, ms, marker="_", s=120, color="black", zorder=3)
    counts = {s: max((r.n for r in rows if r.setting == s), default=0) for s in settings}
    ax.set_xticks(range(len(settings)), [f"{s}\n(n={counts[s]})" for s in settings], rotation=0)
    ax.set_ylabel("success within 5 steps (%)")
    ax.set_ylim(0, 105)
    ax.set_title("Worlds unlike the agent's model (black tick: the matched world)", fontsize=10)
    ax.legend(ncol=len(policies), fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Command line: run or report."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    for name in ("run", "report"):
        p = sub.add_parser(name)
        p.add_argument("--out-dir", default=str(ROOT / "results" / "robustness_main"))
        if name == "report":
            p.add_argument(
                "--robust-dir",
                default=str(ROOT / "results" / "robustness_robust_main"),
                help="a study folder of robust lookaheads (rla...) to pair with --out-dir's la...",
            )
        p.add_argument(
            "--matched",
            # The committed matched worlds: AVX-512 (the whole Table I) and AVX2 (200 tasks)
            default=",".join(
                str(ROOT / "results" / name)
                for name in ("table1_shared_main", "robustness_families_avx2/nominal")
            ),
            help="the matched world's bench folders (their outcomes.jsonl), comma-separated: "
            "each setting pairs with the one run on its own CPU kind, else the first",
        )
        if name == "run":
            p.add_argument("--settings", default="combined25,combined50,tracker")
            p.add_argument("--policies", default="nn,greedy,la2x5")
            p.add_argument("--tasks", type=int, default=200)
            p.add_argument("--task", default="overhand")
            p.add_argument("--level", default="main")
            p.add_argument("--seed", type=int, default=0)
            p.add_argument("--workers", type=int, default=None)
            p.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    if args.cmd == "run":
        parse_study_settings(args.settings)  # a bad name fails before any work
        if args.tasks < 1 or not math.isfinite(args.tasks):
            parser.error("--tasks must be >= 1")
        return run(args)
    return report(args)


if __name__ == "__main__":
    raise SystemExit(main())
