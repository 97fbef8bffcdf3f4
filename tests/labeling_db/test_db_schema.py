"""Schema versions (Alembic) and damaged files: each refused with a clear error, file unchanged."""

from __future__ import annotations

import hashlib
import sqlite3
import threading
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import create_engine, text

from knotlab.core.errors import CorruptFileError, KnotlabError
from knotlab.labeling_db.errors import (
    CorruptDatabaseError,
    DatabaseNotFoundError,
    NotADatabaseError,
    SchemaOutdatedError,
    SchemaTooNewError,
)
from knotlab.labeling_db.models import SCHEMA_REVISION, Base
from knotlab.labeling_db.store import open_store, schema_head, schema_status, upgrade_database
from tests.db_fixtures import make_execution

# One plugin registration, so the session-scoped PostgreSQL server is started once.


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def filled_db(tmp_path: Path) -> Path:
    """A closed SQLite labelling database holding a few executions."""
    path = tmp_path / "labels.db"
    with open_store(f"sqlite:///{path}") as store:
        store.add_executions([make_execution(f"ex-{i}", seed=i, n_points=60) for i in range(30)])
    assert not Path(f"{path}-wal").exists()  # closing checkpointed the WAL
    return path


def test_migrations_build_exactly_the_models(db_url: str) -> None:
    upgrade_database(db_url)
    engine = create_engine(db_url)
    try:
        with engine.connect() as conn:
            diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    finally:
        engine.dispose()
    assert diff == []


def test_the_models_name_the_newest_migration() -> None:
    assert schema_head() == SCHEMA_REVISION


def test_an_older_schema_is_migrated_keeping_its_data(db_url: str) -> None:
    before, after = upgrade_database(db_url, revision="0001")
    assert (before.state, after.revision) == ("empty", "0001")
    engine = create_engine(db_url)
    with engine.begin() as conn:
        conn.execute(
            text("INSERT INTO labellers (name, kind, created_at) VALUES ('old', 'human', :t)"),
            {"t": "2024-01-01 00:00:00"},
        )
    engine.dispose()
    with pytest.raises(SchemaOutdatedError, match="knotlab db upgrade --db "):
        open_store(db_url, auto_upgrade=False)
    assert schema_status(db_url).revision == "0001"  # refusing changed nothing
    with open_store(db_url) as store:
        assert store.schema_status().revision == schema_head()
        assert store.labellers() == ["old"]


def test_a_newer_schema_is_refused(db_url: str, tmp_path: Path) -> None:
    upgrade_database(db_url)
    engine = create_engine(db_url)
    with engine.begin() as conn:
        conn.execute(text("UPDATE alembic_version SET version_num = '9999_future'"))
    engine.dispose()
    path = Path(db_url.removeprefix("sqlite:///")) if db_url.startswith("sqlite") else None
    digest = _sha(path) if path else None
    with pytest.raises(SchemaTooNewError, match="'9999_future' is unknown.*newer knotlab"):
        open_store(db_url)
    with pytest.raises(SchemaTooNewError):
        upgrade_database(db_url)
    if path:
        assert _sha(path) == digest


def test_upgrade_database_reports_empty_databases(tmp_path: Path) -> None:
    path = tmp_path / "new.db"
    with pytest.raises(DatabaseNotFoundError, match="knotlab db init"):
        open_store(f"sqlite:///{path}", create=False)
    assert not path.exists()
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE alembic_version (version_num VARCHAR(32) PRIMARY KEY)")
    con.close()
    with pytest.raises(SchemaOutdatedError, match="no knotlab schema yet; run: knotlab db init"):
        open_store(f"sqlite:///{path}", create=False)
    assert schema_status(f"sqlite:///{path}").state == "empty"
    with open_store(f"sqlite:///{path}", auto_upgrade=False) as store:  # create=True: init
        assert store.schema_status().revision == schema_head()


def test_concurrent_first_opens_initialise_once(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'fresh.db'}"
    errors: list[BaseException] = []

    def opener() -> None:
        try:
            open_store(url).close()
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=opener) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert schema_status(url).revision == schema_head()


def test_a_foreign_database_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "other.db"
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE invoices (id INTEGER PRIMARY KEY)")
    con.commit()
    con.close()
    digest = _sha(path)
    with pytest.raises(NotADatabaseError, match="not a knotlab labelling database.*invoices"):
        open_store(f"sqlite:///{path}")
    assert _sha(path) == digest


def _truncate_half_pages(path: Path) -> None:
    size = path.stat().st_size
    with open(path, "r+b") as fh:
        fh.truncate((size // 2) // 4096 * 4096)


def _truncate_mid_page(path: Path) -> None:
    with open(path, "r+b") as fh:
        fh.truncate(path.stat().st_size - 1000)


def _scribble_middle(path: Path) -> None:
    data = bytearray(path.read_bytes())
    mid = (len(data) // 2) // 4096 * 4096
    data[mid : mid + 4096] = b"\xff" * 4096
    path.write_bytes(bytes(data))


def _scribble_header(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[0:16] = b"Not SQLite here!"
    path.write_bytes(bytes(data))


def _text_file(path: Path) -> None:
    path.write_text("execution_id,labeller\nex-1,alice\n" * 200)


@pytest.mark.parametrize(
    ("damage", "error", "message"),
    [
        (_truncate_half_pages, CorruptDatabaseError, "truncated"),
        (_truncate_mid_page, CorruptDatabaseError, "truncated"),
        (_scribble_middle, CorruptDatabaseError, "corrupt"),
        (_scribble_header, NotADatabaseError, "not an SQLite database"),
        (_text_file, NotADatabaseError, "not an SQLite database"),
    ],
)
def test_a_damaged_file_gives_a_clear_error_and_is_left_unchanged(
    filled_db: Path, damage, error: type[Exception], message: str
) -> None:
    damage(filled_db)
    digest = _sha(filled_db)
    url = f"sqlite:///{filled_db}"
    for attempt in (
        lambda: open_store(url),
        lambda: upgrade_database(url),
        lambda: schema_status(url),
    ):
        with pytest.raises(error, match=message) as info:
            attempt()
        assert str(filled_db) in str(info.value)
        assert isinstance(info.value, KnotlabError) and isinstance(info.value, CorruptFileError)
    assert _sha(filled_db) == digest
    assert not Path(f"{filled_db}-wal").exists()


def test_an_empty_file_is_a_new_database_only_when_creating(tmp_path: Path) -> None:
    path = tmp_path / "empty.db"
    path.write_bytes(b"")  # what SQLite itself leaves while another process creates the file
    with pytest.raises(DatabaseNotFoundError, match="empty file"):
        open_store(f"sqlite:///{path}", create=False)
    assert path.stat().st_size == 0
    with open_store(f"sqlite:///{path}") as store:
        assert store.schema_status().revision == schema_head()
