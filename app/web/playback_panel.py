"""The Playback tab: replay a Table I episode (a bench results directory) or a stored labelling
episode as an animation, with a step timeline, play / pause / speed, the chosen demo, its score
and the stage reached per step, and export to a GIF for slides. Draws under /playback.

Export GIF follows the command line's output rule without a --force to give: the GIF is sent to
the browser and kept in ``exports/`` of the app's working directory under a name no file has
(``<episode>.gif``, else ``<episode>-1.gif``, ...; a file this panel wrote is rewritten), never in
static/, results/ or a task's data folder; the status line names the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import viser

from knotlab.app import defaults
from knotlab.app.options import fresh_file, in_shipped_place
from knotlab.app.web.frame_painter import (
    MAX_PAINT_HZ,
    FramePainter,
    GripperLook,
    next_frame_index,
)
from knotlab.app.web.geometry import hull_points
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.experiments.playback import (
    PlaybackEpisode,
    Replay,
    bench_episode,
    export_playback,
    resimulate,
)
from knotlab.core.selection.explain import stage_name
from knotlab.core.tasks import DEFAULT_TASK, get_task
from knotlab.core.textinput import whole_number

FRAME_DT = 1.0 / 20.0  # simulated s between replay frames (played at SPEEDS x)
SPEEDS = ("1x", "2x", "4x", "8x")
STORE = "labelling store (episode id)"
EXPORT_DIR = Path("exports")  # relative to the working directory, as `knotlab train`'s models/


def export_name(title: str) -> str:
    """A file stem for an episode title: 'la2x5 on main-test-0000' -> 'la2x5-on-main-test-0000'."""
    stem = re.sub(r"[^A-Za-z0-9_.]+", "-", title).strip("-.")[:80]
    return stem or "episode"


def export_path(folder: Path, stem: str, own: set[Path]) -> Path:
    """Where an export of ``stem`` goes in ``folder``: a name no file has, or one in ``own`` (the
    files this panel wrote); never a shipped or committed place (static/, results/, a task's
    data: an OutputPathError)."""
    from knotlab.core.errors import OutputPathError

    path = folder / f"{stem}.gif"
    if in_shipped_place(path):
        raise OutputPathError(
            f"{folder} is a shipped or committed folder (static/, results/ or a task's data); "
            "the app does not export into it"
        )
    return fresh_file(path, own=own)


def save_export(data: bytes, folder: Path, stem: str, own: set[Path]) -> Path:
    """Write ``data`` to `export_path` and add the file to ``own``: a new file is created
    exclusively (one that appears meanwhile is not replaced: the next free name is taken), one
    of ``own`` is replaced whole."""
    folder.mkdir(parents=True, exist_ok=True)
    while True:
        path = export_path(folder, stem, own)
        if path in own:  # its own file: replaced whole, through a fresh temporary beside it
            fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.stem}-", suffix=".tmp")
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
            os.replace(tmp, path)
            return path
        try:
            fh = path.open("xb")
        except FileExistsError:
            continue  # made by someone else since it was picked: take the next name
        own.add(path)
        try:
            with fh:
                fh.write(data)
        except BaseException:
            path.unlink(missing_ok=True)  # its own half-written file
            own.discard(path)
            raise
        return path


def results_dirs(root: Path = defaults.RESULTS_DIR, task: str = DEFAULT_TASK) -> list[str]:
    """Bench results directories of one task under results/ (those with a run.json, at any
    depth, the archive left out): the main level first, Table I's runs first within a level
    (the default source is the committed Table I). A run names its task in run.json; runs made
    before tasks existed are the overhand knot's. Runs in a perturbed world or with a state
    estimator are left out (a replay could not show what they did)."""
    if not root.is_dir():
        return []
    found = []
    for run in sorted(root.rglob("run.json")):
        if "archive" in run.relative_to(root).parts:
            continue
        try:
            identity = json.loads(run.read_text(encoding="utf-8")).get("identity") or {}
        except (OSError, ValueError, AttributeError):
            continue  # not a bench run's file: not a source
        # A replay simulates the nominal world from true observations: a run in a perturbed
        # world or with a state estimator would not replay as it ran, so it is not offered.
        world = identity.get("world", "nominal")
        replayable = world == "nominal" and identity.get("estimator", "perfect") == "perfect"
        if identity.get("task", DEFAULT_TASK) == task and replayable:
            found.append(str(run.parent))
    return sorted(
        found,
        key=lambda d: (
            not d.endswith("_main"),
            Path(d).name not in ("table1_main", "table1_hard"),  # the committed Table I itself
            not Path(d).name.startswith("table1"),
            d,
        ),
    )


DEFAULT_POLICY = "la2x5"  # the paper's best policy: what an audience is shown first


def first_episode(results_dir: str) -> tuple[str, str] | None:
    """(policy, task id) of the first episode a results directory records: the default
    policy's first when it ran, else the first line's; None when it has none."""
    path = Path(results_dir) / "outcomes.jsonl"
    first: tuple[str, str] | None = None
    try:
        with path.open(encoding="utf-8") as fh:
            for line in fh:
                with contextlib.suppress(ValueError, AttributeError):
                    record = json.loads(line)
                    policy, task_id = record.get("policy"), record.get("task_id")
                    if not (isinstance(policy, str) and isinstance(task_id, str)):
                        continue
                    if policy == DEFAULT_POLICY:
                        return policy, task_id
                    first = first or (policy, task_id)
    except OSError:
        return None
    return first


class PlaybackPanel:
    """One tab's playback: load, play, scrub and export an episode."""

    def __init__(
        self,
        client: viser.ClientHandle,
        store_executions: Callable[[int], tuple[PlaybackEpisode, DemoLibrary]],
        set_label_visible: Callable[[bool], None],
        inspect: Callable[[np.ndarray, str], None] | None = None,
        task: str = DEFAULT_TASK,
        frame: Callable[[np.ndarray], None] | None = None,
    ) -> None:
        self._inspect = inspect
        self._frame = frame  # points the camera at points clear of the panel (None: leave it)
        self.task_name = task  # whose runs are listed, and whose shipped files are tried first
        self.client = client
        self._store_execution = store_executions
        self._set_label_visible = set_label_visible
        gui = client.gui
        sources = (*results_dirs(task=task), STORE)
        self.source = gui.add_dropdown("Source", sources)
        # The default policy and task are an episode the default source holds, and follow it.
        policy, task_id = first_episode(sources[0]) or (DEFAULT_POLICY, "0")
        self.policy = gui.add_text("Policy", policy)
        self.task = gui.add_text("Task or episode id", task_id)
        self.source.on_update(lambda _e: self._default_task())
        self.load_button = gui.add_button("Load and replay", icon=viser.Icon.PLAYER_PLAY)
        self.status = gui.add_markdown("Pick an episode of the last Table I run, then Load.")
        self.timeline = gui.add_slider("Frame", 0, 1, 1, 0, disabled=True)
        self.play_button = gui.add_button("Play / pause", disabled=True)
        self.speed = gui.add_button_group("Speed", SPEEDS)
        self.caption = gui.add_markdown("")
        self.export_button = gui.add_button("Export GIF", disabled=True, icon=viser.Icon.DOWNLOAD)
        self.inspect_button = gui.add_button(
            "Inspect this step", disabled=True, hint="what NN, greedy and lookahead would choose"
        )
        self.back_button = gui.add_button("Back to the labelling view")
        self.episode: PlaybackEpisode | None = None
        self.library: DemoLibrary | None = None
        self.replay: Replay | None = None
        self._speed = 2.0
        self._playing = threading.Event()
        self._player: threading.Thread | None = None
        self._updating = False
        self._painter: FramePainter | None = None  # the replay's rope and grippers, drawn in place
        self.export_dir = EXPORT_DIR
        self._exported: set[Path] = set()  # the files this panel wrote (it may rewrite those)
        self.load_button.on_click(lambda _e: self.load())
        self.play_button.on_click(lambda _e: self.toggle())
        self.speed.on_click(lambda _e: self._set_speed(self.speed.value))
        self.timeline.on_update(lambda _e: None if self._updating else self.show(self.frame))
        self.export_button.on_click(lambda _e: self.export())
        self.back_button.on_click(lambda _e: self.stop())
        self.inspect_button.on_click(lambda _e: self.inspect_step())

    @property
    def frame(self) -> int:
        """The frame the timeline is at."""
        return int(self.timeline.value)

    def _set_speed(self, label: str) -> None:
        self._speed = float(label.rstrip("x"))

    # ------------------------------------------------------------------ loading
    def load(self) -> None:
        """Rebuild the episode and re-simulate it with its recorded choices."""
        self._playing.clear()
        self.status.content = "re-simulating the episode with its recorded choices..."
        try:
            source = self.source.value
            if source == STORE:
                episode_id = whole_number(self.task.value, "an episode id")
                self.episode, self.library = self._store_execution(episode_id)
            else:
                self.episode, self.library = bench_episode(
                    source,
                    self.policy.value.strip(),
                    self.task.value.strip(),
                    library_paths=[defaults.library_path(self.task_name)],
                    task_set_paths=[
                        defaults.task_set_path(lv, sp, self.task_name)
                        for lv in get_task(self.task_name).levels
                        for sp in ("test", "train")
                    ],
                )
            t0 = time.perf_counter()
            self.replay = resimulate(self.episode, self.library, dt=FRAME_DT)
        except Exception as exc:  # any bad pick: one line in the panel
            self.status.content = f"**cannot play**: {exc}"
            return
        r, episode = self.replay, self.episode
        warn = "".join(f"  \n warning: {w}" for w in r.warnings)
        self.status.content = (
            f"**{episode.title}**: {len(episode.steps)} steps, "
            f"{'knot tied' if r.knot else 'no knot'}; {len(r)} frames, re-simulated in "
            f"{time.perf_counter() - t0:.1f} s{warn}"
        )
        self._updating = True
        self.timeline.max = max(1, len(r) - 1)
        self.timeline.value = 0  # type: ignore[misc]
        self._updating = False
        self.timeline.disabled = False
        self.play_button.disabled = False
        self.export_button.disabled = False
        self.inspect_button.disabled = self._inspect is None
        self._set_label_visible(False)
        if self._frame is not None:  # the whole episode in view, so the camera never moves
            self._frame(hull_points(r.nodes_fk3))
        self.show(0)
        self.toggle()

    def _default_task(self) -> None:
        """A results source's first episode (policy and task id), or the store's first."""
        source = str(self.source.value)
        if source == STORE:
            self.task.value = "1"  # type: ignore[misc]
            return
        policy, task_id = first_episode(source) or (str(self.policy.value), "")
        self.policy.value = policy  # type: ignore[misc]
        self.task.value = task_id  # type: ignore[misc]

    # ------------------------------------------------------------------ playing
    def toggle(self) -> None:
        """Play from the timeline's frame (from the start when at the end), or pause."""
        if self._playing.is_set():
            self._playing.clear()
            return
        if self.replay is None:
            return
        if self.frame >= len(self.replay) - 1:  # Play at the end plays it again
            self._updating = True
            self.timeline.value = 0  # type: ignore[misc]
            self._updating = False
            self.show(0)
        self._playing.set()
        self._player = threading.Thread(target=self._play, name="playback", daemon=True)
        self._player.start()

    def _play(self) -> None:
        """Play at the chosen speed by the wall clock; frames that fall due while one is being
        drawn are skipped (at most MAX_PAINT_HZ frames a second are sent)."""
        replay = self.replay
        assert replay is not None
        i, last = self.frame, len(replay) - 1
        speed = self._speed
        t_wall0 = time.perf_counter() - i * FRAME_DT / speed
        last_paint = time.perf_counter()
        while self._playing.is_set() and i < last:
            if self._speed != speed:  # the speed changed: go on from here at the new one
                speed = self._speed
                t_wall0 = time.perf_counter() - i * FRAME_DT / speed
            i = next_frame_index(
                lambda k: k * FRAME_DT, i, last + 1, t_wall0, speed, time.perf_counter()
            )
            due = max(t_wall0 + i * FRAME_DT / speed, last_paint + 1.0 / MAX_PAINT_HZ)
            time.sleep(max(0.0, due - time.perf_counter()))
            self._updating = True
            self.timeline.value = i  # type: ignore[misc]
            self._updating = False
            self.show(i)
            last_paint = time.perf_counter()
        self._playing.clear()

    def show(self, i: int) -> None:
        """Draw frame i and its step's caption."""
        replay, episode = self.replay, self.episode
        if replay is None or episode is None or not len(replay):
            return
        i = int(np.clip(i, 0, len(replay) - 1))
        if self._painter is None:
            self._painter = FramePainter(
                self.client,
                "/playback",
                rope_radius=0.01,
                rope_colour=(196, 120, 60),
                look=GripperLook((0, 158, 115), open_radius=0.011, closed_radius=0.016),
            )
        self._painter.paint(replay.nodes_fk3[i], replay.grippers_fg3[i], replay.closed_fg[i])
        step = int(replay.step_f[i])
        s = episode.steps[step]
        score = "-" if s.score is None or not np.isfinite(s.score) else f"{s.score:.3f}"
        stage = replay.stages[step] if step < len(replay.stages) else None
        task = get_task(self.library.task) if self.library is not None else get_task()
        stage_label = stage_name(stage, task.stage_names)
        self.caption.content = (
            f"step **{step + 1}** of {len(episode.steps)} · demo `{s.demo_key}` · score {score}"
            f" · stage reached: **{stage_label}**"
        )

    def inspect_step(self) -> None:
        """Open the rope as it was before the timeline's step in the Inspect tab."""
        replay, episode = self.replay, self.episode
        if replay is None or episode is None or self._inspect is None:
            return
        self._playing.clear()
        step = int(replay.step_f[self.frame])
        first = int(np.flatnonzero(replay.step_f == step)[0])  # the rope before the step
        self._inspect(replay.nodes_fk3[first], f"{episode.title}, before step {step + 1}")

    def export(self) -> None:
        """Write the episode as a GIF and send it to the browser as a download."""
        if self.episode is None or self.library is None:
            return
        self.status.content = "rendering the GIF..."
        stem = export_name(self.episode.title)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"{stem}.gif"
            try:
                export_playback(self.episode, self.library, path, fps=15, speed=4.0, size=400)
            except Exception as exc:
                self.status.content = f"**export failed**: {exc}"
                return
            data = path.read_bytes()
        try:
            saved = save_export(data, self.export_dir, stem, self._exported)
        except Exception as exc:  # a read-only or shipped folder: the download still goes out
            kept = f"not kept on the server: {exc}"
            name = f"{stem}.gif"
        else:
            kept = f"kept as {saved.resolve()}"
            name = saved.name
        self.client.send_file_download(name, data, save_immediately=True)
        self.status.content = f"exported {name} ({len(data) / 1024:.0f} kB); {kept}"

    def stop(self) -> None:
        """Stop playing and show the labelling view again."""
        self._playing.clear()
        self.client.scene.remove_by_name("/playback")
        self._painter = None
        self._set_label_visible(True)
