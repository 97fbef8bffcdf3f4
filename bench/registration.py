"""Registration benchmark: single-pair exact, whole-library scan (fits/s), per-demo loop, ranking
agreement scan vs exact (Spearman), and pycpd's deformable registration on the same pairs.

Usage: .venv/bin/python bench/registration.py [--json] [--workers 2] [--repeats 7] [--quick]
       [--target avx2]
BLAS runs single-threaded (set below, before NumPy loads); the scan's parallelism is its own
worker threads over chunks of demos.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"
if "--target" in sys.argv and sys.argv[sys.argv.index("--target") + 1 :][:1] == ["avx2"]:
    # Before numba and OpenBLAS load: they read these once.
    from knotlab.core.machine import compile_for_avx2

    compile_for_avx2(Path(__file__).resolve().parents[1] / "runs" / "numba-avx2")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.core.machine import cpu_model, machine_line  # noqa: E402
from knotlab.core.registration import (  # noqa: E402
    EXACT,
    SCAN,
    LibraryRegistrar,
    register,
)
from knotlab.core.registration.kernel import PHASES  # noqa: E402
from knotlab.core.registration.rpm import rpm_batch  # noqa: E402
from knotlab.core.registration.sides import scene_side  # noqa: E402
from knotlab.core.registration.synthetic import corrupt, library, rope_cloud, smooth_warp  # noqa: E402

N_DEMOS = 148


def _blas_info() -> str:
    try:
        from threadpoolctl import threadpool_info

        return "; ".join(
            f"{i.get('internal_api')} {i.get('version')} threads={i.get('num_threads')}"
            for i in threadpool_info()
        )
    except ImportError:
        return "threadpoolctl not installed"


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _scan_bench(n_points: int, workers: int, repeats: int, rng: np.random.Generator) -> dict:
    demos = library(rng, N_DEMOS, n_points)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[7]))
    registrar = LibraryRegistrar(SCAN, chunk_size=16, n_workers=workers)
    t0 = time.perf_counter()
    registrar.prepare(demos, key=f"bench-{n_points}")
    prepare_s = time.perf_counter() - t0
    registrar.scan(scene, demos, key=f"bench-{n_points}")  # warm-up
    scan_s, result = _median_time(
        lambda: registrar.scan(scene, demos, key=f"bench-{n_points}"), repeats
    )
    single = LibraryRegistrar(SCAN, chunk_size=16, n_workers=1)
    single.prepare(demos, key="p")
    single_s, _ = _median_time(lambda: single.scan(scene, demos, key="p"), max(3, repeats // 2))
    phases = _phase_split(single.prepare(demos, key="p"), scene_side(scene, SCAN), repeats)
    loop = LibraryRegistrar(SCAN, chunk_size=1, n_workers=1)
    loop.prepare(demos, key="l")
    loop_s, _ = _median_time(lambda: loop.scan(scene, demos, key="l"), 3)
    t0 = time.perf_counter()
    for demo in demos:
        register(demo, scene, SCAN)
    cold_loop_s = time.perf_counter() - t0
    return {
        "n_points": n_points,
        "prepare_s": prepare_s,
        "scan_s": scan_s,
        "fits_per_s": N_DEMOS / scan_s,
        "scan_1worker_s": single_s,
        "fits_per_s_1worker": N_DEMOS / single_s,
        "loop_precomputed_s": loop_s,
        "loop_cold_s": cold_loop_s,
        "phases_ms_1worker": phases,
        "all_ok": bool(result.ok_a.all()),
    }


def _scan_seconds(n_points: int, n_demos: int, workers: int, repeats: int, rng) -> float:
    """Median wall seconds of one whole-library scan (demo side prepared, kernels warm)."""
    demos = library(rng, n_demos, n_points)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[0]))
    # SCAN caps clouds at 150 points (a larger one is subsampled): lift the cap for 300.
    params = dataclasses.replace(SCAN, max_points=max(SCAN.max_points, n_points))
    registrar = LibraryRegistrar(params, chunk_size=16, n_workers=workers)
    key = f"scaling-{n_points}-{n_demos}"
    registrar.scan(scene, demos, key=key)  # prepare + warm-up
    seconds, _ = _median_time(lambda: registrar.scan(scene, demos, key=key), repeats)
    return seconds


def _scaling(workers: int, repeats: int, rng) -> dict:
    """Scan cost against points per cloud (148 demos) and against library size (150 points),
    with the log-log slopes (cost ~ points^a, ~ demos^b)."""
    points = (50, 81, 100, 150, 300)
    sizes = (37, 74, 148, 296)
    by_points = {n: _scan_seconds(n, N_DEMOS, workers, repeats, rng) for n in points}
    by_size = {a: _scan_seconds(150, a, workers, repeats, rng) for a in sizes}
    slope_p = float(np.polyfit(np.log(points), np.log(list(by_points.values())), 1)[0])
    slope_a = float(np.polyfit(np.log(sizes), np.log(list(by_size.values())), 1)[0])
    return {
        "workers": workers,
        "points": {str(n): {"scan_s": t, "fits_per_s": N_DEMOS / t} for n, t in by_points.items()},
        "library_sizes_at_150": {
            str(a): {"scan_s": t, "fits_per_s": a / t} for a, t in by_size.items()
        },
        "slope_points": slope_p,
        "slope_library": slope_a,
    }


def _plot_scaling(scaling: dict, path: Path) -> Path:
    """Log-log plot: scan seconds against points per cloud and against library size."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 3.6), dpi=110)
    FigureCanvasAgg(fig)
    panels = (
        ("points", f"points per cloud ({N_DEMOS} demos)", scaling["slope_points"]),
        ("library_sizes_at_150", "demos in the library (150 points)", scaling["slope_library"]),
    )
    for i, (key, label, slope) in enumerate(panels):
        ax = fig.add_subplot(1, 2, i + 1)
        xs = [int(k) for k in scaling[key]]
        ys = [1000 * v["scan_s"] for v in scaling[key].values()]
        ax.loglog(xs, ys, marker="o", lw=2, color="#4C72B0")
        for x, y, v in zip(xs, ys, scaling[key].values(), strict=True):
            ax.annotate(f"{v['fits_per_s']:,.0f}/s", (x, y), textcoords="offset points",
                        xytext=(4, -12), fontsize=7)  # fmt: skip
        ax.set_xlabel(label)
        ax.set_ylabel("ms per whole-library scan")
        ax.set_title(f"cost ~ x^{slope:.2f}", fontsize=10)
        ax.grid(alpha=0.3, which="both")
    fig.suptitle(f"Library scan, SCAN preset, {scaling['workers']} worker threads", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def _phase_split(demo, scene, repeats: int) -> dict[str, float]:
    """ms per whole-library scan, 1 thread, per phase: the fused kernel is run stopping after
    each phase in turn (`stop_after`), the stopping points interleaved round by round so that
    the VM's drifts hit them alike, and the fastest runs of successive points differenced (the
    work is deterministic: the fastest run is the least disturbed one). A phase whose difference
    comes out negative is within the noise; it is reported as measured."""
    idx = np.arange(len(demo))
    kernel: dict[str, list[float]] = {name: [] for name in PHASES}
    setup: list[float] = []
    for _ in range(max(3, repeats)):
        for stop, name in enumerate(PHASES):
            t: dict[str, float] = {}
            rpm_batch(demo, idx, scene, SCAN, False, t, stop)
            kernel[name].append(t["rpm kernel"])
            setup.append(t["setup"])
    out: dict[str, float] = {}
    prev = 0.0
    for name in PHASES:
        fastest = 1000 * min(kernel[name])
        out[name] = fastest - prev
        prev = fastest
    out["setup"] = 1000 * min(setup)
    return out


def _start_up() -> dict:
    """Seconds for a fresh interpreter to import and run its first scan-preset registration,
    with numba's on-disk cache as it is (warm) and with an empty cache dir (cold: compiles)."""
    import subprocess
    import tempfile

    code = (
        "import time; t0 = time.perf_counter();"
        "import numpy as np; from knotlab.core.registration import register, SCAN;"
        "from knotlab.core.registration.synthetic import rope_cloud;"
        "c = rope_cloud(np.random.default_rng(0), 100);"
        "register(c, c + 0.01, SCAN); print(time.perf_counter() - t0)"
    )
    root = str(Path(__file__).resolve().parents[1])
    out = {}
    for label in ("warm", "cold"):
        env = dict(os.environ)
        with tempfile.TemporaryDirectory() as tmp:
            if label == "cold":
                env["NUMBA_CACHE_DIR"] = tmp
            res = subprocess.run(
                [sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True
            )
        ok = res.returncode == 0
        out[f"{label}_s"] = float(res.stdout.strip().splitlines()[-1]) if ok else None
    return out


def _pairs(rng: np.random.Generator, n_pairs: int, n_points: int):
    out = []
    for _ in range(n_pairs):
        demo = rope_cloud(rng, n_points)
        warp = smooth_warp(rng, 0.03, angle_rad=0.05)
        out.append((demo, warp, corrupt(rng, warp(demo))))
    return out


def _pair_bench(rng: np.random.Generator, n_pairs: int) -> dict:
    from pycpd import DeformableRegistration

    pairs = _pairs(rng, n_pairs, 150)
    res: dict[str, list[float]] = {k: [] for k in ("exact_s", "exact_err", "scan_err")}
    res.update({"pycpd_s": [], "pycpd_err": []})
    for demo, warp, scene in pairs:
        truth = warp(demo)
        t0 = time.perf_counter()
        reg = register(demo, scene, EXACT)
        res["exact_s"].append(time.perf_counter() - t0)
        res["exact_err"].append(float(np.linalg.norm(reg.f(demo) - truth, axis=1).mean()))
        scan_reg = register(demo, scene, SCAN)
        res["scan_err"].append(float(np.linalg.norm(scan_reg.f(demo) - truth, axis=1).mean()))
        t0 = time.perf_counter()
        cpd = DeformableRegistration(X=scene, Y=demo, alpha=2.0, beta=0.1, w=0.05)
        moved, _ = cpd.register()
        res["pycpd_s"].append(time.perf_counter() - t0)
        res["pycpd_err"].append(float(np.linalg.norm(moved - truth, axis=1).mean()))
    return {k: float(np.median(v)) for k, v in res.items()}


def _spearman(rng: np.random.Generator, n_points: int, workers: int) -> dict:
    from scipy.stats import spearmanr

    demos = library(rng, N_DEMOS, n_points)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[11]))
    scan = LibraryRegistrar(SCAN, chunk_size=16, n_workers=workers).scan(scene, demos)
    t0 = time.perf_counter()
    exact = LibraryRegistrar(EXACT, chunk_size=8, n_workers=workers).scan(scene, demos)
    exact_s = time.perf_counter() - t0
    rho = spearmanr(scan.nn_cost_a, exact.nn_cost_a).statistic
    top = int(np.argmin(exact.nn_cost_a))
    return {
        "n_points": n_points,
        "spearman_nn_cost": float(rho),
        "exact_library_s": exact_s,
        "exact_best_rank_in_scan": int(np.argsort(np.argsort(scan.nn_cost_a))[top]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true", help="print one JSON object last")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--pairs", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="skip the exact-library Spearman")
    parser.add_argument(
        "--target",
        choices=("host", "avx2"),
        default="host",
        help="avx2: compile the kernel (and pick OpenBLAS kernels) for an AVX2 CPU, to measure "
        "AVX2 code on an AVX-512 machine (its own numba cache in runs/numba-avx2)",
    )
    parser.add_argument(
        "--cold-start", action="store_true", help="also time numba compilation from an empty cache"
    )
    parser.add_argument(
        "--scaling",
        action="store_true",
        help="also time scans at 50-300 points and 37-296 demos, with a log-log plot",
    )
    parser.add_argument(
        "--plot",
        default=str(Path(__file__).resolve().parents[1] / "runs" / "registration_scaling.png"),
        help="where --scaling writes its plot",
    )
    args = parser.parse_args()
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    warnings.simplefilter("ignore", RuntimeWarning)
    rng = np.random.default_rng(2024)
    machine = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "blas": _blas_info(),
        "scan_workers": args.workers,
        "load_avg_1min": os.getloadavg()[0],
    }
    scans = [_scan_bench(n, args.workers, args.repeats, rng) for n in (100, 150)]
    pairs = _pair_bench(rng, args.pairs)
    spear = None if args.quick else _spearman(rng, 100, args.workers)
    start = _start_up() if args.cold_start else None
    scaling = _scaling(args.workers, args.repeats, rng) if args.scaling else None

    print("knotlab registration benchmark")
    for key, val in machine.items():
        print(f"  {key:14s} {val}")
    print(f"\nWhole-library scan, {N_DEMOS} demos, SCAN preset (medians of {args.repeats})")
    print(
        f"{'points':>6} {'prepare s':>9} {'scan s':>8} {'fits/s':>8} {'1-worker':>9} "
        f"{'loop s':>8} {'cold loop s':>11}"
    )
    for s in scans:
        print(
            f"{s['n_points']:>6} {s['prepare_s']:>9.3f} {s['scan_s']:>8.4f} "
            f"{s['fits_per_s']:>8.0f} {s['fits_per_s_1worker']:>9.0f} "
            f"{s['loop_precomputed_s']:>8.3f} {s['loop_cold_s']:>11.3f}"
        )
    for s in scans:
        phases = ", ".join(
            f"{k} {v:.1f}{' (within noise)' if v < 0 else ''}"
            for k, v in s["phases_ms_1worker"].items()
        )
        print(f"  phases at {s['n_points']} points, 1 worker, ms per scan: {phases}")
    print(f"\nSingle pairs at 150 points (median of {args.pairs}; 2 mm noise, 5 % outliers)")
    print(f"  exact: {pairs['exact_s']:.3f} s, mean error {1000 * pairs['exact_err']:.1f} mm")
    print(f"  scan preset mean error {1000 * pairs['scan_err']:.1f} mm")
    print(
        f"  pycpd deformable: {pairs['pycpd_s']:.3f} s, "
        f"mean error {1000 * pairs['pycpd_err']:.1f} mm"
    )
    if spear:
        print(
            f"\nRanking agreement at {spear['n_points']} points: Spearman(scan, exact) = "
            f"{spear['spearman_nn_cost']:.3f}; exact over the library took "
            f"{spear['exact_library_s']:.1f} s; exact's best demo is scan rank "
            f"{spear['exact_best_rank_in_scan']}"
        )
    if start:
        print(
            f"\nStart-up (fresh interpreter: import + first SCAN registration): numba cache warm "
            f"{start['warm_s']:.2f} s, cold (compiling) {start['cold_s']:.1f} s"
        )
    if scaling:
        print(f"\nScaling ({args.workers} workers; medians of {args.repeats})")
        print("| points | ms per scan | fits/s |\n|---|---|---|")
        for n, v in scaling["points"].items():
            print(f"| {n} | {1000 * v['scan_s']:.1f} | {v['fits_per_s']:,.0f} |")
        print("\n| demos (150 points) | ms per scan | fits/s |\n|---|---|---|")
        for a, v in scaling["library_sizes_at_150"].items():
            print(f"| {a} | {1000 * v['scan_s']:.1f} | {v['fits_per_s']:,.0f} |")
        print(
            f"cost ~ points^{scaling['slope_points']:.2f}, ~ demos^{scaling['slope_library']:.2f}; "
            f"plot: {_plot_scaling(scaling, Path(args.plot))}"
        )
    machine["load_avg_1min_end"] = os.getloadavg()[0]
    if args.json:
        out = {"machine": machine, "scan": scans, "pairs": pairs, "spearman": spear}
        print(json.dumps({**out, "start_up": start, "scaling": scaling}))


if __name__ == "__main__":
    main()
