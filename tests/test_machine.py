"""Where a figure was measured: the CPU kind, and the AVX2 code an AVX-512 machine can run."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from knotlab.core import machine


def test_the_machine_line_names_the_vector_width_and_an_avx2_build(monkeypatch, tmp_path) -> None:
    width = machine.vector_width()
    assert width in ("avx512", "avx2", "no avx2", "unknown")
    monkeypatch.delenv("NUMBA_CPU_FEATURES", raising=False)
    assert machine.compiled_for() == width
    assert f"({machine.numeric_kind()})" in machine.machine_line()
    for var in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES", "OPENBLAS_CORETYPE", "NUMBA_CACHE_DIR"):
        # setenv first: delenv of an absent variable records nothing to undo, and the values
        # compile_for_avx2 sets would outlive the test
        monkeypatch.setenv(var, "")
        monkeypatch.delenv(var)
    machine.compile_for_avx2(tmp_path)
    assert machine.compiled_for() == "avx2"
    assert "code compiled for avx2" in machine.machine_line() or width == "avx2"
    assert machine.machine_info()["compiled_for"] == "avx2"


def test_the_numeric_kind_names_blas_kernels_only_where_they_are_not_the_widths_usual_ones():
    assert machine.numeric_kind_of("avx512", "SkylakeX") == "avx512"
    assert machine.numeric_kind_of("avx512", "Cooperlake") == "avx512, OpenBLAS Cooperlake"
    assert machine.numeric_kind_of("avx2", "Haswell") == "avx2"
    assert machine.numeric_kind_of("avx2", None) == "avx2"  # no OpenBLAS loaded
    # An AVX-512 CPU whose environment forces OpenBLAS's Haswell kernels (a Zen 5 box here): its
    # last bits are not those of the shipped AVX-512 numbers.
    assert machine.numeric_kind_of("avx512", "Haswell") == "avx512, OpenBLAS Haswell"
    assert machine.numeric_kind_of("avx2", "Sandybridge") == "avx2, OpenBLAS Sandybridge"


def test_the_numeric_kind_follows_the_kernels_openblas_loaded() -> None:
    """In fresh processes (OpenBLAS picks its kernels once, when it loads)."""
    code = "from knotlab.core import machine; print(machine.numeric_kind())"
    env = dict(os.environ)  # as this process loaded it (a box may set OPENBLAS_CORETYPE)
    plain = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.strip()
    assert plain == machine.numeric_kind()
    forced = subprocess.run(
        [sys.executable, "-c", code],
        env={**env, "OPENBLAS_CORETYPE": "Sandybridge"},  # kernels every x86-64 CPU here runs
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert forced == f"{machine.compiled_for()}, OpenBLAS Sandybridge"


@pytest.mark.slow
def test_numba_compiled_for_avx2_uses_no_avx512_registers(tmp_path) -> None:
    """In a fresh process (numba reads its target once): a vector loop's assembly."""
    code = f"""
from knotlab.core.machine import compile_for_avx2
compile_for_avx2({str(tmp_path)!r})
import numpy as np
from numba import njit

@njit
def axpy(a, x, y):
    for i in range(x.size):
        y[i] += a * x[i]

x = np.ones(64, np.float32)
axpy(np.float32(2), x, x.copy())
asm = next(iter(axpy.inspect_asm().values()))
print("zmm" in asm, "ymm" in asm)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"], out.stdout + out.stderr


def test_a_machine_record_names_its_numeric_kind_even_from_before_the_field():
    from knotlab.core.machine import recorded_numeric_kind

    haswell = ["openblas 0.3.30 Haswell (libscipy_openblas.so)"]
    skylake = ["openblas 0.3.30 SkylakeX (libscipy_openblas.so)"]
    assert recorded_numeric_kind({"numeric_kind": "avx2", "blas": skylake}) == "avx2"
    assert recorded_numeric_kind({"compiled_for": "avx2", "vector_width": "avx512"}) == "avx2"
    assert recorded_numeric_kind({"vector_width": "avx512", "blas": haswell}) == (
        "avx512, OpenBLAS Haswell"
    )
    assert recorded_numeric_kind({"blas": skylake * 2}) == "avx512"  # only the kernels recorded
    assert recorded_numeric_kind({"blas": haswell}) == "avx2"
    assert recorded_numeric_kind({"blas": haswell + skylake}) == "unrecorded"
    assert recorded_numeric_kind({}) == "unrecorded"


def test_records_of_another_kind_are_counted_and_named_and_unrecorded_ones_are_not(monkeypatch):
    records = [{"numeric_kind": "avx512"}, {"numeric_kind": "avx2"}, {}, {"numeric_kind": "avx2"}]
    assert machine.numeric_kinds(records) == {"avx2": 2, "avx512": 1, "unrecorded": 1}
    monkeypatch.setattr(machine, "numeric_kind", lambda: "avx2")
    kinds = [machine.kind_of_record(r) for r in records]
    assert machine.other_kinds_warning("labels.db", kinds, "labels") == (
        "labels.db holds labels made on avx512; this machine is avx2, whose last bits can "
        "choose other demos at near-ties"
    )
    assert machine.other_kinds_warning("x", ["avx2", "unrecorded"], "tries") is None
    assert machine.other_kinds_warning("x", [], "tries") is None


def test_the_blas_kernel_is_numpys_whatever_other_openblas_loaded_first(monkeypatch):
    import threadpoolctl

    solver = "/venv/site-packages/scs.libs/libopenblas-r0-11edc3fa.3.15.so"  # SCS bundles one
    infos = [
        {"internal_api": "openblas", "architecture": "Zen", "filepath": solver},
        {
            "internal_api": "openblas",
            "architecture": "Haswell",
            "filepath": "/venv/site-packages/scipy.libs/libscipy_openblas-6cdc3b4a.so",
        },
        {
            "internal_api": "openblas",
            "architecture": "SkylakeX",
            "filepath": "/venv/site-packages/numpy.libs/libscipy_openblas64_-32a4b2a6.so",
        },
    ]
    monkeypatch.setattr(threadpoolctl, "threadpool_info", lambda: list(infos))
    kernel = machine.openblas_kernel.__wrapped__  # uncached
    assert kernel() == "SkylakeX"  # NumPy's, before SciPy's and the solver's
    del infos[2]
    assert kernel() == "Haswell"  # then SciPy's build
    del infos[1]
    assert kernel() == "Zen"  # any OpenBLAS at all, last
    record = {"vector_width": "avx2", "blas": [f"openblas 0.3.15 Zen ({solver.split('/')[-1]})"]}
    record["blas"].append("openblas 0.3.30 Haswell (libscipy_openblas-6cdc3b4a.so)")
    assert machine.recorded_numeric_kind(record) == "avx2"
    assert machine.recorded_numeric_kind({"blas": record["blas"]}) == "avx2"


def test_the_numeric_kind_does_not_depend_on_what_a_process_imported_first() -> None:
    """A solver's bundled OpenBLAS loaded before NumPy's (in fresh processes)."""
    pytest.importorskip("scs")
    code = "from knotlab.core import machine; print(machine.numeric_kind())"
    runs = [
        subprocess.run(
            [sys.executable, "-c", prefix + code], capture_output=True, text=True, check=True
        ).stdout.strip()
        for prefix in ("", "import scs\n")
    ]
    assert runs[0] == runs[1] == machine.numeric_kind()
