"""Playback: bench outcomes carry what a replay needs, and a replay writes a faithful GIF."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from knotlab.app import cli
from knotlab.core.experiments.episode import decode_nodes, encode_nodes
from knotlab.core.experiments.playback import (
    PlaybackError,
    bench_episode,
    export_playback,
)
from tests.minilib import write_mini_files

pytestmark = pytest.mark.xdist_group("bench")


def test_rope_nodes_survive_the_compact_encoding_to_a_tenth_of_a_millimetre() -> None:
    nodes = np.random.default_rng(0).uniform(-0.9, 0.9, size=(41, 3))
    text = encode_nodes(nodes)
    assert text is not None and len(text) < 400
    assert np.abs(decode_nodes(text) - nodes).max() <= 0.5e-4 + 1e-12
    assert encode_nodes(np.full((3, 3), np.nan)) is None
    assert encode_nodes(np.full((3, 3), 5.0)) is None  # beyond +-3.2 m


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory) -> dict:
    """An nn bench run on one mini task (up to 3 steps): outcomes with the playback fields."""
    d = tmp_path_factory.mktemp("playback")
    lib, tasks = write_mini_files(d, n_tasks=1)
    out = d / "run"
    rc = cli.main(
        [
            *("bench", "--policies", "nn", "--tasks", "1", "--out", str(out)),
            *("--library", str(lib), "--task-set", str(tasks), "--max-steps", "3"),
            *("--workers", "1", "--no-progress"),
        ]
    )
    assert rc == 0
    (record,) = [json.loads(line) for line in (out / "outcomes.jsonl").read_text().splitlines()]
    return {"dir": d, "out": out, "library": lib, "tasks": tasks, "record": record}


def test_bench_outcomes_record_scores_and_the_rope_before_each_step(bench_run) -> None:
    rec = bench_run["record"]
    n = rec["n_steps"]
    assert n >= 1 and len(rec["scores"]) == n and len(rec["nodes_before"]) == n
    assert all(s is not None and s <= 0 for s in rec["scores"])  # nn: -registration cost
    assert decode_nodes(rec["nodes_before"][0]).shape == (41, 3)


def test_playback_replays_the_episode_and_writes_every_frame(bench_run, tmp_path) -> None:
    rec = bench_run["record"]
    episode, library = bench_episode(
        bench_run["out"], "nn", rec["task_id"], library_paths=[bench_run["library"]],
        task_set_paths=[bench_run["tasks"]],
    )  # fmt: skip
    fps = 10.0
    path, replay = export_playback(episode, library, tmp_path / "ep.gif", fps=fps, speed=8, size=96)
    assert replay.warnings == []  # same rope before every step, same stages, same end
    assert replay.knot == rec["success"] and replay.stages == rec["stages"]
    with Image.open(path) as gif:
        durations = []
        for i in range(gif.n_frames):
            gif.seek(i)
            durations.append(gif.info["duration"])
    # Pillow merges identical consecutive frames (a rope at rest) and adds up their durations.
    assert sum(durations) == len(replay) * round(1000 / fps)
    assert len(replay) > 3 * len(episode.steps)


def test_old_outcome_files_without_playback_fields_still_play(bench_run, tmp_path) -> None:
    old = tmp_path / "old"
    old.mkdir()
    for name in ("run.json", "results.json"):
        (old / name).write_text((bench_run["out"] / name).read_text())
    rec = {k: v for k, v in bench_run["record"].items() if k not in ("scores", "nodes_before")}
    (old / "outcomes.jsonl").write_text(json.dumps(rec) + "\n")
    episode, _ = bench_episode(old, "nn", rec["task_id"], library_paths=[bench_run["library"]])
    assert [s.score for s in episode.steps] == [None] * rec["n_steps"]
    assert all(s.nodes_before_k3 is None for s in episode.steps)


def test_playback_command_errors_are_one_line(bench_run, tmp_path, capsys) -> None:
    spec = f"{bench_run['out']}:nn:{bench_run['record']['task_id']}"
    lib = ["--library", str(bench_run["library"])]
    assert cli.main(["playback", spec, "--out", str(tmp_path / "x.mp4"), *lib]) in (0, 2)
    err = capsys.readouterr().err.strip()
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        assert "imageio-ffmpeg" in err and ".gif" in err and "\n" not in err
    assert cli.main(["playback", "nowhere:nn", "--out", str(tmp_path / "x.gif")]) == 2
    assert "RESULTS_DIR:POLICY:TASK_ID" in capsys.readouterr().err
    assert cli.main(["playback", f"{tmp_path}:nn:t", "--out", str(tmp_path / "x.gif")]) == 2
    assert "not a bench results directory" in capsys.readouterr().err
    with pytest.raises(PlaybackError, match="no episode"):
        bench_episode(bench_run["out"], "greedy", "nope", library_paths=[bench_run["library"]])
    assert not Path(tmp_path / "x.gif").exists()


@pytest.mark.slow
def test_a_store_episode_plays_from_its_labelled_start(bench_run, tmp_path, capsys) -> None:
    from knotlab.labeling_db.store import open_store
    from tests.minilib import mini_executions

    url = f"sqlite:///{tmp_path / 'k.db'}"
    with open_store(url) as store:
        (episode_id,) = store.add_executions(mini_executions(2)[:1])
    out = tmp_path / "db.gif"
    lib = ["--library", str(bench_run["library"])]
    rc = cli.main(["playback", f"db:{episode_id}", "--db", url, "--out", str(out), *lib])
    assert rc == 0, capsys.readouterr().err
    # The command replays the episode as stored as the core re-simulation does. (Whether the
    # replay of this 3-step demo through registration ties the knot again is a near tie: it
    # depends on the CPU, and on the store's float32 copy of the start rope against the float64
    # original; docs/determinism.md.)
    from knotlab.app.episodes import store_episode
    from knotlab.core.experiments.playback import resimulate

    with open_store(url) as store:
        episode, library = store_episode(store, episode_id, bench_run["library"])
    replay = resimulate(episode, library, dt=0.05)
    said = capsys.readouterr().out
    assert ("(knot)" if replay.knot else "(no knot)") in said, said
    with Image.open(out) as gif:
        assert gif.n_frames > 3
    assert cli.main(["playback", "db:x", "--db", url, "--out", str(tmp_path / "x.gif")]) == 2
    assert "integer id" in capsys.readouterr().err
