"""The state-aware scripted figure-eight expert and its style parameters.

A figure-eight knot in an open rope is a loop whose free end first wraps over the rope leaving
the loop and then threads the loop (under its first arm, over its second). One pen lay alone
can only make descending crossings (docs/tasks.md, "Why four steps"), so the expert uses four
moves with the right gripper, computing every pick and place from the rope it observes:

1. **Loop** (pen from end B). Frame: origin at arc length ``loop_start`` from end A, x along the
   rope there, y = ``chirality`` x rotated by +90 degrees. End B is lifted to
   `LOOP_LAY_HEIGHT` and laid like a pen: a 270-degree loop of radius ``loop_radius``, then
   straight down across the A side (the loop's crossing, B over A) and on for ``run_drop``
   below it: the *run*. What is left of end A (about 0.3 m) is the *tail*.
2. **Wrap** (pen from end A). Frame at the loop's crossing: x along the A strand entering it,
   y towards the loop. End A is lifted to ``wrap_height`` and laid from ``wrap_back`` behind
   the crossing, down and round across the run (the tail over the run) and then along x,
   ``wrap_drop`` below the crossing, to ``wrap_run`` beyond it: the tail now lies under the
   loop as the overhand expert's tail does after its first step.
3. **First arm over the tail** (pick and place). Tail direction d = chord of the tail's last
   8 cm, normal n towards the loop. Pick the loop's first half (from the A side) where it
   crosses the line ``grasp_gx`` beyond the tail tip along d (the crossing nearest the tail);
   else its farthest point along d; lift ``lift3`` and put it down at tail tip + ``grasp_gx`` d
   - ``drag_dy`` n. One leg of the dragged arm crosses the tail; the other comes back beyond
   the tip.
4. **Pull the tail out** over the loop's other side: pick the tail ``end_grasp`` from its tip
   and move it by ``pull_dx`` d - ``pull_dy`` n (d, n measured after step 2).

Checks and retries, as the overhand expert's: after each step the open rope's crossing code must
be the expected stage (`stages.STAGE_CODES`), the last one the figure-eight invariant. A failed
step is retried from the same pre-step state with a jittered style (``max_attempts`` tries);
then the expert starts over from the start rope (at most ``max_restarts`` loops). Only the
accepted tries are recorded. The expert observes the simulator's rope nodes.
Measured (bench/expert.py --task figure8): see docs/tasks.md.

Shape suffixes: k = rope nodes, 2/3 = xy/xyz.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.tasks.expert_moves import (
    RopeEnd,
    end_grasp_point,
    pen_lay,
    perp,
    pick_beyond_tip,
    pick_place,
    point_at,
    unit,
)
from knotlab.core.tasks.expert_runner import DemoRun, ScriptedExpert, StepRecord, Verdict
from knotlab.core.tasks.figure8.stages import STAGE_CODES, is_figure_eight_analysis
from knotlab.core.world.knot import analyse_knot, canonical_code
from knotlab.core.world.protocol import World
from knotlab.core.world.rope import segment_crossings_xy
from knotlab.core.world.trajectory import GripperTrajectory

N_STEPS = 4
LOOP_LAY_HEIGHT = 0.65  # m: end B hangs ~0.6 m of rope; lower, the loop's start kinks
MIN_PICK_HEIGHT = 0.015  # step 3 picks the loop at least this far from the tail line
_CANONICAL = tuple(canonical_code(code) for code in STAGE_CODES)


@dataclass(frozen=True)
class Figure8Style:
    """How one demonstration ties the knot: the expert's free choices (metres unless stated)."""

    chirality: int = 1  # +1: loop on the left of the rope; -1: the mirror variant
    loop_radius: float = 0.08
    loop_start: float = 0.40  # arc length from end A where the loop is laid
    loop_lead: float = 0.03  # the lay starts this far along the rope beyond loop_start
    run_drop: float = 0.14  # the run is laid this far below the A side
    wrap_back: float = 0.04
    wrap_drop: float = 0.06
    wrap_run: float = 0.10
    wrap_height: float = 0.30
    end_grasp: float = 0.0125  # grasp distance from the rope tip (steps 1, 2 and 4)
    grasp_gx: float = 0.0
    drag_dy: float = 0.08
    lift3: float = 0.04
    pull_dx: float = 0.20
    pull_dy: float = 0.05
    lift4: float = 0.05
    speed: float = 0.2  # m/s for steps 3 and 4
    lay_speed: float = 0.3  # m/s for steps 1 and 2

    def __post_init__(self) -> None:
        if self.chirality not in (1, -1):
            raise InvalidInputError(
                f"Figure8Style.chirality must be +1 or -1, got {self.chirality}"
            )
        for name in ("loop_radius", "loop_start", "wrap_height", "lift3", "lift4", "speed"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidInputError(f"Figure8Style.{name} must be positive, got {value}")
        if not 0.0 <= self.end_grasp <= 0.1:
            raise InvalidInputError(
                f"Figure8Style.end_grasp must be in [0, 0.1], got {self.end_grasp}"
            )

    def to_dict(self) -> dict:
        """Plain JSON-able dict (stored in demo metadata)."""
        return {k: (int(v) if k == "chirality" else float(v)) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> Figure8Style:
        """Inverse of :meth:`to_dict`."""
        return cls(**d)


def sample_style(rng: np.random.Generator, mirror_prob: float = 0.5) -> Figure8Style:
    """A moderately varied style (a narrow spread, as the overhand expert's)."""
    return Figure8Style(
        chirality=-1 if rng.uniform() < mirror_prob else 1,
        loop_radius=float(rng.uniform(0.075, 0.085)),
        loop_start=float(rng.uniform(0.39, 0.41)),
        run_drop=float(rng.uniform(0.13, 0.15)),
        wrap_drop=float(rng.uniform(0.055, 0.065)),
        wrap_run=float(rng.uniform(0.09, 0.11)),
        end_grasp=float(rng.uniform(0.01, 0.03)),
        grasp_gx=float(rng.uniform(-0.01, 0.01)),
        drag_dy=float(rng.uniform(0.07, 0.10)),
        pull_dx=float(rng.uniform(0.17, 0.22)),
        pull_dy=float(rng.uniform(0.03, 0.07)),
    )


def _jitter(style: Figure8Style, rng: np.random.Generator, step: int) -> Figure8Style:
    """A nearby style for a retry of ``step`` (same chirality and grasp choices)."""
    if step == 0:  # a new loop: size, place and lead
        return replace(
            style,
            loop_radius=float(np.clip(style.loop_radius + rng.uniform(-0.006, 0.006), 0.07, 0.09)),
            loop_start=float(style.loop_start + rng.uniform(-0.015, 0.015)),
            loop_lead=float(np.clip(style.loop_lead + rng.uniform(-0.01, 0.02), 0.02, 0.06)),
        )
    if step == 1:
        return replace(
            style,
            wrap_drop=float(np.clip(style.wrap_drop + rng.uniform(-0.01, 0.01), 0.045, 0.08)),
            wrap_run=float(np.clip(style.wrap_run + rng.uniform(-0.02, 0.02), 0.07, 0.13)),
        )
    if step == 2:
        return replace(
            style,
            grasp_gx=float(np.clip(style.grasp_gx + rng.uniform(-0.02, 0.02), -0.03, 0.03)),
            drag_dy=float(np.clip(style.drag_dy + rng.uniform(-0.01, 0.05), 0.07, 0.15)),
        )
    return replace(
        style,
        pull_dx=float(style.pull_dx + rng.uniform(-0.03, 0.03)),
        pull_dy=float(style.pull_dy + rng.uniform(-0.03, 0.03)),
    )


# ---------------------------------------------------------------------- what the steps measure
@dataclass(frozen=True)
class LoopCrossing:
    """The loop's own crossing: where it is and the node positions of its two visits."""

    point_2: np.ndarray
    first: float  # node position (index + fraction) of the visit nearer end A
    second: float

    @property
    def loop_nodes(self) -> tuple[int, int]:
        """Node range of the loop (between the two visits)."""
        return math.ceil(self.first), math.floor(self.second)


@dataclass(frozen=True)
class TailFrame:
    """The tail measured after the wrap: its tip, direction d and normal n, and the loop."""

    tip_2: np.ndarray
    along_2: np.ndarray  # d, towards the tip
    normal_2: np.ndarray  # n, from the tail towards the loop's centre
    loop_nodes: tuple[int, int]


def loop_crossing(nodes_k3: np.ndarray) -> LoopCrossing | None:
    """The innermost crossing (the fewest nodes between its visits), None without crossings."""
    xy = nodes_k3[:, :2]
    i, j, t, s = segment_crossings_xy(xy[:-1], xy[1:], cyclic=False)
    if i.size == 0:
        return None
    a, b = i + t, j + s
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    k = int(np.argmin(hi - lo))
    seg = int(i[k])
    point = xy[seg] + t[k] * (xy[seg + 1] - xy[seg])
    return LoopCrossing(point, float(lo[k]), float(hi[k]))


def _loop_centre(nodes_k3: np.ndarray, crossing: LoopCrossing) -> np.ndarray:
    lo, hi = crossing.loop_nodes
    if hi - lo < 3:
        raise InvalidInputError("the observed loop is too small to work with")
    return nodes_k3[lo : hi + 1, :2].mean(axis=0)


def tail_frame(nodes_k3: np.ndarray) -> TailFrame | None:
    """Measure the tail (end A) and the loop after the wrap; None without a loop."""
    crossing = loop_crossing(nodes_k3)
    if crossing is None:
        return None
    lo, hi = crossing.loop_nodes
    if hi - lo < 3:
        return None
    tip = nodes_k3[0, :2]
    along = unit(tip - point_at(nodes_k3, 0.08)[:2])
    normal = perp(along)
    if float(np.dot(_loop_centre(nodes_k3, crossing) - tip, normal)) < 0:
        normal = -normal
    return TailFrame(tip, along, normal, (lo, hi))


# ---------------------------------------------------------------------- the four steps
def plan_loop(nodes_k3: np.ndarray, style: Figure8Style) -> GripperTrajectory:
    """Step 1: lift end B high and lay a loop across the A side, then the run below it."""
    s0 = style.loop_start
    origin = point_at(nodes_k3, s0)[:2]
    ex = unit(origin - point_at(nodes_k3, s0 - 0.20)[:2])
    ey = style.chirality * perp(ex)
    r = style.loop_radius
    centre = np.array([-0.02, r])
    ang = np.linspace(-0.5 * np.pi, np.pi, 19)  # counter-clockwise in the local frame, 270 deg
    loop = centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    cx = centre[0] - r  # x of the descending leg that crosses the A side
    local = np.vstack([[style.loop_lead, 0.0], loop, [cx, -style.run_drop]])
    path = origin + local[:, :1] * ex + local[:, 1:2] * ey
    return pen_lay(
        nodes_k3, RopeEnd.B, path, LOOP_LAY_HEIGHT, grasp=style.end_grasp, speed=style.lay_speed
    )


def plan_wrap(nodes_k3: np.ndarray, style: Figure8Style) -> GripperTrajectory:
    """Step 2: lift end A and lay the tail round, across the run, to lie below the loop."""
    crossing = loop_crossing(nodes_k3)
    if crossing is None:
        raise InvalidInputError("no loop to wrap around")
    seg = math.floor(crossing.first)
    ex = unit(nodes_k3[seg + 1, :2] - nodes_k3[max(seg - 3, 0), :2])  # the A strand, into it
    ey = perp(ex)
    if float(np.dot(_loop_centre(nodes_k3, crossing) - crossing.point_2, ey)) < 0:
        ey = -ey
    back, drop = style.wrap_back, style.wrap_drop
    local = np.array(
        [[-back, 0.0], [-back - 0.025, -0.035], [-back + 0.01, -drop], [style.wrap_run, -drop]]
    )
    path = crossing.point_2 + local[:, :1] * ex + local[:, 1:2] * ey
    return pen_lay(
        nodes_k3, RopeEnd.A, path, style.wrap_height, grasp=style.end_grasp, speed=style.lay_speed
    )


def plan_over_tail(
    nodes_k3: np.ndarray, style: Figure8Style, frame: TailFrame
) -> GripperTrajectory:
    """Step 3: pick the loop's first half beyond the tail tip and drag it across the tail."""
    lo, hi = frame.loop_nodes
    side = nodes_k3[lo : (lo + hi) // 2 + 1]  # the loop's first half, from the A side
    target = style.grasp_gx
    pick = pick_beyond_tip(
        side, frame.tip_2, frame.along_2, frame.normal_2, target, MIN_PICK_HEIGHT
    )
    place = frame.tip_2 + target * frame.along_2 - style.drag_dy * frame.normal_2
    return pick_place(pick, style.lift3, place, 0.02, style.speed)


def plan_pull_tail(
    nodes_k3: np.ndarray, style: Figure8Style, frame: TailFrame
) -> GripperTrajectory:
    """Step 4: pick the tail near its tip and pull it out over the loop's other side."""
    pick = end_grasp_point(nodes_k3, RopeEnd.A, style.end_grasp)
    place = pick[:2] + style.pull_dx * frame.along_2 - style.pull_dy * frame.normal_2
    return pick_place(pick, style.lift4, place, 0.02, style.speed)


# ---------------------------------------------------------------------- running a demo
def _plan(
    step: int, nodes_k3: np.ndarray, style: Figure8Style, frame: TailFrame | None
) -> GripperTrajectory:
    if step == 0:
        return plan_loop(nodes_k3, style)
    if step == 1:
        return plan_wrap(nodes_k3, style)
    if frame is None:
        raise InvalidInputError("steps 3 and 4 need the tail frame measured after step 2")
    if step == 2:
        return plan_over_tail(nodes_k3, style, frame)
    return plan_pull_tail(nodes_k3, style, frame)


def _judge(step: int, post: np.ndarray, frame: TailFrame | None) -> Verdict[TailFrame]:
    """The expected stage's code after steps 1-3, the figure-eight after step 4; after the wrap
    the tail is measured."""
    analysis = analyse_knot(post)
    if step == N_STEPS - 1:
        good = is_figure_eight_analysis(post, analysis)
    else:
        good = canonical_code(analysis.gauss_code) == _CANONICAL[step]
    if step == 1 and good:
        frame = tail_frame(post)
        good = frame is not None
    return Verdict(analysis.gauss_code, good, frame)


EXPERT = ScriptedExpert(N_STEPS, _plan, _judge, _jitter, rng_stream=8)


def run_expert(
    world: World,
    start_nodes_k3: np.ndarray,
    style: Figure8Style,
    seed: int = 0,
    max_attempts: int = 3,
    max_restarts: int = 8,
) -> DemoRun[Figure8Style]:
    """Tie a figure-eight knot from ``start_nodes_k3`` (`expert_runner`: every step starts from
    ``world.reset(pre_nodes)``, so each recorded step replays bit for bit; a step is tried up to
    ``max_attempts`` times, then a new loop, at most ``max_restarts``). Seeded by ``seed``."""
    return EXPERT.run(
        world,
        start_nodes_k3,
        style,
        seed=seed,
        max_attempts=max_attempts,
        max_restarts=max_restarts,
    )


__all__ = [
    "N_STEPS",
    "DemoRun",
    "Figure8Style",
    "LoopCrossing",
    "StepRecord",
    "TailFrame",
    "loop_crossing",
    "plan_loop",
    "plan_over_tail",
    "plan_pull_tail",
    "plan_wrap",
    "run_expert",
    "sample_style",
    "tail_frame",
]
