"""Helpers and fixtures for tests/test_db_*.py: a throwaway PostgreSQL server, sample records.

Test modules import the fixtures they use (`pg_server`, `db_url`) from here.

`PostgresServer` runs Debian's PostgreSQL binaries (``/usr/lib/postgresql/*/bin``) in a temporary
directory on a free loopback port, as the unprivileged ``postgres`` user when we are root.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from knotlab.core.selection.labels import DeadEndState, LabelledExecution, LabelledStep

REQUIRE_ENV = "KNOTLAB_REQUIRE_POSTGRES"


def postgres_bindir() -> Path | None:
    """Directory of the newest installed PostgreSQL server binaries, or None."""
    found = sorted(
        glob.glob("/usr/lib/postgresql/*/bin/initdb"),
        key=lambda p: int(Path(p).parts[-3]) if Path(p).parts[-3].isdigit() else 0,
    )
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    return Path(initdb).parent if initdb else None


def postgres_required() -> bool:
    """Whether a missing PostgreSQL must fail the tests instead of skipping them (CI)."""
    return bool(os.environ.get(REQUIRE_ENV) or os.environ.get("CI"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresServer:
    """A private PostgreSQL cluster in a temporary directory; `stop()` removes everything."""

    def __init__(self, bindir: Path) -> None:
        self.bindir = bindir
        self.root = Path(tempfile.mkdtemp(prefix="knotlab-pg-"))
        self.port = 0
        self._user: str | None = None
        if os.geteuid() == 0:
            try:
                pwd.getpwnam("postgres")
                self._user = "postgres"
            except KeyError as exc:
                raise RuntimeError("running as root but there is no 'postgres' user") from exc
            shutil.chown(self.root, user="postgres")
        self.data = self.root / "data"
        self.sockets = self.root / "sock"
        self.sockets.mkdir()
        if self._user:
            shutil.chown(self.sockets, user="postgres")

    def _cmd(self, *args: str) -> list[str]:
        cmd = [str(self.bindir / args[0]), *args[1:]]
        return ["runuser", "-u", self._user, "--", *cmd] if self._user else cmd

    def start(self) -> None:
        """initdb, then start the server on a free port (retrying if the port is taken)."""
        subprocess.run(
            self._cmd(
                "initdb", "-D", str(self.data), "-U", "knotlab", "--auth=trust", "-E", "UTF8"
            ),
            check=True,
            capture_output=True,
            timeout=120,
        )
        last = ""
        for _ in range(5):
            self.port = _free_port()
            opts = (
                f"-p {self.port} -k {self.sockets} -c listen_addresses=127.0.0.1 "
                "-c fsync=off -c full_page_writes=off -c max_connections=60"
            )
            proc = subprocess.run(
                self._cmd(
                    "pg_ctl",
                    "start",
                    "-w",
                    "-t",
                    "60",
                    "-D",
                    str(self.data),
                    "-l",
                    str(self.root / "server.log"),
                    "-o",
                    opts,
                ),
                capture_output=True,
                text=True,
                timeout=90,
            )
            if proc.returncode == 0:
                return
            last = proc.stdout + proc.stderr
        raise RuntimeError(f"could not start PostgreSQL: {last}")

    def create_database(self) -> str:
        """A new empty database; returns its SQLAlchemy URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(
            f"host=127.0.0.1 port={self.port} user=knotlab dbname=postgres", autocommit=True
        ) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return f"postgresql+psycopg://knotlab@127.0.0.1:{self.port}/{name}"

    def stop(self) -> None:
        """Stop the server and delete its directory."""
        if self.data.exists():
            subprocess.run(
                self._cmd("pg_ctl", "stop", "-m", "immediate", "-w", "-D", str(self.data)),
                capture_output=True,
                timeout=60,
            )
        shutil.rmtree(self.root, ignore_errors=True)


def make_execution(
    key: str,
    *,
    labeller: str = "oracle",
    source: str = "oracle",
    n_steps: int = 3,
    n_points: int = 30,
    knot: bool = True,
    n_dead: int = 1,
    seed: int = 0,
) -> LabelledExecution:
    """A small valid execution with random clouds (deterministic in `seed`)."""
    rng = np.random.default_rng(seed)
    steps = []
    for i in range(n_steps):
        last = i == n_steps - 1
        steps.append(
            LabelledStep(
                step_index=i,
                cloud_n3=rng.normal(size=(n_points, 3)),
                chosen_demo=f"s{i:03d}-t{seed % 7}",
                outcome="knot" if (last and knot) else "progressed",
                rope_nodes_k3=rng.normal(size=(12, 3)),
                candidates=("s000-t0", "s001-t1", "s002-t2"),
                candidate_scores_c=rng.normal(size=3),
                model_version="m-test" if i % 2 else None,
            )
        )
    dead = tuple(DeadEndState(rng.normal(size=(n_points, 3))) for _ in range(n_dead))
    return LabelledExecution(
        execution_id=key,
        source=source,  # type: ignore[arg-type]
        labeller=labeller,
        steps=tuple(steps),
        ended_in_knot=knot and n_steps > 0,
        dead_ends=dead,
        task_id=f"task-{seed}",
        library_hash="lib-abc123",
        metadata={"seed": seed, "note": "test"},
    )


def cloud(seed: int, n: int = 30) -> np.ndarray:
    """A random (n, 3) cloud."""
    return np.random.default_rng(seed).normal(size=(n, 3))


# ----------------------------------------------------------------------------- fixtures

# Every PostgreSQL-backed test runs on one xdist worker, so one server serves them all.
PG_GROUP = pytest.mark.xdist_group("labeling_db_postgres")


@pytest.fixture(scope="session")
def pg_server() -> Iterator[PostgresServer]:
    """A throwaway PostgreSQL server for the whole test session (skipped if not installed)."""
    bindir = postgres_bindir()
    if bindir is None:
        reason = "PostgreSQL server binaries not installed (run scripts/install_system_deps.sh)"
        if postgres_required():
            pytest.fail(reason)
        pytest.skip(reason)
    server = PostgresServer(bindir)
    try:
        server.start()
    except Exception as exc:
        server.stop()
        if postgres_required():
            raise
        pytest.skip(f"could not start PostgreSQL: {exc}")
    yield server
    server.stop()


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=PG_GROUP)])
def db_url(request: pytest.FixtureRequest, tmp_path) -> str:
    """A URL of a fresh, empty database: a SQLite file in tmp_path, or a PostgreSQL database."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'labels.db'}"
    return request.getfixturevalue("pg_server").create_database()
