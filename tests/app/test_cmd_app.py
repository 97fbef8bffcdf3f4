"""`knotlab app` as `make run` starts it: serves the page, Ctrl-C stops it cleanly."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import urllib.request

import pytest

from knotlab.app.cli import build_parser


def test_app_defaults_are_loopback_port_8080_and_five_candidates():
    from knotlab.app.options import resolve_level

    args = build_parser().parse_args(["app"])
    assert (args.host, args.port, args.top, args.task) == ("127.0.0.1", 8080, 5, "overhand")
    assert resolve_level(args) == "main"
    assert build_parser().parse_args(["app", "--top-k", "3"]).top == 3  # the README's spelling


@pytest.mark.parametrize(
    "flag", [["--top", "0"], ["--top", "10"], ["--top-k", "10"], ["--port", "-1"]]
)
def test_app_rejects_bad_numbers(flag, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["app", *flag])
    assert exc.value.code == 2
    assert "expected" in capsys.readouterr().err


def _serve(tmp_path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "knotlab.app.cli",
            "app",
            "--db",
            f"sqlite:///{tmp_path / 'k.db'}",
            "--port",
            "0",
            *extra,
        ],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _wait_for_url(proc: subprocess.Popen, timeout: float = 120.0) -> tuple[str, list[str]]:
    lines: list[str] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        match = re.search(r"labelling at (http://\S+)", line)
        if match:
            return match.group(1), lines
    proc.kill()
    raise AssertionError("the app never printed its URL:\n" + "".join(lines))


def test_app_serves_the_page_and_stops_cleanly_on_ctrl_c(tmp_path):
    proc = _serve(tmp_path)
    try:
        url, lines = _wait_for_url(proc)
        assert url.startswith("http://127.0.0.1:")
        assert any("registered 300 main training starts" in line for line in lines)
        with urllib.request.urlopen(url, timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read(2000).lower()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert "stopping" in out and "Traceback" not in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k.db"]  # nothing else written


@pytest.mark.slow
def test_a_non_loopback_host_warns_that_anyone_can_label(tmp_path):
    proc = _serve(tmp_path, "--host", "0.0.0.0")
    try:
        _url, lines = _wait_for_url(proc)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(lines) + out
    assert "warning: serving on 0.0.0.0: anyone" in text
