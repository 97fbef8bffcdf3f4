"""Database conditions as sentences: read-only, unreachable, in memory, full, locked.

Each is one line naming the database (its password masked) and what to do, through the store and
through the command line (exit 2 for a database the user must fix, 1 when writing failed), and
the database is left as it was.
"""

from __future__ import annotations

import hashlib
import os
import resource
import signal
import socket
import sqlite3
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import pytest
from sqlalchemy.engine import make_url
from sqlalchemy.exc import IntegrityError, OperationalError

from knotlab.app import cli
from knotlab.labeling_db.engine import database_error, is_in_memory
from knotlab.labeling_db.errors import (
    CorruptDatabaseError,
    DatabaseBusyError,
    DatabaseFailedError,
    DatabaseReadOnlyError,
    DatabaseUnavailableError,
    DatabaseWriteError,
    InMemoryDatabaseError,
)
from knotlab.labeling_db.interchange import write_labels
from knotlab.labeling_db.store import StoredExecution, open_store, upgrade_database
from tests.db_fixtures import make_execution

URL = "postgresql+psycopg://knot:s3cret@db.example:5432/labels"


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _labels(path: Path, *keys: str, n_points: int = 20) -> Path:
    items = [
        StoredExecution(
            make_execution(key, n_points=n_points, seed=i),
            status="completed",
            started_at=datetime(2026, 1, 1, tzinfo=UTC),
        )
        for i, key in enumerate(keys)
    ]
    with open(path, "w", encoding="utf-8") as fh:
        write_labels(items, fh, "jsonl")
    return path


@pytest.fixture
def filled(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A knotlab database file holding one execution; the working directory is tmp_path."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("KNOTLAB_DB_URL", raising=False)
    monkeypatch.delenv(cli.DEBUG_ENV, raising=False)
    path = tmp_path / "k.db"
    with open_store(f"sqlite:///{path}") as store:
        store.add_execution(make_execution("already-here"))
    return path


def _one_line(argv: list[str], capsys: pytest.CaptureFixture[str], code: int, *words: str) -> str:
    capsys.readouterr()
    assert cli.main(argv) == code
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and "unexpected" not in err and "[SQL" not in err, err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


# ----------------------------------------------------------------------------- read-only


def _read_only_url(path: Path) -> str:
    # As root, chmod does not stop writes: SQLite's own read-only mode is the same condition.
    return f"sqlite:///file:{path}?mode=ro&uri=true"


def test_a_read_only_database_refuses_writes_in_one_line(filled: Path, capsys) -> None:
    digest = _sha(filled)
    with (
        open_store(_read_only_url(filled), create=False) as store,
        pytest.raises(DatabaseReadOnlyError, match="the database is read-only"),
    ):
        store.add_execution(make_execution("new"))
    labels = _labels(filled.parent / "in.jsonl", "new-0", "new-1")
    line = _one_line(
        ["labels", "import", str(labels), "--db", _read_only_url(filled)],
        capsys,
        2,
        "read-only",
        "nothing was written",
        "writable",
    )
    assert line.startswith("knotlab labels import: error: sqlite:///file")
    assert _sha(filled) == digest
    with open_store(f"sqlite:///{filled}") as store:
        assert [e.execution_id for e in store.training_executions()] == ["already-here"]


def test_label_oracle_into_a_read_only_database_is_one_line(filled: Path, capsys) -> None:
    digest = _sha(filled)
    argv = ["label", "--oracle", "--db", _read_only_url(filled), "--tasks", "1", "--workers", "1"]
    _one_line([*argv, "--no-progress"], capsys, 2, "read-only", "nothing was written")
    assert _sha(filled) == digest


@pytest.mark.skipif(
    os.geteuid() == 0, reason="root writes through file modes; the mode=ro test covers this"
)
def test_a_chmod_read_only_file_is_one_line(filled: Path, capsys) -> None:
    labels = _labels(filled.parent / "in.jsonl", "new-0")
    os.chmod(filled, 0o444)
    try:
        _one_line(["labels", "import", str(labels), "--db", f"sqlite:///{filled}"], capsys, 2)
    finally:
        os.chmod(filled, 0o644)


# ----------------------------------------------------------------------------- unreachable


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed again: nothing listens there


def test_a_refused_server_connection_is_one_line_with_the_password_masked(
    filled: Path, capsys
) -> None:
    url = f"postgresql+psycopg://knot:s3cret@127.0.0.1:{_closed_port()}/labels"
    labels = _labels(filled.parent / "in.jsonl", "new-0")
    for argv in (
        ["db", "stats", "--db", url],
        ["labels", "import", str(labels), "--db", url],
        ["labels", "export", "--db", url, "--out", "x.jsonl"],
    ):
        line = _one_line(argv, capsys, 2, "cannot connect to the database server", "knot:***@")
        assert "s3cret" not in line and "server is running" in line
    assert not (filled.parent / "x.jsonl").exists()


def test_an_sqlite_file_that_cannot_be_opened_is_one_line(tmp_path: Path) -> None:
    url = f"sqlite:///file:{tmp_path / 'none.db'}?mode=ro&uri=true"
    with pytest.raises(DatabaseUnavailableError, match="cannot open the database file"):
        open_store(url, create=False)


# ----------------------------------------------------------------------------- in memory


@pytest.mark.parametrize(
    "url", ["sqlite://", "sqlite:///:memory:", "sqlite:///file:x?mode=memory&uri=true"]
)
def test_an_in_memory_url_is_refused_by_commands_that_store(filled: Path, capsys, url: str) -> None:
    labels = _labels(filled.parent / "in.jsonl", "new-0")
    before = sorted(p.name for p in filled.parent.iterdir())
    _one_line(
        ["labels", "import", str(labels), "--db", url], capsys, 2, "in-memory", "keeps nothing"
    )
    _one_line(["db", "init", "--db", url], capsys, 2, "in-memory")
    argv = ["label", "--oracle", "--db", url, "--tasks", "1", "--no-progress"]
    _one_line(argv, capsys, 2, "in-memory")
    with pytest.raises(InMemoryDatabaseError):
        open_store(url, persistent=True)
    with pytest.raises(InMemoryDatabaseError):
        upgrade_database(url, persistent=True)
    with open_store(url) as store:  # a library caller may still use one on purpose
        store.add_execution(make_execution("in-memory"))
    assert sorted(p.name for p in filled.parent.iterdir()) == before  # no file made for it


def test_which_urls_are_in_memory() -> None:
    memory = ["sqlite://", "sqlite:///:memory:", "sqlite:///file::memory:?uri=true"]
    memory.append("sqlite:///file:shared?mode=memory&cache=shared&uri=true")
    for url in memory:
        assert is_in_memory(make_url(url)), url
    for url in ["sqlite:///k.db", "sqlite:///file:k.db?mode=ro&uri=true", URL]:
        assert not is_in_memory(make_url(url)), url


# ----------------------------------------------------------------------------- full disk


def _limit_file_size() -> None:  # in the child: SIGXFSZ ignored, so a write fails with EFBIG
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))


def test_a_full_disk_is_one_line_exit_1_and_nothing_is_stored(filled: Path) -> None:
    # A file size limit makes SQLite's writes fail as a full disk does (SQLITE_FULL on ENOSPC,
    # SQLITE_IOERR_WRITE on EFBIG): both are the same sentence.
    labels = _labels(filled.parent / "in.jsonl", "big-0", "big-1", n_points=4000)
    env = {k: v for k, v in os.environ.items() if k not in ("KNOTLAB_DB_URL", cli.DEBUG_ENV)}
    argv = ["labels", "import", str(labels), "--db", f"sqlite:///{filled}"]
    res = subprocess.run(
        [sys.executable, "-m", "knotlab.app.cli", *argv],
        preexec_fn=_limit_file_size,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert res.returncode == 1, res.stderr
    (line,) = res.stderr.splitlines()
    assert "could not write the database" in line and "nothing was written" in line, line
    with open_store(f"sqlite:///{filled}") as store:
        assert [e.execution_id for e in store.training_executions()] == ["already-here"]


# ----------------------------------------------------------------------------- classification


def _operational(message: str, **attrs: str) -> OperationalError:
    orig = sqlite3.OperationalError(message)
    for name, value in attrs.items():
        setattr(orig, name, value)
    return OperationalError("INSERT INTO labels VALUES (?)", {}, orig)


class _PgError(Exception):
    def __init__(self, message: str, sqlstate: str | None) -> None:
        super().__init__(message)
        self.sqlstate = sqlstate


@pytest.mark.parametrize(
    ("exc", "kind", "words"),
    [
        (_operational("attempt to write a readonly database"), DatabaseReadOnlyError, "read-only"),
        (
            _operational("database or disk is full", sqlite_errorname="SQLITE_FULL"),
            DatabaseWriteError,
            "a full disk",
        ),
        (
            _operational("disk I/O error", sqlite_errorname="SQLITE_IOERR_WRITE"),
            DatabaseWriteError,
            "file size limit",
        ),
        (_operational("unable to open database file"), DatabaseUnavailableError, "cannot open"),
        (_operational("database is locked"), DatabaseBusyError, "locked by another process"),
        (_operational("database disk image is malformed"), CorruptDatabaseError, "corrupt"),
        (
            OperationalError("x", {}, _PgError("could not extend file: No space left", "53100")),
            DatabaseWriteError,
            "Free space",
        ),
        (
            OperationalError("x", {}, _PgError("connection failed:\n\tIs it running?", None)),
            DatabaseUnavailableError,
            "connection failed: Is it running?",
        ),
        (
            OperationalError("x", {}, _PgError('database "labels" does not exist', "3D000")),
            DatabaseUnavailableError,
            "database name",
        ),
        (
            OperationalError("x", {}, _PgError("read-only transaction", "25006")),
            DatabaseReadOnlyError,
            "read-only",
        ),
        (_operational("something odd\nhappened"), DatabaseFailedError, "something odd happened"),
    ],
)
def test_database_conditions_become_one_sentence(exc, kind, words) -> None:
    error = database_error(exc, "postgresql+psycopg://knot:***@db.example:5432/labels")
    assert isinstance(error, kind)
    text = str(error)
    assert "\n" not in text and words in text and text.startswith("postgresql+psycopg://knot:***@")
    assert "[SQL" not in text and "INSERT" not in text
    failed_run = (DatabaseWriteError, DatabaseFailedError, DatabaseBusyError)
    assert kind.exit_code == (1 if kind in failed_run else 2)


def test_a_constraint_is_not_a_database_condition() -> None:
    exc = IntegrityError("INSERT", {}, sqlite3.IntegrityError("UNIQUE constraint failed"))
    assert database_error(exc, "sqlite:///k.db") is None
