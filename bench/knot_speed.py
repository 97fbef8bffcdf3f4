"""Knot-test speed: `analyse_knot` on a 41-node rope (the simulated rope's size).

Usage: python bench/knot_speed.py [--repeats 30] [--json]
Prints the median and 90th percentile wall time per call with the machine's details; with --json
also the same figures as one JSON object on the last line. Target: median < 5 ms (the bound
tests/world/test_knot.py asserted before wall-clock checks moved out of the tests), so the knot
test, run after every simulated step, never holds the policies up.
"""

from __future__ import annotations

import os

# One BLAS thread: the benchmark measures the knot test, not BLAS contention on shared cores.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from knotlab.core.machine import cpu_model, machine_line  # noqa: E402
from knotlab.core.world.knot import analyse_knot  # noqa: E402
from knotlab.core.world.rope import resample_by_arc_length  # noqa: E402

TARGET_MEDIAN_MS = 5.0


def trefoil_41() -> np.ndarray:
    """A parametric trefoil opened by cutting a small arc, resampled to 41 nodes."""
    t = np.linspace(0.1, 2 * np.pi - 0.1, 200)
    curve = np.stack([np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)])
    return resample_by_arc_length(curve.T, 41)


def measure(repeats: int) -> dict:
    """Time `analyse_knot` ``repeats`` times on the 41-node trefoil; median and p90 in ms."""
    rope = trefoil_41()
    assert analyse_knot(rope).is_overhand, "the benchmark rope must be a knot"
    times_ms = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        analyse_knot(rope)
        times_ms.append(1e3 * (time.perf_counter() - t0))
    return {
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "repeats": repeats,
        "analyse_knot_ms_median": round(statistics.median(times_ms), 3),
        "analyse_knot_ms_p90": round(float(np.percentile(times_ms, 90)), 3),
    }


def main(argv: list[str] | None = None) -> int:
    """Print the timing table (and the JSON line with --json); exit 1 if over the target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    res = measure(args.repeats)
    print(
        f"machine: {res['cpu_model']}, {res['cpu_count']} cores; python {res['python']}, "
        f"numpy {res['numpy']}; {res['repeats']} calls"
    )
    print(f"{'measure':<46}{'median':>10}{'p90':>10}")
    name = f"analyse_knot, 41 nodes (ms, target < {TARGET_MEDIAN_MS:g})"
    print(f"{name:<46}{res['analyse_knot_ms_median']:>10}{res['analyse_knot_ms_p90']:>10}")
    if args.json:
        print(json.dumps(res))
    return 0 if res["analyse_knot_ms_median"] < TARGET_MEDIAN_MS else 1


if __name__ == "__main__":
    sys.exit(main())
