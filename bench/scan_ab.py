"""A/B the whole library scan at two revisions: alternating processes, fastest scans, outputs.

`bench/kernel_ab.py` swaps only the compiled kernel inside one process. A change around the
kernel (its arguments, chunking, threads, costs) needs the whole `core` package at each
revision, so this script checks REV out into a temporary git worktree and runs timing processes
alternately, one at REV and one on the working tree, `--rounds` times; each process times
`--repeats` scans per worker count after a warm-up and reports its fastest. Alternating spreads
the 10-20 % drift of these VMs over both sides. It also compares the two sides' outputs (costs,
spline coefficients, correspondences of the SCAN scan, a scan of uneven clouds and an EXACT
scan): "identical", or the largest relative difference.

Usage: .venv/bin/python bench/scan_ab.py [--base REV] [--rounds 5] [--repeats 8]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
N_DEMOS, N_POINTS = 148, 150


def _cases():
    """The scans both sides run: (name, params, demos, scene, chunk size)."""
    from knotlab.core.registration.params import EXACT, SCAN
    from knotlab.core.registration.synthetic import corrupt, library, smooth_warp

    rng = np.random.default_rng(0)
    demos = library(rng, N_DEMOS, N_POINTS)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[7]))
    uneven = [cloud[: 60 + 3 * i] for i, cloud in enumerate(library(rng, 30, 150))]
    uneven_scene = corrupt(rng, smooth_warp(rng, 0.03)(uneven[3]))[:97]
    return [
        ("scan", SCAN, demos, scene, 8),
        ("uneven", SCAN, uneven, uneven_scene, 5),
        ("exact", EXACT, demos[:12], scene, 4),
    ]


def child(repeats: int, workers: list[int], chunk: int, outputs: Path | None) -> None:
    """Time the scans in this process (whichever `knotlab` it imports) and print one JSON line."""
    from knotlab.core.registration import LibraryRegistrar
    from knotlab.core.registration.params import SCAN

    cases = _cases()
    _, _, demos, scene, _ = cases[0]
    best = {}
    for w in workers:
        registrar = LibraryRegistrar(SCAN, chunk_size=chunk, n_workers=w)
        registrar.scan(scene, demos, key="ab")  # compile / load, build the demo side
        fastest = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            registrar.scan(scene, demos, key="ab")
            fastest = min(fastest, time.perf_counter() - t0)
        best[str(w)] = fastest
    if outputs is not None:
        arrays = {}
        for name, params, case_demos, case_scene, case_chunk in cases:
            registrar = LibraryRegistrar(params, chunk_size=case_chunk, n_workers=2)
            res = registrar.scan(case_scene, case_demos, keep_correspondence=True)
            for field in ("costs_ac", "e_f_ak3", "e_g_ak3", "corr_anm"):
                arrays[f"{name}.{field}"] = getattr(res, field)
            # without correspondences (the timed scans): a 2-worker scan then starts the first
            # iteration while it factorises the scene, a path the scan above does not take
            res = registrar.scan(case_scene, case_demos)
            for field in ("costs_ac", "e_f_ak3", "e_g_ak3"):
                arrays[f"{name}_no_corr.{field}"] = getattr(res, field)
        np.savez(outputs, **arrays)
    print(json.dumps(best))


def _compare(before: Path, after: Path) -> list[str]:
    """One line per output array: identical, or the largest relative difference."""
    lines = []
    with np.load(before) as a, np.load(after) as b:
        for key in a.files:
            x, y = a[key], b[key]
            if np.array_equal(x, y):
                lines.append(f"{key}: identical")
                continue
            both = np.isfinite(x) & np.isfinite(y)
            rel = np.abs(x[both] - y[both]) / np.maximum(np.abs(x[both]), 1e-300)
            finite_same = np.array_equal(np.isfinite(x), np.isfinite(y))
            lines.append(
                f"{key}: {int(np.sum(x != y))} of {x.size} differ, largest relative "
                f"{rel.max():.1e}" + ("" if finite_same else ", finite/infinite pattern differs")
            )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="HEAD", help="git revision of the 'before' side")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--workers", default="1,2")
    parser.add_argument("--chunk", type=int, default=16)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--outputs", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    workers = [int(w) for w in args.workers.split(",")]
    if args.child:
        child(args.repeats, workers, args.chunk, args.outputs)
        return
    # The parent only: a child may run an older revision's core, without this function.
    from knotlab.core.machine import machine_line

    print(f"machine: {machine_line()}")  # every figure names its CPU kind

    with tempfile.TemporaryDirectory(prefix="scan_ab_") as tmp_name:
        tmp = Path(tmp_name)
        tree = tmp / "base"
        made = subprocess.run(
            ["git", "worktree", "add", "--detach", str(tree), args.base],
            cwd=ROOT,
            capture_output=True,
            text=True,
        )
        if made.returncode != 0:
            sys.exit(f"scan_ab: cannot check out {args.base}: {made.stderr.strip()}")
        try:
            # A `knotlab` package whose `core` is the worktree's, first on the path of that side.
            shim = tmp / "shim" / "knotlab"
            shim.mkdir(parents=True)
            (shim / "__init__.py").write_text("")
            (shim / "core").symlink_to(tree / "core")
            sides = {
                f"before ({args.base})": {**os.environ, "PYTHONPATH": str(tmp / "shim")},
                "after (working tree)": {**os.environ, "PYTHONPATH": ""},
            }
            best: dict[tuple[str, str], float] = {}
            outputs = {label: tmp / f"out{i}.npz" for i, label in enumerate(sides)}
            base_cmd = [sys.executable, __file__, "--child", "--repeats", str(args.repeats)]
            base_cmd += ["--workers", args.workers, "--chunk", str(args.chunk)]
            for r in range(args.rounds):
                for label, env in sides.items():
                    cmd = base_cmd + (["--outputs", str(outputs[label])] if r == 0 else [])
                    run = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tmp)
                    if run.returncode != 0:
                        sys.exit(f"scan_ab: the {label} side failed:\n{run.stderr[-2000:]}")
                    for w, seconds in json.loads(run.stdout.strip().splitlines()[-1]).items():
                        best[label, w] = min(best.get((label, w), np.inf), seconds)
                    print(f"round {r + 1}/{args.rounds} {label} done", file=sys.stderr)
            labels = list(sides)
            print(f"Whole-library scan, {N_DEMOS} demos x {N_POINTS} points, chunk {args.chunk};")
            print(f"fastest of {args.rounds} alternating processes x {args.repeats} scans")
            print("| side | workers | ms per scan | fits/s |")
            print("|---|---|---|---|")
            for (label, w), seconds in best.items():
                print(f"| {label} | {w} | {1e3 * seconds:.1f} | {N_DEMOS / seconds:,.0f} |")
            print("\nOutputs, after vs before:")
            for line in _compare(outputs[labels[0]], outputs[labels[1]]):
                print("  " + line)
        finally:
            subprocess.run(
                ["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, capture_output=True
            )


if __name__ == "__main__":
    main()
