"""A/B the scan kernel: two versions of kernel.py, interleaved timings, bit-identity check.

The 2-core VMs this project runs on vary by 10-20 % from one run to the next on identical work,
so a before/after pair of `bench/registration.py` runs cannot show a 10 % kernel change. This
script loads both versions of `core/registration/kernel.py` into one process (numba, no cache),
alternates them scan by scan and keeps each one's fastest scan, so drift hits both alike. It
also prints each version's fingerprint (costs, spline coefficients and correspondences of SCAN
scans at two sizes and an EXACT scan): a speed-up that changes a bit shows up there.

Usage: .venv/bin/python bench/kernel_ab.py [--base REV] [--repeats 25]
(compares the kernel at git REV, default HEAD, with the working tree's). Both kernels are called
by the working tree's `rpm.py`, so REV's kernel must take the same arguments: since 8541b48 the
inputs are padded (`padded_length`), and older kernels are compared with `bench/scan_ab.py`.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import importlib.util  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from types import ModuleType  # noqa: E402

import numpy as np  # noqa: E402

import knotlab.core.registration.rpm as rpm  # noqa: E402
from knotlab.core.registration import LibraryRegistrar  # noqa: E402
from knotlab.core.registration.params import EXACT, SCAN  # noqa: E402
from knotlab.core.registration.synthetic import corrupt, library, smooth_warp  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
KERNEL = "core/registration/kernel.py"


def _load(source: str, name: str, folder: Path) -> ModuleType:
    """Import kernel source as module `name`, compiled fresh (the on-disk cache is per file)."""
    path = folder / f"{name}.py"
    path.write_text(source.replace("cache=True", "cache=False"))
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _fingerprint(cases) -> str:
    """sha1 of every output array of the cases' scans, first 16 hex digits."""
    digest = hashlib.sha1()
    for params, demos, scene in cases:
        result = LibraryRegistrar(params, chunk_size=8, n_workers=2).scan(
            scene, demos, keep_correspondence=True
        )
        for arr in (result.costs_ac, result.e_f_ak3, result.e_g_ak3, result.corr_anm):
            digest.update(np.ascontiguousarray(arr).tobytes())
    return digest.hexdigest()[:16]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="HEAD", help="git revision of the 'before' kernel")
    parser.add_argument("--repeats", type=int, default=25)
    args = parser.parse_args()
    from knotlab.core.machine import machine_line

    print(f"machine: {machine_line()}")  # every figure names its CPU kind
    before = subprocess.run(
        ["git", "show", f"{args.base}:{KERNEL}"], cwd=ROOT, capture_output=True, text=True
    )
    if before.returncode != 0:
        sys.exit(f"kernel_ab: cannot read {KERNEL} at {args.base}: {before.stderr.strip()}")
    after = (ROOT / KERNEL).read_text()

    rng = np.random.default_rng(0)
    demos = library(rng, 148, 150)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[7]))
    small = library(rng, 40, 120)
    small_scene = corrupt(rng, smooth_warp(rng, 0.03)(small[3]))[:97]
    cases = [(SCAN, demos, scene), (SCAN, small, small_scene), (EXACT, demos[:12], scene)]

    with tempfile.TemporaryDirectory() as tmp:
        variants = {
            f"before ({args.base})": _load(before.stdout, "kernel_before", Path(tmp)),
            "after (working tree)": _load(after, "kernel_after", Path(tmp)),
        }
        registrars = {w: LibraryRegistrar(SCAN, chunk_size=16, n_workers=w) for w in (1, 2)}
        for label, module in variants.items():
            rpm.rpm_kernel = module.rpm_kernel  # run_chunks -> rpm_batch looks it up per call
            print(f"{label}: fingerprint {_fingerprint(cases)}", flush=True)
        best = {(label, w): np.inf for label in variants for w in registrars}
        for _ in range(args.repeats):
            for label, module in variants.items():
                rpm.rpm_kernel = module.rpm_kernel
                for w, registrar in registrars.items():
                    t0 = time.perf_counter()
                    registrar.scan(scene, demos, key="ab")
                    best[label, w] = min(best[label, w], time.perf_counter() - t0)
    print(f"\nWhole-library scan, 148 demos x 150 points, fastest of {args.repeats} (interleaved)")
    print("| kernel | workers | ms per scan | fits/s |")
    print("|---|---|---|---|")
    for (label, w), seconds in best.items():
        print(f"| {label} | {w} | {1e3 * seconds:.1f} | {148 / seconds:,.0f} |")


if __name__ == "__main__":
    main()
