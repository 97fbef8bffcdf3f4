"""Generate the demonstration library: the scripted expert over seeded start ropes, in parallel.

Decisions (documented here because the library's users depend on them):
- **Only successful demonstrations are kept.** Candidate start ropes j = 0, 1, 2, ... are drawn
  from ``SeedSequence(seed, spawn_key=(j,))``; the expert runs on each, and the library holds the
  first ``n_starts`` candidates (in candidate order) whose run reached the task's knot,
  renumbered 0..n_starts-1. Every segment's ``metadata["demo_knotted"]`` is therefore True; the
  expert's success rate during generation is stored in the library metadata. Candidates run in
  parallel processes in fixed-size batches, and which ones are kept depends only on the seed, so
  the file is bit-identical for any number of workers.
- **Replay is exact by construction.** Before every step the expert calls
  ``world.reset(pre_nodes)`` with the rope nodes read back after the previous step (the rope is at
  rest after ``execute``'s settle), so ``reset(pre_nodes) + execute(trajectory)`` reproduces
  ``post_nodes`` bit for bit; the simulator rebuilds its world from that plain state.
- **Clouds without noise.** ``pre_cloud_n3`` is the settings' observation model
  (`knotlab.core.world.observation`: the rope centreline by default, or the camera cloud) after
  ``reset(pre_nodes)``, noise 0: the library is the clean reference; callers add sensor noise to
  the scene side if they want it. The model is recorded as ``metadata["observation_model"]``, and
  every scene cloud of an episode, a lookahead or the oracle is made with the same model.
- Start ropes: 3 cm sine bends, rotated by at most +-30 degrees and shifted by at most +-0.1 m
  (a narrow range keeps registration neighbours close); styles from `core.demos.expert.sample_style`
  (half of them mirrored).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from knotlab.core.demos.library import DemoLibrary, DemoSegment, segment_key
from knotlab.core.errors import InvalidInputError
from knotlab.core.parallel import PerProcess
from knotlab.core.seeds import child_seed
from knotlab.core.tasks import DEFAULT_TASK, get_task
from knotlab.core.world.observation import DEFAULT_OBSERVATION, ObservationModel, observe

if TYPE_CHECKING:  # the simulator imports pybullet: built in the workers only
    from knotlab.core.world.sim import RopeWorld

GENERATOR = "knotlab.core.demogen/1"


@dataclass(frozen=True)
class GenSettings:
    """Everything that determines a generated library (stored in its metadata)."""

    seed: int = 0
    bend_amplitude: float = 0.03
    max_rotation: float = math.pi / 6
    max_translation: float = 0.1
    mirror_prob: float = 0.5
    max_attempts: int = 3  # tries of steps 2 and 3 from the same pre-step state
    max_restarts: int = 4  # loops laid per demo at most
    observation: ObservationModel = DEFAULT_OBSERVATION  # how pre-step clouds are made
    task: str = DEFAULT_TASK  # whose scripted expert demonstrates

    def to_dict(self) -> dict:
        """JSON-able copy."""
        return {
            "seed": int(self.seed),
            "bend_amplitude": float(self.bend_amplitude),
            "max_rotation": float(self.max_rotation),
            "max_translation": float(self.max_translation),
            "mirror_prob": float(self.mirror_prob),
            "max_attempts": int(self.max_attempts),
            "max_restarts": int(self.max_restarts),
            "observation_model": self.observation.value,
            # Absent means the overhand knot (libraries made before tasks were named), so the
            # shipped library's bytes and hash stay what they were.
            **({} if self.task == DEFAULT_TASK else {"task": self.task}),
        }


def candidate_seed(seed: int, candidate: int) -> int:
    """Seed of candidate demo ``candidate`` of a library generated with ``seed``."""
    return child_seed(seed, candidate)


@dataclass(frozen=True, eq=False)
class CandidateResult:
    """One expert run: its steps (pre nodes, cloud, trajectory, post nodes) and outcome."""

    candidate: int
    seed: int
    knotted: bool
    failed_step: int | None
    style: dict
    steps: list  # dicts with step, pre, cloud, traj, post, code, attempts, style
    wall_time: float
    restarts: int = 0


def _new_world() -> RopeWorld:
    from knotlab.core.world.sim import RopeWorld

    return RopeWorld()


_WORLD = PerProcess(_new_world)  # one simulator per worker process, reused across candidates


def run_candidate(job: tuple[GenSettings, int]) -> CandidateResult:
    """Draw candidate ``j``'s start rope and style, run the expert, observe each pre-step cloud."""
    settings, j = job
    world = _WORLD.get()
    s = candidate_seed(settings.seed, j)
    run = get_task(settings.task).demonstrate(world, settings, s)
    style = run.style
    steps = []
    for rec in run.steps:
        world.reset(rec.pre_nodes_k3)
        steps.append(
            {
                "step": rec.step_index,
                "pre": rec.pre_nodes_k3,
                "cloud": observe(world, settings.observation),
                "traj": rec.trajectory,
                "post": rec.post_nodes_k3,
                "code": rec.code,
                "attempts": rec.attempts,
                "style": rec.style.to_dict(),
            }
        )
    return CandidateResult(
        j, s, run.knotted, run.failed_step, style.to_dict(), steps, run.wall_time, run.restarts
    )


@dataclass(frozen=True, eq=False)
class GenReport:
    """What generation did: the library plus counts and timing (timing is not in the file)."""

    library: DemoLibrary
    candidates: int
    knotted: int
    failed_at_step: dict
    wall_time: float


def generate_library(
    n_starts: int,
    settings: GenSettings | None = None,
    *,
    workers: int | None = None,
    progress: bool = True,
    max_candidates: int | None = None,
) -> GenReport:
    """A library of ``n_starts`` successful expert demos (one segment per expert step: the
    task's ``expert_steps``), seeded and parallel."""
    from knotlab.core.parallel import default_workers, imap_processes

    settings = settings or GenSettings()
    if n_starts < 1:
        raise InvalidInputError(f"n_starts must be >= 1, got {n_starts}")
    max_candidates = max_candidates or 4 * n_starts + 10
    workers = default_workers() if workers is None else max(1, workers)
    wall0 = time.perf_counter()
    results: list[CandidateResult] = []
    next_j = 0
    # Batches of a fixed size (not dependent on workers) keep the kept set seed-determined.
    while sum(r.knotted for r in results) < n_starts and next_j < max_candidates:
        need = n_starts - sum(r.knotted for r in results)
        batch = min(max(need + need // 4 + 1, 2), max_candidates - next_j)
        jobs = [(settings, j) for j in range(next_j, next_j + batch)]
        got: list = [None] * batch
        for i, res in imap_processes(
            run_candidate, jobs, workers=workers, desc="expert demos", progress=progress
        ):
            got[i] = res
        results.extend(got)
        next_j += batch
    kept = [r for r in results if r.knotted][:n_starts]
    if len(kept) < n_starts:
        raise InvalidInputError(
            f"only {len(kept)} of {max_candidates} candidate demos ended in a knot; "
            f"needed {n_starts}"
        )
    last = kept[-1].candidate
    tried = [r for r in results if r.candidate <= last]
    n_knot = sum(r.knotted for r in tried)
    n_steps = get_task(settings.task).expert_steps
    fails = {str(k): sum(1 for r in tried if r.failed_step == k) for k in range(n_steps)}
    segments = []
    for new_index, r in enumerate(kept):
        for st in r.steps:
            segments.append(
                DemoSegment(
                    key=segment_key(new_index, st["step"]),
                    start_index=new_index,
                    step_index=st["step"],
                    pre_nodes_k3=st["pre"],
                    pre_cloud_n3=st["cloud"],
                    trajectory=st["traj"],
                    post_nodes_k3=st["post"],
                    metadata={
                        "seed": r.seed,
                        "candidate": r.candidate,
                        "style": st["style"],
                        "demo_style": r.style,
                        "demo_knotted": r.knotted,
                        "code": st["code"],
                        "attempts": st["attempts"],
                        "restarts": r.restarts,
                    },
                )
            )
    meta = {
        "generator": GENERATOR,
        **settings.to_dict(),
        "n_starts": n_starts,
        "candidates_tried": len(tried),
        "candidates_knotted": n_knot,
        "expert_success_rate": round(n_knot / len(tried), 4),
        "failed_at_step": fails,
        "cloud_noise": 0.0,
    }
    return GenReport(
        DemoLibrary(segments, meta), len(tried), n_knot, fails, time.perf_counter() - wall0
    )
