"""Where a measurement was taken: CPU model and vector width, usable cores, load, BLAS kernels,
Python, platform."""

from __future__ import annotations

import functools
import os
import platform
from collections import Counter
from collections.abc import Iterable, Mapping
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux), or the platform's best guess."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def vector_width() -> str:
    """The widest x86 vector extension the CPU has: "avx512", "avx2", else "no avx2".

    Speed figures differ by several times between AVX-512 and AVX2 machines (the registration
    kernel's vector loops), so every figure names it.
    """
    try:
        flags = next(
            (
                line
                for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("flags")
            ),
            "",
        ).split()
    except OSError:
        return "unknown"
    if "avx512f" in flags:
        return "avx512"
    return "avx2" if "avx2" in flags else "no avx2"


# LLVM target features of an AVX2 + FMA x86 CPU (Haswell and later, Zen) with every AVX-512
# extension off. NUMBA_CPU_NAME alone does not do it: numba still takes the host's features, and
# the code keeps its zmm registers (checked in the assembly).
AVX2_FEATURES = (
    "+64bit,+avx,+avx2,+bmi,+bmi2,+cmov,+cx16,+f16c,+fma,+lzcnt,+mmx,+movbe,+pclmul,+popcnt,"
    "+sse,+sse2,+sse3,+sse4.1,+sse4.2,+ssse3,+xsave,-avx512f,-avx512bw,-avx512vl,-avx512dq,"
    "-avx512cd,-avx512vnni,-avx512bf16,-avx512vbmi,-avx512vbmi2,-avx512ifma"
)


def compile_for_avx2(cache_dir: str | Path) -> None:
    """Make numba (imported after this call) compile for an AVX2 CPU and OpenBLAS use its
    Haswell kernels, with a numba cache of their own in ``cache_dir``: on an AVX-512 machine,
    the code an AVX2 machine runs, on this hardware (a benchmark's ``--target avx2``)."""
    os.environ["NUMBA_CPU_NAME"] = "haswell"
    os.environ["NUMBA_CPU_FEATURES"] = AVX2_FEATURES
    os.environ["OPENBLAS_CORETYPE"] = "Haswell"
    os.environ["NUMBA_CACHE_DIR"] = str(cache_dir)


def compiled_for() -> str:
    """The vector width numba compiles for: the CPU's own, or "avx2" under `compile_for_avx2`."""
    if "-avx512f" in os.environ.get("NUMBA_CPU_FEATURES", ""):
        return "avx2"
    return vector_width()


# The OpenBLAS kernels each vector width's machines have picked here (and the shipped numbers
# were made with). Any other kernel may differ in the last bits, so it is named: an environment
# that sets OPENBLAS_CORETYPE=Haswell on an AVX-512 CPU makes other numbers than SkylakeX's.
USUAL_BLAS_KERNELS = {
    "avx512": frozenset({"SkylakeX"}),
    "avx2": frozenset({"Haswell"}),
}


def _blas_rank(filepath: str) -> int:
    """How surely a loaded OpenBLAS is the one the numbers come from: NumPy's own (0), another
    SciPy-OpenBLAS build, as SciPy's (1), any other (2). Solver wheels bundle their own OpenBLAS
    (SCS ships 0.3.15, which calls a Zen CPU's kernels 'Zen' where NumPy's says 'Haswell'), and
    which of them loads first depends on what a process imported before."""
    path = Path(filepath)
    if "numpy" in path.parent.name:
        return 0
    return 1 if path.name.startswith("libscipy_openblas") else 2


@functools.lru_cache(maxsize=1)
def openblas_kernel() -> str | None:
    """The kernel family NumPy's OpenBLAS picked ('SkylakeX', 'Haswell'), None without one."""
    import numpy  # noqa: F401  (loads the OpenBLAS whose kernels the numbers come from)

    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return None
    found = [
        (_blas_rank(str(info.get("filepath") or "")), str(info["architecture"]))
        for info in threadpool_info()
        if info.get("internal_api") == "openblas" and info.get("architecture")
    ]
    return min(found)[1] if found else None


def unusual_blas(compiled: str, blas_kernel: str | None) -> str:
    """', OpenBLAS <kernel>' where the kernel is not the usual one for the compiled-for width,
    else ''."""
    usual = USUAL_BLAS_KERNELS.get(compiled)
    if blas_kernel is None or usual is None or blas_kernel in usual:
        return ""
    return f", OpenBLAS {blas_kernel}"


def numeric_kind_of(compiled: str, blas_kernel: str | None) -> str:
    """The numeric kind of a (compiled-for width, OpenBLAS kernel) pair: the width alone where
    the kernel is the usual one for it, else both ('avx512, OpenBLAS Haswell')."""
    return compiled + unusual_blas(compiled, blas_kernel)


def numeric_kind() -> str:
    """The kind of CPU whose numbers this process makes to the last bit: the vector width numba
    compiles for, plus OpenBLAS's kernels where they are not that width's usual ones."""
    return numeric_kind_of(compiled_for(), openblas_kernel())


UNRECORDED_KIND = "unrecorded"  # a record from before records named the CPU's numeric kind
# The field under which a record (an episode's outcome line, a labelled execution's metadata, a
# tried state) names the numeric kind of the CPU that computed it.
NUMERIC_KIND_KEY = "numeric_kind"


def kind_of_record(record: Mapping[str, object]) -> str:
    """The numeric kind a record names ('unrecorded' where it names none)."""
    return str(record.get(NUMERIC_KIND_KEY, UNRECORDED_KIND))


def numeric_kinds(records: Iterable[Mapping[str, object]]) -> dict[str, int]:
    """How many of ``records`` each numeric kind of CPU made, 'unrecorded' for older ones."""
    return dict(sorted(Counter(kind_of_record(r) for r in records).items()))


def other_kinds_warning(where: str, kinds: Iterable[str], what: str) -> str | None:
    """A sentence when ``kinds`` (those of the ``what`` already in ``where``) name another
    numeric kind than this machine's (unrecorded ones aside), else None: work added here can
    choose other demos at near-ties than the same work there."""
    here = numeric_kind()
    others = sorted({k for k in kinds if k not in (here, UNRECORDED_KIND)})
    if not others:
        return None
    return (
        f"{where} holds {what} made on {' and '.join(others)}; this machine is {here}, whose "
        "last bits can choose other demos at near-ties"
    )


def recorded_numeric_kind(machine: Mapping[str, object]) -> str:
    """The numeric kind a `machine_info` record names: its own field where it has one, else its
    compiled-for or vector width and NumPy's BLAS kernel, else the width whose usual kernel its
    BLAS picked (records from before they named a width); 'unrecorded' where none of these is."""
    if isinstance(machine.get(NUMERIC_KIND_KEY), str):
        return str(machine[NUMERIC_KIND_KEY])
    blas = machine.get("blas")
    # 'openblas 0.3.30 Haswell (libscipy_openblas-6cdc3b4a.so)': NumPy's and SciPy's builds first
    entries = sorted(
        (_blas_rank(str(b).split()[-1].strip("()")), str(b).split()[2])
        for b in (blas if isinstance(blas, list) else [])
        if len(str(b).split()) > 3
    )
    kernels = [k for rank, k in entries if rank == entries[0][0]] if entries else []
    width = machine.get("compiled_for") or machine.get("vector_width")
    if isinstance(width, str):
        return numeric_kind_of(width, kernels[0] if kernels else None)
    for kind, usual in USUAL_BLAS_KERNELS.items():
        if kernels and all(k in usual for k in kernels):
            return kind
    return UNRECORDED_KIND


def machine_line() -> str:
    """One line naming where a figure was measured: 'AMD EPYC (avx512), 2 cores, load 0.5'
    ('AMD EPYC (avx512, code compiled for avx2), ...' under `compile_for_avx2`; '(avx512,
    OpenBLAS Haswell)' where the environment picks OpenBLAS kernels unusual for the width)."""
    try:
        load = f", load {os.getloadavg()[0]:.1f}"
    except OSError:
        load = ""
    width = vector_width()
    target = compiled_for()
    kind = width if target == width else f"{width}, code compiled for {target}"
    kind += unusual_blas(target, openblas_kernel())
    return f"{cpu_model()} ({kind}), {usable_cores()} cores{load}"


def usable_cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def blas_kernels() -> list[str]:
    """Each loaded BLAS library and the kernel it picked for this CPU: 'openblas 0.3.30 Haswell'."""
    # OpenBLAS chooses its kernels per CPU at load time (OPENBLAS_CORETYPE overrides); results
    # can differ in the last bits between kernels, so a results file records which ran.
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return []
    return [
        f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')} "
        f"({Path(i.get('filepath') or '?').name})"
        for i in threadpool_info()
        if i.get("user_api") == "blas"
    ]


def machine_info() -> dict:
    """CPU model, cores, load average, BLAS kernels, Python and platform, as a JSON-able dict."""
    try:
        load = round(os.getloadavg()[0], 2)
    except OSError:
        load = None
    return {
        "cpu_model": cpu_model(),
        "vector_width": vector_width(),
        "compiled_for": compiled_for(),
        "numeric_kind": numeric_kind(),
        "cpu_count": os.cpu_count(),
        "usable_cores": usable_cores(),
        "load_average_1m": load,
        "blas": blas_kernels(),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
