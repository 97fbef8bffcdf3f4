"""Engines from URLs, schema checks and migrations (SQLite file checks, WAL, busy timeouts)."""

from __future__ import annotations

import sqlite3
import struct
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import quote

from sqlalchemy import Connection, Engine, create_engine, event, inspect, text
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, NoSuchModuleError, OperationalError
from sqlalchemy.pool import NullPool, StaticPool

from knotlab.labeling_db.errors import (
    CorruptDatabaseError,
    DatabaseBusyError,
    DatabaseFailedError,
    DatabaseNotFoundError,
    DatabaseReadOnlyError,
    DatabaseUnavailableError,
    DatabaseUrlError,
    DatabaseWriteError,
    InMemoryDatabaseError,
    LabelingDbError,
    NotADatabaseError,
    SchemaOutdatedError,
    SchemaTooNewError,
)
from knotlab.labeling_db.models import (
    SCHEMA_REVISION,
)
from knotlab.labeling_db.records import SchemaState, SchemaStatus

DEFAULT_URL = "sqlite:///knotlab.db"
MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"
_SQLITE_MAGIC = b"SQLite format 3\x00"
_PG_MIGRATION_LOCK = 0x6B6E6F74  # "knot": serialises concurrent schema upgrades
if TYPE_CHECKING:
    from alembic.config import Config
    from alembic.script import ScriptDirectory


# ----------------------------------------------------------------------------- schema


# Alembic is imported only to migrate or to judge a database that is not at SCHEMA_REVISION:
# it costs ~0.5 s of start-up, paid by every labelling process otherwise.


@lru_cache(maxsize=1)
def _script() -> ScriptDirectory:
    from alembic.script import ScriptDirectory

    return ScriptDirectory.from_config(alembic_config())


def alembic_config(connection: Connection | None = None) -> Config:
    """An Alembic config for the packaged migrations, optionally bound to an open connection."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


def schema_head() -> str:
    """The newest schema revision this knotlab knows."""
    head = _script().get_current_head()
    assert head is not None, "labeling_db/migrations has no revisions"
    return head


def _status_of(conn: Connection, url_text: str) -> SchemaStatus:
    tables = tuple(
        sorted(t for t in inspect(conn).get_table_names() if not t.startswith("sqlite_"))
    )
    if "alembic_version" not in tables:
        state: SchemaState = "foreign" if tables else "empty"
        return SchemaStatus(url_text, state, None, SCHEMA_REVISION, tables)
    heads = tuple(conn.execute(text("SELECT version_num FROM alembic_version")).scalars())
    if heads == (SCHEMA_REVISION,):  # fast path: the revision these models describe
        return SchemaStatus(url_text, "current", SCHEMA_REVISION, SCHEMA_REVISION, tables)
    head = schema_head()
    if not heads:  # stamped at base: empty, unless unversioned tables sit beside it
        state = "foreign" if len(tables) > 1 else "empty"
        return SchemaStatus(url_text, state, None, head, tables)
    if len(heads) != 1:
        return SchemaStatus(url_text, "too_new", ",".join(heads) or None, head, tables)
    rev = heads[0]
    known = {r.revision for r in _script().walk_revisions()}
    if rev == head:
        state = "current"
    elif rev in known:
        state = "outdated"
    else:
        state = "too_new"
    return SchemaStatus(url_text, state, rev, head, tables)


def _raise_for(status: SchemaStatus, *, create: bool, auto_upgrade: bool) -> bool:
    """Raise if `status` cannot be opened with these options; True when a migration must run."""
    url = status.url
    if status.state == "current":
        return False
    if status.state == "foreign":
        shown = ", ".join(status.tables[:6]) + (", ..." if len(status.tables) > 6 else "")
        raise NotADatabaseError(
            f"{url}: not a knotlab labelling database (it has tables {shown} but no "
            f"alembic_version table); refusing to touch it"
        )
    if status.state == "too_new":
        raise SchemaTooNewError(
            f"{url}: schema revision {status.revision!r} is unknown to this knotlab (newest "
            f"known: {status.head!r}); it was written by a newer knotlab. Upgrade knotlab to "
            f"open it; the database was not changed"
        )
    if status.state == "empty":
        if not create:
            raise SchemaOutdatedError(
                f"{url}: database has no knotlab schema yet; run: knotlab db init --db {url}"
            )
        return True
    if not auto_upgrade:
        raise SchemaOutdatedError(
            f"{url}: schema revision {status.revision!r} is older than this knotlab's "
            f"{status.head!r}; run: knotlab db upgrade --db {url}"
        )
    return True


# ----------------------------------------------------------------------------- engines


def _url_text(url: URL) -> str:
    return url.render_as_string(hide_password=True)


def _sqlite_path(url: URL) -> Path | None:
    db = url.database
    if not db or db == ":memory:" or db.startswith("file:"):
        return None
    return Path(db).expanduser()


def _check_sqlite_file(path: Path) -> None:
    """Refuse a file that is not a whole SQLite database, reading it only."""
    if path.is_dir():
        raise NotADatabaseError(f"{path}: is a directory, not a database file")
    size = path.stat().st_size
    with open(path, "rb") as fh:
        header = fh.read(100)
    if len(header) < 100 or header[:16] != _SQLITE_MAGIC:
        raise NotADatabaseError(f"{path}: not an SQLite database (bad file header)")
    (page_size,) = struct.unpack(">H", header[16:18])
    page_size = 65536 if page_size == 1 else page_size
    if page_size < 512 or page_size & (page_size - 1):
        raise CorruptDatabaseError(f"{path}: corrupt header (page size {page_size})")
    wal = Path(str(path) + "-wal")
    wal_has_frames = wal.exists() and wal.stat().st_size > 0
    if size % page_size and not wal_has_frames:
        raise CorruptDatabaseError(
            f"{path}: truncated ({size} bytes is not a whole number of {page_size}-byte pages)"
        )
    change, n_pages = struct.unpack(">II", header[24:32])
    (valid_for,) = struct.unpack(">I", header[92:96])
    if change == valid_for and n_pages * page_size > size and not wal_has_frames:
        raise CorruptDatabaseError(
            f"{path}: truncated ({size} bytes on disk, the header says "
            f"{n_pages} pages of {page_size} bytes)"
        )


def _is_corruption(exc: BaseException | None) -> bool:
    msg = str(exc).lower()
    return any(s in msg for s in ("malformed", "not a database", "encrypted", "corrupt"))


# ----------------------------------------------------------------------------- database errors

# SQLite result codes (sqlite3 errors carry them as ``sqlite_errorname``) and PostgreSQL SQLSTATEs.
_PG_CONNECT_STATES = {"28000", "28P01", "3D000", "57P01", "57P02", "57P03"}  # + class 08
_CONNECT_WORDS = ("connection", "could not connect", "could not translate host", "timeout expired")


def _one_line(exc: BaseException | None, limit: int = 200) -> str:
    """A driver message in one line of at most ``limit`` characters."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[:limit] + "..."


def database_error(exc: DBAPIError, url_text: str) -> LabelingDbError | None:
    """The one-line error a database condition is reported as, naming the database (its
    password masked) and what to do; None for an error that is not a condition of the database
    (a constraint, a bug: the caller re-raises it)."""
    orig = exc.orig
    msg = str(orig).lower()
    code = str(getattr(orig, "sqlite_errorname", "") or "")
    state = str(getattr(orig, "sqlstate", "") or "")
    detail = _one_line(orig)
    if _is_corruption(orig) or code in ("SQLITE_CORRUPT", "SQLITE_NOTADB"):
        return CorruptDatabaseError(f"{url_text}: database is corrupt ({detail})")
    if code.startswith("SQLITE_READONLY") or "readonly database" in msg or state == "25006":
        return DatabaseReadOnlyError(
            f"{url_text}: the database is read-only ({detail}); nothing was written. Make the "
            "database file and its folder writable by this user, or give another --db"
        )
    if (
        code.startswith(("SQLITE_FULL", "SQLITE_IOERR"))
        or "disk is full" in msg
        or "no space left" in msg
        or state.startswith("53")
    ):
        return DatabaseWriteError(
            f"{url_text}: could not write the database ({detail}: a full disk, a file size "
            "limit or a failing disk); nothing was written. Free space and rerun"
        )
    if code.startswith("SQLITE_CANTOPEN") or "unable to open database file" in msg:
        return DatabaseUnavailableError(
            f"{url_text}: cannot open the database file ({detail}); check that its folder exists "
            "and that this user may read and write the file and its folder"
        )
    if code.startswith(("SQLITE_BUSY", "SQLITE_LOCKED")) or "database is locked" in msg:
        return DatabaseBusyError(
            f"{url_text}: the database is locked by another process ({detail}); nothing was "
            "written. Rerun when that process is done"
        )
    if (
        state.startswith("08")
        or state in _PG_CONNECT_STATES
        or exc.connection_invalidated
        or (
            isinstance(exc, OperationalError) and not code and any(w in msg for w in _CONNECT_WORDS)
        )
    ):
        return DatabaseUnavailableError(
            f"{url_text}: cannot connect to the database server ({detail}); check the host, "
            "port, user, password and database name in the URL, and that the server is running"
        )
    if isinstance(exc, OperationalError):
        return DatabaseFailedError(f"{url_text}: the database failed ({detail})")
    return None


def _open_error(exc: DBAPIError, url_text: str) -> LabelingDbError:
    """The one-line error of a database that could not be opened (or checked, or migrated)."""
    return database_error(exc, url_text) or DatabaseUnavailableError(
        f"{url_text}: cannot open the database ({_one_line(exc.orig)})"
    )


def is_in_memory(url: URL) -> bool:
    """Whether ``url`` is an SQLite database that lives in memory (``sqlite://``, ``:memory:``,
    ``file::memory:``, ``mode=memory``): it keeps nothing once the process ends."""
    if url.get_backend_name() != "sqlite":
        return False
    db = url.database or ""
    if db in ("", ":memory:"):
        return True
    return db.startswith("file:") and (
        db[5:].split("?")[0] in ("", ":memory:") or url.query.get("mode") == "memory"
    )


def _refuse_in_memory(url: URL, url_text: str) -> None:
    if is_in_memory(url):
        raise InMemoryDatabaseError(
            f"{url_text}: an in-memory database keeps nothing after this command; give a "
            f"database file (e.g. --db {DEFAULT_URL}) or a database server URL"
        )


def _readonly_sqlite_status(path: Path, url_text: str) -> SchemaStatus | None:
    """Integrity-check and read the schema revision through a read-only connection."""

    def connect() -> sqlite3.Connection:
        return sqlite3.connect(f"file:{quote(str(path))}?mode=ro", uri=True)

    aux = [Path(f"{path}{suffix}") for suffix in ("-wal", "-shm")]
    aux_before = [p.exists() for p in aux]
    engine = create_engine("sqlite://", creator=connect, poolclass=NullPool)
    try:
        with engine.connect() as conn:
            rows = conn.exec_driver_sql("PRAGMA quick_check(5)").scalars().all()
            if rows != ["ok"]:
                raise CorruptDatabaseError(
                    f"{path}: database is corrupt (integrity check: {'; '.join(map(str, rows))})"
                )
            return _status_of(conn, url_text)
    except DBAPIError as exc:
        if not _is_corruption(exc.orig):
            return None  # e.g. a hot journal a read-only connection may not replay: check later
        error = CorruptDatabaseError(f"{path}: database is corrupt ({exc.orig})")
        error.__cause__ = exc
    except CorruptDatabaseError as exc:
        error = exc
    finally:
        engine.dispose()
    # A WAL-mode file opened read-only leaves empty -wal/-shm files: remove the ones we made.
    if not aux_before[0] and aux[0].exists() and aux[0].stat().st_size == 0:
        for p, existed in zip(aux, aux_before, strict=True):
            if not existed:
                p.unlink(missing_ok=True)
    raise error


_URL_EXAMPLES = "sqlite:///knotlab.db or postgresql+psycopg://user@host/db"


def _server_engine(url: URL, *, echo: bool) -> Engine:
    """An engine for a database server; an unknown dialect or a missing driver names the URL."""
    text = _url_text(url)
    try:
        return create_engine(url, echo=echo, pool_pre_ping=True)
    except NoSuchModuleError as exc:
        raise DatabaseUrlError(
            f"{text}: unknown database dialect {url.drivername!r}; expected a URL like "
            f"{_URL_EXAMPLES}"
        ) from exc
    except ImportError as exc:
        raise DatabaseUrlError(
            f"{text}: the database driver for {url.drivername!r} is not installed "
            f"(No module named {exc.name!r}); install it or use a URL like {_URL_EXAMPLES}"
        ) from exc


def _make_engine(url: URL, *, busy_timeout_s: float, echo: bool) -> Engine:
    if url.get_backend_name() != "sqlite":
        return _server_engine(url, echo=echo)
    memory = _sqlite_path(url) is None
    engine = create_engine(
        url,
        echo=echo,
        poolclass=StaticPool if memory else None,
        connect_args={"check_same_thread": False} if memory else {},
    )

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: sqlite3.Connection, _record: object) -> None:
        dbapi_conn.isolation_level = None  # we issue BEGIN ourselves (see _on_begin)
        cur = dbapi_conn.cursor()
        cur.execute(f"PRAGMA busy_timeout = {int(busy_timeout_s * 1000)}")
        cur.execute("PRAGMA foreign_keys = ON")
        if not memory:
            cur.execute("PRAGMA journal_mode = WAL")
            cur.execute("PRAGMA synchronous = FULL")  # a committed label survives power loss
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Connection) -> None:
        write = conn.get_execution_options().get("knotlab_write", False)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")

    return engine


def _parse_url(url: str | URL) -> URL:
    try:
        return make_url(url)
    except ArgumentError as exc:
        raise DatabaseUrlError(
            f"{url!r} is not a database URL ({exc}); expected a URL like {_URL_EXAMPLES}"
        ) from exc


def _prepare(
    url: str | URL, *, create: bool, persistent: bool = False
) -> tuple[URL, str, SchemaStatus | None]:
    """Check a SQLite file before anything may write to it; returns a pre-read status if any.

    ``persistent``: refuse an in-memory database (what is stored must outlive the command)."""
    parsed = _parse_url(url)
    text = _url_text(parsed)
    if persistent:
        _refuse_in_memory(parsed, text)
    path = _sqlite_path(parsed) if parsed.get_backend_name() == "sqlite" else None
    if path is None:
        return parsed, text, None
    # A 0-byte file is an empty SQLite database (another process may be creating it right now):
    # it holds nothing to lose, so it is treated like a missing file.
    if not path.exists() or (path.is_file() and path.stat().st_size == 0):
        if not create:
            raise DatabaseNotFoundError(
                f"{path}: no such database (or an empty file); create it with: "
                f"knotlab db init --db {text}"
            )
        if not path.parent.is_dir():
            raise DatabaseNotFoundError(f"{path}: directory {path.parent} does not exist")
        return parsed, text, None
    _check_sqlite_file(path)
    return parsed, text, _readonly_sqlite_status(path, text)


def _upgrade(engine: Engine, url_text: str, revision: str, *, create: bool) -> SchemaStatus:
    """Migrate to `revision` inside one write transaction, re-reading the revision under lock."""
    with engine.connect() as conn:
        conn.execution_options(knotlab_write=True)
        with conn.begin():
            if conn.dialect.name == "postgresql":
                conn.exec_driver_sql(f"SELECT pg_advisory_xact_lock({_PG_MIGRATION_LOCK})")
            status = _status_of(conn, url_text)
            _raise_for(status, create=create, auto_upgrade=True)
            from alembic import command

            command.upgrade(alembic_config(conn), revision)
        return _status_of(conn, url_text)


def schema_status(url: str | URL = DEFAULT_URL) -> SchemaStatus:
    """Read a database's schema revision without changing it."""
    parsed, text, status = _prepare(url, create=False)
    if status is not None:
        return status
    engine = _make_engine(parsed, busy_timeout_s=10.0, echo=False)
    try:
        with engine.connect() as conn:
            return _status_of(conn, text)
    except DBAPIError as exc:
        raise _open_error(exc, text) from exc
    finally:
        engine.dispose()


def upgrade_database(
    url: str | URL = DEFAULT_URL,
    *,
    revision: str = "head",
    create: bool = True,
    persistent: bool = False,
) -> tuple[SchemaStatus, SchemaStatus]:
    """Create or migrate the schema (``alembic upgrade``); returns the status before and after.

    ``persistent``: refuse an in-memory database URL (a command's schema would vanish with it).
    """
    parsed, text, before = _prepare(url, create=create, persistent=persistent)
    if before is not None:
        _raise_for(before, create=create, auto_upgrade=True)
    engine = _make_engine(parsed, busy_timeout_s=30.0, echo=False)
    try:
        with engine.connect() as conn:
            first = before or _status_of(conn, text)
        _raise_for(first, create=create, auto_upgrade=True)
        after = _upgrade(engine, text, revision, create=create)
        return first, after
    except DBAPIError as exc:
        error = database_error(exc, text)
        if error is not None:
            raise error from exc
        raise LabelingDbError(
            f"{text}: migration failed, nothing changed ({_one_line(exc.orig)})"
        ) from exc
    finally:
        engine.dispose()
