"""Play an episode back: re-simulate it from its start with the recorded choices, render frames.

An episode to play is a start rope and the demo chosen at each step (from a bench results file
or from the labelling store). The simulator is deterministic, so resetting to the start and
transferring the same demos onto the same observations reproduces the run; every execution is
recorded with a `FrameRecorder`. What was recorded (stage per step, the rope before each step,
knot or not) is compared with what the replay did, and every difference becomes a warning.
Frames are drawn top-down with matplotlib (rope as a thick line, grippers as dots: filled while
holding) and written as a GIF (Pillow) or, when imageio-ffmpeg is installed, an MP4.
Shape suffixes: k = rope nodes, g = grippers, f = frames.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Protocol, TypeVar

import numpy as np

from knotlab.core.demos.library import DemoLibrary
from knotlab.core.demos.tasks import TaskSet
from knotlab.core.errors import InvalidInputError, KnotlabError
from knotlab.core.experiments.episode import decode_nodes, step_seed
from knotlab.core.selection.labels import LabelledExecution
from knotlab.core.world.frames import FrameRecorder
from knotlab.core.world.render import rope_width_pt, table_axes, table_figure, thick_line

NODES_TOLERANCE_M = 0.002  # replayed vs recorded rope before a step: more is a warning
FORMATS: tuple[str, ...] = (".gif", ".mp4")


class PlaybackError(KnotlabError):
    """An episode cannot be found, rebuilt or written as an animation."""


@dataclass(frozen=True, eq=False)
class PlaybackStep:
    """One recorded decision: the demo, its score (Q or -cost) and what the record says it did."""

    demo_key: str
    score: float | None = None
    stage: int | None = None  # stage reached after the step, when recorded
    nodes_before_k3: np.ndarray | None = None  # the rope before the step, when recorded


@dataclass(frozen=True, eq=False)
class PlaybackEpisode:
    """What a replay needs: the start rope, the choices, and the recorded result."""

    title: str  # e.g. "greedy on main-test-0001"
    start_nodes_k3: np.ndarray
    steps: tuple[PlaybackStep, ...]
    recorded_knot: bool
    noise: float = 0.0  # observation noise of the run (bench), with its episode seed
    seed: int | None = 0  # None: observed unseeded, as the labelling app observes
    # The labelling app places each state at rest from the rope its previous step ended in
    # (so that an undo or a resume places it again bit for bit); a replay of its episodes
    # places each step's state from ``nodes_before_k3`` likewise instead of simulating on.
    placed_at_rest: bool = False


@dataclass
class Replay:
    """The re-simulated episode: frames, per-frame step index, the end, and any mismatch."""

    nodes_fk3: np.ndarray
    grippers_fg3: np.ndarray
    closed_fg: np.ndarray
    step_f: np.ndarray  # which step each frame belongs to
    stages: list[int]
    knot: bool
    warnings: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.step_f)


# ----------------------------------------------------------------------------- loading


def load_matching_library(
    candidates: Sequence[str | Path | None], library_hash: str
) -> DemoLibrary:
    """The first candidate library file whose content hash is ``library_hash``."""
    return _first_matching(candidates, library_hash, DemoLibrary.load, "demo library")


def load_matching_task_set(candidates: Sequence[str | Path | None], task_set_hash: str) -> TaskSet:
    """The first candidate task-set file whose content hash is ``task_set_hash``."""
    return _first_matching(candidates, task_set_hash, TaskSet.load, "task set")


class _Hashed(Protocol):
    def content_hash(self) -> str: ...


_H = TypeVar("_H", bound=_Hashed)


def _first_matching(
    candidates: Sequence[str | Path | None],
    wanted: str,
    load: Callable[[str | Path], _H],
    what: str,
) -> _H:
    tried = []
    for c in candidates:
        if c is None or str(c) in tried:
            continue
        tried.append(str(c))
        if not Path(c).exists():
            continue
        obj = load(c)
        if obj.content_hash() == wanted:
            return obj
    raise PlaybackError(
        f"no {what} with hash {wanted} among {', '.join(tried) or 'no candidates'}; "
        f"pass the one the run used"
    )


def bench_episode(
    results_dir: str | Path,
    policy: str,
    task_id: str,
    *,
    library_paths: Sequence[str | Path | None] = (),
    task_set_paths: Sequence[str | Path | None] = (),
) -> tuple[PlaybackEpisode, DemoLibrary]:
    """One (policy, task) episode of a `knotlab bench` results directory, and its library.

    The library and task set are the first of the given paths, then those the run recorded in
    results.json, whose content hashes match the run identity in run.json.
    """
    from knotlab.core.experiments.bench import OUTCOMES_FILE, RESULTS_FILE, RUN_FILE, OutcomeLog

    out = Path(results_dir)
    if not (out / RUN_FILE).exists():
        raise PlaybackError(f"{out} is not a bench results directory (no {RUN_FILE})")
    identity = json.loads((out / RUN_FILE).read_text(encoding="utf-8"))["identity"]
    record = OutcomeLog(out / OUTCOMES_FILE).load().get((policy, task_id))
    if record is None:
        raise PlaybackError(f"{out / OUTCOMES_FILE} has no episode of {policy!r} on {task_id!r}")
    arguments: dict = {}
    if (out / RESULTS_FILE).exists():
        arguments = json.loads((out / RESULTS_FILE).read_text(encoding="utf-8")).get(
            "arguments", {}
        )
    library = load_matching_library(
        [*library_paths, arguments.get("library")], identity["library_hash"]
    )
    tasks = load_matching_task_set(
        [*task_set_paths, arguments.get("task_set")], identity["task_set_hash"]
    )
    task = next((t for t in tasks if t.task_id == task_id), None)
    if task is None:
        raise PlaybackError(f"task {task_id!r} is not in the run's task set")
    chosen = list(record.get("chosen", []))
    scores = list(record.get("scores", [])) or [None] * len(chosen)
    stages = list(record.get("stages", [])) or [None] * len(chosen)
    nodes = list(record.get("nodes_before", [])) or [None] * len(chosen)
    steps = tuple(
        PlaybackStep(key, score, stage, None if n is None else decode_nodes(n))
        for key, score, stage, n in zip(chosen, scores, stages, nodes, strict=True)
    )
    episode = PlaybackEpisode(
        f"{policy} on {task_id}",
        task.start_nodes_k3,
        steps,
        bool(record["success"]),
        float(identity.get("noise", 0.0)),
        int(record.get("seed", 0)),
    )
    return episode, library


def execution_episode(
    execution: LabelledExecution,
    title: str,
    placed_k3: Mapping[int, np.ndarray] | None = None,
) -> PlaybackEpisode:
    """A labelled execution (a store episode) as a playback episode, from its first step's rope.

    ``placed_k3``: for an episode made in the labelling app, the exact ropes its states were
    placed from at rest, by step index (a step without one was placed from its stored rope);
    the replay then places every state as the app did. Without it the replay simulates on from
    the first rope, as the oracle's and the bench's episodes ran.
    """
    if not execution.steps:
        raise PlaybackError(f"{title}: the execution has no labelled steps to play")
    start = execution.steps[0].rope_nodes_k3
    if start is None:
        raise PlaybackError(f"{title}: its start state has no rope nodes, only a cloud")
    placed = {} if placed_k3 is None else dict(placed_k3)
    steps = []
    for s in execution.steps:
        score = None
        if s.candidate_scores_c is not None and s.chosen_demo in s.candidates:
            score = float(s.candidate_scores_c[s.candidates.index(s.chosen_demo)])
        before = placed.get(s.step_index, s.rope_nodes_k3)
        steps.append(PlaybackStep(s.chosen_demo, score, None, before))
    if placed_k3 is None:
        return PlaybackEpisode(title, start, tuple(steps), execution.ended_in_knot)
    first = steps[0].nodes_before_k3
    assert first is not None
    return PlaybackEpisode(
        title, first, tuple(steps), execution.ended_in_knot, seed=None, placed_at_rest=True
    )


# ----------------------------------------------------------------------------- re-simulation


def resimulate(
    episode: PlaybackEpisode, library: DemoLibrary, *, dt: float, progress: bool = False
) -> Replay:
    """Reset to the start and apply the recorded demos, recording a frame every ``dt`` sim s."""
    from knotlab.core.execution.apply import apply_demo
    from knotlab.core.registration.planner import DemoTransferer
    from knotlab.core.world.observation import ObservationModel, observe
    from knotlab.core.world.sim import RopeWorld

    observation = ObservationModel.of_library_metadata(library.metadata)
    transferer = DemoTransferer(library)
    nodes, grippers, closed, step_of = [], [], [], []
    stages: list[int] = []
    warnings: list[str] = []
    knot = False
    with RopeWorld() as world:
        world.reset(episode.start_nodes_k3)
        for i, step in enumerate(episode.steps):
            if step.demo_key not in library.keys:
                raise PlaybackError(f"step {i}: demo {step.demo_key!r} is not in the library")
            before = world.rope_nodes()
            recorded = step.nodes_before_k3
            if recorded is not None and recorded.shape == before.shape:
                gap = float(np.linalg.norm(before - recorded, axis=1).max())
                if gap > NODES_TOLERANCE_M:
                    warnings.append(
                        f"step {i}: the replayed rope is {1000 * gap:.1f} mm from the recorded one"
                    )
                if episode.placed_at_rest and i > 0:
                    world.reset(recorded)  # as the app placed it (step 0: the reset above)
                    before = world.rope_nodes()
            seed = None if episode.seed is None else step_seed(episode.seed, i)
            cloud = observe(world, observation, noise=episode.noise, seed=seed)
            rec = FrameRecorder(dt)
            outcome = apply_demo(world, transferer, cloud, library.index_of(step.demo_key), rec)
            frames = rec.frames()
            if frames is None:  # nothing executed (registration failed): hold the rope still
                nodes.append(before[None])
                grippers.append(np.full((1, 2, 3), np.nan))
                closed.append(np.zeros((1, 2), bool))
                step_of.append(np.array([i]))
            else:
                nodes.append(frames.nodes_fk3)
                grippers.append(frames.grippers_fg3)
                closed.append(frames.closed_fg)
                step_of.append(np.full(len(frames), i))
            stages.append(int(outcome.stage))
            if step.stage is not None and int(step.stage) != int(outcome.stage):
                warnings.append(
                    f"step {i}: replay reached stage {int(outcome.stage)}, the record says "
                    f"{step.stage}"
                )
            if outcome.knot:
                knot = True
                break
            if outcome.exploded:
                warnings.append(f"step {i}: the simulation blew up during the replay")
                break
    if knot != episode.recorded_knot:
        warnings.append(
            f"the replay {'tied' if knot else 'did not tie'} a knot, the record says "
            f"{'knot' if episode.recorded_knot else 'no knot'}"
        )
    if len(stages) != len(episode.steps):
        warnings.append(f"the replay ended after {len(stages)} of {len(episode.steps)} steps")
    return Replay(
        np.concatenate(nodes),
        np.concatenate(grippers),
        np.concatenate(closed),
        np.concatenate(step_of),
        stages,
        knot,
        warnings,
    )


# ----------------------------------------------------------------------------- rendering


def _caption(episode: PlaybackEpisode, replay: Replay, i: int) -> str:
    step = episode.steps[i]
    score = "-" if step.score is None or not math.isfinite(step.score) else f"{step.score:.3f}"
    stage = replay.stages[i] if i < len(replay.stages) else "?"
    n = len(episode.steps)
    return f"step {i + 1}/{n}   demo {step.demo_key}   Q {score}   -> stage {stage}"


def render_frames(episode: PlaybackEpisode, replay: Replay, *, size: int = 400) -> list:
    """Every frame as a PIL image (top-down view, fixed limits, caption at the top)."""
    from PIL import Image

    # Frame the rope and the grippers while they hold it: an idle gripper parked far away
    # would otherwise shrink the rope to a few pixels.
    xy = np.concatenate(
        [replay.nodes_fk3.reshape(-1, 3)[:, :2], replay.grippers_fg3[replay.closed_fg][:, :2]]
    )
    xy = xy[np.isfinite(xy).all(axis=1)]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    centre, span = 0.5 * (lo + hi), float((hi - lo).max()) + 0.1
    fig, canvas = table_figure(size, size)
    ax = table_axes(fig, (0.0, 0.0, 1.0, 0.92), centre, span)
    width = max(2.0, rope_width_pt(0.02, size, span))  # the rope's 2 cm diameter, in points
    rope = thick_line(ax, [], [], color="#3b5b92", width=width)
    (end,) = ax.plot([], [], "o", color="#c44e52", ms=width * 0.9)  # one end: shows direction
    grip = ax.scatter([np.nan, np.nan], [np.nan, np.nan], s=80, zorder=3)
    title = fig.text(0.5, 0.96, "", ha="center", va="center", fontsize=8)
    fig.text(0.01, 0.005, episode.title, fontsize=7, color="#555555")
    images = []
    for f in range(len(replay)):
        nodes = replay.nodes_fk3[f]
        rope.set_data(nodes[:, 0], nodes[:, 1])
        end.set_data(nodes[:1, 0], nodes[:1, 1])
        grip.set_offsets(replay.grippers_fg3[f][:, :2])
        grip.set_facecolor(["#222222" if c else "none" for c in replay.closed_fg[f]])
        grip.set_edgecolor("#222222")
        title.set_text(_caption(episode, replay, int(replay.step_f[f])))
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        images.append(Image.fromarray(rgba[:, :, :3].copy()))
    return images


def _mp4_writer() -> ModuleType:
    try:
        import imageio_ffmpeg
    except ImportError:
        raise PlaybackError(
            "MP4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); "
            "write a .gif instead"
        ) from None
    return imageio_ffmpeg


def write_animation(images: list, path: str | Path, *, fps: float) -> Path:
    """Write frames as a GIF (Pillow) or MP4 (imageio-ffmpeg), atomically (temp + rename)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise PlaybackError(f"{path}: the animation must be a .gif or .mp4 file")
    if not images:
        raise PlaybackError("no frames to write")
    if not (math.isfinite(fps) and fps > 0):
        raise InvalidInputError(f"fps must be > 0, got {fps}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{suffix}")
    if suffix == ".gif":
        # One shared palette keeps the file small and the colours steady between frames.
        first = images[0].quantize(colors=64)
        frames = [first] + [im.quantize(palette=first) for im in images[1:]]
        frames[0].save(
            tmp,
            save_all=True,
            append_images=frames[1:],
            duration=round(1000 / fps),
            loop=0,
            optimize=True,
        )
    else:
        imageio_ffmpeg = _mp4_writer()
        w, h = images[0].size
        writer = imageio_ffmpeg.write_frames(str(tmp), (w, h), fps=fps, macro_block_size=1)
        writer.send(None)
        for im in images:
            writer.send(np.ascontiguousarray(np.asarray(im)))
        writer.close()
    os.replace(tmp, path)
    return path


def export_playback(
    episode: PlaybackEpisode,
    library: DemoLibrary,
    path: str | Path,
    *,
    fps: float = 20.0,
    speed: float = 4.0,
    size: int = 400,
) -> tuple[Path, Replay]:
    """Re-simulate, render and write ``path``; ``speed`` simulated seconds per second of film."""
    if not (math.isfinite(speed) and speed > 0):
        raise InvalidInputError(f"speed must be > 0, got {speed}")
    if not (math.isfinite(fps) and fps > 0):
        raise InvalidInputError(f"fps must be > 0, got {fps}")
    if Path(path).suffix.lower() not in FORMATS:
        raise PlaybackError(f"{path}: the animation must be a .gif or .mp4 file")
    if Path(path).suffix.lower() == ".mp4":
        _mp4_writer()  # fail before minutes of simulation, not after
    replay = resimulate(episode, library, dt=speed / fps)
    images = render_frames(episode, replay, size=size)
    return write_animation(images, path, fps=fps), replay
