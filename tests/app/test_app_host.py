"""`knotlab app --host`: an address this machine does not have fails at once, in one line; Ctrl-C
stops the app within 5 s, while it starts and while it serves."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from knotlab.app.cmd_app import check_host
from knotlab.core.errors import InvalidInputError


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _app(tmp_path: Path, *flags: str, **kwargs) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k not in ("KNOTLAB_DB_URL", "KNOTLAB_DEBUG")}
    db = f"sqlite:///{tmp_path / 'k.db'}"
    return subprocess.Popen(
        [sys.executable, "-m", "knotlab.app.cli", "app", "--db", db, *flags],
        cwd=tmp_path,
        env={**env, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"},
        text=True,
        **kwargs,
    )


def test_a_host_this_machine_does_not_have_fails_in_one_line_at_once(tmp_path: Path) -> None:
    # 192.0.2.1 is TEST-NET-1 (RFC 5737): never an address of this machine
    start = time.monotonic()
    proc = _app(tmp_path, "--host", "192.0.2.1", "--port", str(_free_port()),
                stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    try:
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert time.monotonic() - start < 10
    assert proc.returncode == 2, err
    assert err.splitlines() == [
        "knotlab app: error: --host 192.0.2.1: this machine has no such address (give one of "
        "its own addresses, 127.0.0.1 for this machine only, or 0.0.0.0 for every network)"
    ]
    assert out == ""
    assert list(tmp_path.iterdir()) == []  # no database made, nothing started


def test_check_host_accepts_this_machine_s_addresses_and_busy_ports() -> None:
    check_host("127.0.0.1", 0)
    check_host("0.0.0.0", 0)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        check_host("127.0.0.1", busy.getsockname()[1])  # viser moves to the next free port
    with pytest.raises(InvalidInputError, match="no such address"):
        check_host("192.0.2.1", 8080)


def _stop_within_5_s(proc: subprocess.Popen) -> tuple[str, float]:
    start = time.monotonic()
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return out, time.monotonic() - start


def _read_until(proc: subprocess.Popen, text: str, timeout: float = 120.0) -> str:
    seen = ""
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seen += line
        if text in line:
            return seen
    raise AssertionError(f"the app never printed {text!r}:\n{seen}")


def _ignoring_sigint() -> None:  # a shell's `cmd &`: the child inherits SIGINT as ignored
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def test_ctrl_c_stops_the_app_within_5_s_while_serving(tmp_path: Path) -> None:
    proc = _app(tmp_path, "--port", "0", "--sim-workers", "0", stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT, preexec_fn=_ignoring_sigint)  # fmt: skip
    _read_until(proc, "labelling at http://127.0.0.1:")
    out, took = _stop_within_5_s(proc)
    assert proc.returncode == 0 and took < 5, out
    assert "stopping" in out and "Traceback" not in out


def test_ctrl_c_stops_the_app_within_5_s_while_it_starts(tmp_path: Path) -> None:
    proc = _app(tmp_path, "--port", "0", "--sim-workers", "0", stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT, preexec_fn=_ignoring_sigint)  # fmt: skip
    _read_until(proc, "ranking candidates with")  # loaded, about to warm up and serve
    out, took = _stop_within_5_s(proc)
    assert took < 5, out
    assert proc.returncode in (0, 130), out  # interrupted, or it was already serving
    assert "Traceback" not in out
