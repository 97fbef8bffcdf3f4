"""scripts/table1_shared.sh end to end on one tiny task: segments logged, stop trap, resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.bench_modules import load_bench_module

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="a bash script")


def _script(project_root: Path, results: Path, tasks: int) -> list[str]:
    env = {"TASKS": str(tasks), "POLICIES": "nn", "RESULTS": str(results), "ENGINE": "local"}
    return [
        "env",
        *(f"{k}={v}" for k, v in env.items()),
        str(project_root / "scripts" / "table1_shared.sh"),
        "1",
    ]


def _episodes(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


@pytest.mark.slow
def test_table1_shared_logs_each_segment_and_resumes_after_a_stop(project_root, tmp_path) -> None:
    """A TERM mid-run leaves a stop line and the finished episodes; a rerun only adds the rest."""
    report = load_bench_module(project_root, "table1_report")
    main = tmp_path / "table1_shared_main"
    run = subprocess.Popen(_script(project_root, tmp_path, 3), start_new_session=True)
    deadline = time.monotonic() + 240
    while not (main / "outcomes.jsonl").exists() or not _episodes(main / "outcomes.jsonl"):
        assert run.poll() is None, "the script ended before its first episode"
        assert time.monotonic() < deadline, "no episode within 240 s"
        time.sleep(0.5)
    os.kill(run.pid, signal.SIGTERM)
    assert run.wait(timeout=120) == 143  # the trap's exit status: stopped, not failed
    first = _episodes(main / "outcomes.jsonl")
    assert 1 <= len(first) < 3
    segments = report.read_segments((main / "segments.log").read_text())
    assert len(segments) == 1 and segments[0].seconds is not None  # the stop line was written
    assert not (tmp_path / "table1_shared_hard").exists()  # stopped before the next level

    done = subprocess.run(_script(project_root, tmp_path, 3), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    episodes = _episodes(main / "outcomes.jsonl")
    assert sorted(e["task_index"] for e in episodes) == [0, 1, 2]  # nothing run twice
    assert episodes[: len(first)] == first  # the first segment's lines are kept as they were
    for level in ("main", "hard"):
        log = (tmp_path / f"table1_shared_{level}" / "segments.log").read_text()
        segments = report.read_segments(log)
        assert all(s.seconds is not None and s.workers == 1 for s in segments)
        assert "engine=local" in log
    assert len(_episodes(tmp_path / "table1_shared_hard" / "outcomes.jsonl")) == 3


def test_table1_shared_refuses_an_unknown_engine(project_root, tmp_path) -> None:
    cmd = _script(project_root, tmp_path, 1)
    cmd[cmd.index("ENGINE=local")] = "ENGINE=slurm"
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.strip() == "table1_shared.sh: ENGINE must be local or ray, not 'slurm'"
    assert not any(tmp_path.iterdir())  # nothing written
