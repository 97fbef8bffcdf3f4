"""`knotlab bench` stopped by SIGTERM: exit 143, only whole outcome lines, no worker left behind."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from tests.minilib import write_mini_files
from tests.processes import needs_proc, pool_workers, still_alive_after, wait_until

pytestmark = [pytest.mark.xdist_group("bench"), needs_proc]


def _lines(path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines(keepends=True) if path.exists() else []


def test_sigterm_mid_run_exits_143_with_whole_lines_and_no_workers(tmp_path):
    lib, tasks = write_mini_files(tmp_path, n_tasks=3)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "knotlab.app.cli", "bench", "--policies", "nn,oracle"]
    cmd += ["--tasks", "3", "--max-steps", "2", "--workers", "2", "--no-progress"]
    cmd += ["--library", str(lib), "--task-set", str(tasks), "--out", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        outcomes = out / "outcomes.jsonl"
        # Mid-run: some episodes written, both workers still busy with others (6 in all).
        assert wait_until(lambda: _lines(outcomes) or proc.poll() is not None, timeout=300)
        assert proc.poll() is None, "the run finished before it could be interrupted"
        workers = pool_workers(proc.pid)
        assert len(workers) == 2
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:  # pragma: no cover - never leave the child behind
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err
    assert err.strip().splitlines()[-1] == "knotlab bench: terminated (SIGTERM)"
    assert "Traceback" not in err
    assert still_alive_after(workers, timeout=10) == set()
    lines = _lines(outcomes)
    assert 1 <= len(lines) < 6
    assert all(line.endswith("\n") and json.loads(line)["policy"] for line in lines)
    assert not (out / "results.json").exists()  # an interrupted run is not a result
