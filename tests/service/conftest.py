"""A real `knotlab serve` process on a free loopback port, for the service's HTTP tests."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

URL = re.compile(r"knotlab serve: (http://\S+/v1)")


@dataclass
class Served:
    """A running service: its base URL (…/v1) and process."""

    url: str
    process: subprocess.Popen
    token: str | None = None
    printed: str = ""  # what it printed up to the URL


def start_service(*args: str, token: str | None = None, timeout: float = 120) -> Served:
    """Start `knotlab serve --port 0 ARGS` and wait for the URL it announces."""
    env = dict(os.environ)
    env.pop("KNOTLAB_TOKEN", None)
    if token is not None:
        env["KNOTLAB_TOKEN"] = token
    proc = subprocess.Popen(
        [sys.executable, "-m", "knotlab.app.cli", "serve", "--port", "0", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + timeout
    lines = []
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if (m := URL.search(line)) is not None:
            return Served(m.group(1), proc, token, "".join(lines))
    proc.kill()
    raise AssertionError("knotlab serve did not start:\n" + "".join(lines))


def stop_service(served: Served) -> float:
    """Ctrl-C the service; the seconds it took to exit."""
    t0 = time.monotonic()
    served.process.send_signal(signal.SIGINT)
    try:
        served.process.wait(timeout=15)
    except subprocess.TimeoutExpired:
        served.process.kill()
        raise
    return time.monotonic() - t0


@pytest.fixture(scope="module")
def service() -> Iterator[Served]:
    served = start_service("--workers", "2")
    yield served
    stop_service(served)
