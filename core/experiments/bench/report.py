"""The table: success rates with Wilson score 95 % intervals, the text table, the bar chart.

centre = (k + z^2/2) / (n + z^2),  half = z sqrt(k (n - k) / n + z^2 / 4) / (n + z^2).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from knotlab.core.atomic import atomic_path
from knotlab.core.errors import InvalidInputError
from knotlab.core.tasks import DEFAULT_TASK, get_task

RESULTS_FORMAT = "knotlab-bench-results"
RESULTS_VERSION = 1
RESULTS_FILE = "results.json"
CHART_FILE = "table1.png"
Z_95 = 1.959963984540054
# The paper's Table I (success within 5 steps); no oracle row there.
# The paper's Table I: the overhand knot's reference rates (its task carries them).
PAPER_TABLE1: dict[str, float] = dict(get_task(DEFAULT_TASK).reference_rates)


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (scipy's; (nan, nan) for n = 0)."""
    from scipy.stats import binomtest, norm

    if n < 0 or not 0 <= successes <= n:
        raise InvalidInputError(f"need 0 <= successes <= n, got {successes} of {n}")
    if n == 0:
        return (math.nan, math.nan)
    ci = binomtest(int(successes), int(n)).proportion_ci(
        confidence_level=float(2 * norm.cdf(z) - 1), method="wilson"
    )
    return (float(ci.low), float(ci.high))


def summarize(policy: str, records: Sequence[dict], reference: Mapping[str, float]) -> dict:
    """One Table I row: successes, rate, Wilson 95 %, decision time per step, steps, failures;
    ``reference``: the task's published rates (`Task.reference_rates`), shown beside ours."""
    n = len(records)
    k = sum(bool(r["success"]) for r in records)
    lo, hi = wilson_interval(k, n)
    decide = [t for r in records for t in r.get("decision_s", []) if t is not None]
    decide = [t for t in decide if math.isfinite(t)]
    failures = Counter(r["failure_kind"] for r in records if not r["success"])
    return {
        "policy": policy,
        "n": n,
        "successes": k,
        "rate": k / n if n else math.nan,
        "wilson_low": lo,
        "wilson_high": hi,
        "paper_rate": reference.get(policy),
        "mean_decision_s_per_step": float(np.mean(decide)) if decide else math.nan,
        "mean_steps": float(np.mean([r["n_steps"] for r in records])) if n else math.nan,
        "mean_steps_success": (
            float(np.mean([r["n_steps"] for r in records if r["success"]])) if k else math.nan
        ),
        "mean_episode_wall_s": float(np.mean([r["wall_s"] for r in records])) if n else math.nan,
        "failures": dict(sorted(failures.items())),
    }


def format_table(rows: Sequence[dict], title: str = "Table I") -> str:
    """Plain-text Table I: ours next to the paper's figure."""
    head = (
        f"{'policy':<8} {'success':>9} {'rate':>7} {'95% Wilson':>15} {'paper':>7} "
        f"{'decide s/step':>13} {'steps':>6}  failures"
    )
    lines = [title, head, "-" * len(head)]
    for r in rows:
        paper = f"{100 * r['paper_rate']:.1f}%" if r["paper_rate"] is not None else "-"
        interval = f"[{100 * r['wilson_low']:.1f}, {100 * r['wilson_high']:.1f}]"
        fails = ", ".join(f"{k} {v}" for k, v in r["failures"].items()) or "-"
        lines.append(
            f"{r['policy']:<8} {r['successes']:>4}/{r['n']:<4} {100 * r['rate']:>6.1f}% "
            f"{interval:>15} {paper:>7} {r['mean_decision_s_per_step']:>13.3f} "
            f"{r['mean_steps']:>6.2f}  {fails}"
        )
    return "\n".join(lines)


def plot_table(rows: Sequence[dict], path: str | Path, title: str = "") -> Path:
    """Bar chart of success rates with Wilson 95 % error bars and the paper's figures (Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    fig = Figure(figsize=(1.6 + 1.3 * len(rows), 4.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(rows))
    rate = np.array([100 * r["rate"] for r in rows])
    err = np.array(
        [
            [100 * (r["rate"] - r["wilson_low"]) for r in rows],
            [100 * (r["wilson_high"] - r["rate"]) for r in rows],
        ]
    )
    ax.bar(x, rate, width=0.6, color="#4C72B0", label="knotlab", yerr=err, capsize=5)
    paper = [(i, 100 * r["paper_rate"]) for i, r in enumerate(rows) if r["paper_rate"] is not None]
    if paper:
        ax.scatter(*zip(*paper, strict=True), marker="D", color="#DD8452", zorder=3, label="paper")
    for i, r in enumerate(rows):
        top = 100 * r["wilson_high"] if math.isfinite(r["wilson_high"]) else 0.0
        ax.annotate(f"{r['successes']}/{r['n']}", (i, top + 2), ha="center", fontsize=8)
    ax.set_xticks(x, [r["policy"] for r in rows])
    ax.set_ylim(0, 110)
    ax.set_ylabel("success rate (%)  [Wilson 95 %]")
    ax.set_title(title or "success rate per policy")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    return path


def package_versions() -> dict[str, str | None]:
    """Versions of the packages that decide the numbers."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for name in ("numpy", "scipy", "pybullet", "cvxpy", "clarabel", "knotlab", "ray"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out
