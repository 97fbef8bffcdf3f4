"""The labelling store: engine from a URL, schema checks and migrations, and the app's queries.

`open_store(url)` gives a :class:`Store`. Every public method is one unit of work: one session,
one explicit transaction, committed before it returns. Writes on SQLite take the write lock up
front (``BEGIN IMMEDIATE``) and are retried with bounded, jittered backoff while the database is
locked; on PostgreSQL, serialisation failures and deadlocks are retried the same way.
Only plain records (``core.labels`` dataclasses and the dataclasses below) leave this module.
Shape suffixes: n = cloud points, k = rope nodes, c = candidates shown.
"""

from __future__ import annotations

import json
import random
import sqlite3
import struct
import time
import uuid
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar
from urllib.parse import quote

import numpy as np
from sqlalchemy import Connection, Engine, create_engine, event, func, inspect, select, text
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, IntegrityError
from sqlalchemy.orm import Session
from sqlalchemy.pool import NullPool, StaticPool

from core.errors import InvalidInputError
from core.labels import OUTCOMES, DeadEndState, LabelledExecution, LabelledStep
from labeling_db.arrays import decode_array, encode_array
from labeling_db.errors import (
    ConflictError,
    CorruptDatabaseError,
    DatabaseBusyError,
    DatabaseNotFoundError,
    InvalidRecordError,
    LabelingDbError,
    NotADatabaseError,
    RecordNotFoundError,
    SchemaOutdatedError,
    SchemaTooNewError,
)
from labeling_db.models import (
    EPISODE_STATUSES,
    SCHEMA_REVISION,
    DeadEnd,
    DemoLibrary,
    Episode,
    Label,
    Labeller,
    ModelArray,
    ModelTrainingLabel,
    RopeState,
    TrainedModel,
    utcnow,
)

DEFAULT_URL = "sqlite:///knotlab.db"
MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"
_SQLITE_MAGIC = b"SQLite format 3\x00"
_PG_MIGRATION_LOCK = 0x6B6E6F74  # "knot": serialises concurrent schema upgrades
_PG_CLAIM_LOCK = 0x6B6E6F75  # serialises claiming the next unlabelled start state
_MAX_KEY = 200
if TYPE_CHECKING:
    from alembic.config import Config
    from alembic.script import ScriptDirectory

_RETRY_SQLSTATES = {"40001", "40P01", "55P03"}  # serialization failure, deadlock, lock n/a
T = TypeVar("T")

SchemaState = Literal["empty", "current", "outdated", "too_new", "foreign"]


# ----------------------------------------------------------------------------- records


@dataclass(frozen=True)
class StateProvenance:
    """Where a rope state came from: task id, step within its episode, and the sampling seed."""

    task_id: str | None = None
    episode_step: int | None = None
    seed: int | None = None


@dataclass(frozen=True, eq=False)
class StateRecord:
    """A stored rope state."""

    state_id: int
    role: str
    cloud_n3: np.ndarray
    rope_nodes_k3: np.ndarray | None
    provenance: StateProvenance
    created_at: datetime


@dataclass(frozen=True)
class EpisodeInfo:
    """A labelling episode's bookkeeping (no arrays)."""

    episode_id: int
    execution_id: str
    labeller: str
    source: str
    status: str
    start_state_id: int | None
    n_labels: int
    ended_in_knot: bool
    started_at: datetime
    finished_at: datetime | None


@dataclass(frozen=True)
class LabelInfo:
    """One stored label's bookkeeping (no arrays)."""

    label_id: int
    episode_id: int
    execution_id: str
    labeller: str
    step_index: int
    state_id: int
    chosen_demo: str
    outcome: str
    source: str
    labelled_at: datetime


@dataclass(frozen=True)
class LabellerProgress:
    """How far one labeller has got."""

    labeller: str
    labels: int
    outcomes: dict[str, int]
    episodes_in_progress: int
    episodes_completed: int
    episodes_abandoned: int
    knots: int
    dead_ends: int
    last_label_at: datetime | None
    start_states_remaining: int


@dataclass(frozen=True)
class ModelInfo:
    """A trained model's description (no arrays)."""

    version: str
    created_at: datetime
    library_hash: str | None
    hyperparameters: dict[str, Any]
    feature_spec: dict[str, Any]
    params: dict[str, Any]
    metrics: dict[str, Any]
    n_training_labels: int


@dataclass(frozen=True, eq=False)
class ModelRecord:
    """A trained model with its arrays (float64), ready to rebuild a `core.learn.QModel`."""

    info: ModelInfo
    arrays: dict[str, np.ndarray]


@dataclass(frozen=True, eq=False)
class StoredExecution:
    """A `LabelledExecution` plus what the store keeps around it (status, times, provenance).

    Empty `labelled_at` / provenance tuples mean "now" / "derived from the execution".
    """

    execution: LabelledExecution
    status: str = "completed"
    started_at: datetime | None = None
    finished_at: datetime | None = None
    labelled_at: tuple[datetime, ...] = ()
    step_provenance: tuple[StateProvenance, ...] = ()
    dead_end_provenance: tuple[StateProvenance, ...] = ()

    def __post_init__(self) -> None:
        ex = self.execution
        if not isinstance(ex, LabelledExecution):
            raise InvalidRecordError(f"execution must be a LabelledExecution, got {type(ex)}")
        if self.status not in EPISODE_STATUSES:
            raise InvalidRecordError(
                f"execution {ex.execution_id!r}: status must be one of {EPISODE_STATUSES}, "
                f"got {self.status!r}"
            )
        for name, seq, n in (
            ("labelled_at", self.labelled_at, len(ex.steps)),
            ("step_provenance", self.step_provenance, len(ex.steps)),
            ("dead_end_provenance", self.dead_end_provenance, len(ex.dead_ends)),
        ):
            if seq and len(seq) != n:
                raise InvalidRecordError(
                    f"execution {ex.execution_id!r}: {name} has {len(seq)} entries, expected {n}"
                )
        object.__setattr__(self, "labelled_at", tuple(self.labelled_at))
        object.__setattr__(self, "step_provenance", tuple(self.step_provenance))
        object.__setattr__(self, "dead_end_provenance", tuple(self.dead_end_provenance))


@dataclass(frozen=True)
class SchemaStatus:
    """Which schema revision a database is at, compared with this knotlab's newest."""

    url: str
    state: SchemaState
    revision: str | None
    head: str
    tables: tuple[str, ...] = field(default=())


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
                f"{url}: database has no knotlab schema yet; run: knotlab db init --url {url}"
            )
        return True
    if not auto_upgrade:
        raise SchemaOutdatedError(
            f"{url}: schema revision {status.revision!r} is older than this knotlab's "
            f"{status.head!r}; run: knotlab db upgrade --url {url}"
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


def _is_corruption(exc: BaseException) -> bool:
    msg = str(exc).lower()
    return any(s in msg for s in ("malformed", "not a database", "encrypted", "corrupt"))


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


def _make_engine(url: URL, *, busy_timeout_s: float, echo: bool) -> Engine:
    if url.get_backend_name() != "sqlite":
        return create_engine(url, echo=echo, pool_pre_ping=True)
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
        raise LabelingDbError(f"{url!r} is not a database URL ({exc})") from exc


def _prepare(url: str | URL, *, create: bool) -> tuple[URL, str, SchemaStatus | None]:
    """Check a SQLite file before anything may write to it; returns a pre-read status if any."""
    parsed = _parse_url(url)
    text = _url_text(parsed)
    path = _sqlite_path(parsed) if parsed.get_backend_name() == "sqlite" else None
    if path is None:
        return parsed, text, None
    # A 0-byte file is an empty SQLite database (another process may be creating it right now):
    # it holds nothing to lose, so it is treated like a missing file.
    if not path.exists() or (path.is_file() and path.stat().st_size == 0):
        if not create:
            raise DatabaseNotFoundError(
                f"{path}: no such database (or an empty file); create it with: "
                f"knotlab db init --url {text}"
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
    finally:
        engine.dispose()


def upgrade_database(
    url: str | URL = DEFAULT_URL, *, revision: str = "head", create: bool = True
) -> tuple[SchemaStatus, SchemaStatus]:
    """Create or migrate the schema (``alembic upgrade``); returns the status before and after."""
    parsed, text, before = _prepare(url, create=create)
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
        raise LabelingDbError(f"{text}: migration failed, nothing changed ({exc.orig})") from exc
    finally:
        engine.dispose()


def open_store(
    url: str | URL = DEFAULT_URL,
    *,
    create: bool = True,
    auto_upgrade: bool = True,
    busy_timeout_s: float = 10.0,
    max_attempts: int = 8,
    echo: bool = False,
) -> Store:
    """Open (and, if allowed, create or migrate) the labelling database at `url`."""
    parsed, text, status = _prepare(url, create=create)
    if status is not None:
        _raise_for(status, create=create, auto_upgrade=auto_upgrade)
    engine = _make_engine(parsed, busy_timeout_s=busy_timeout_s, echo=echo)
    try:
        with engine.connect() as conn:
            status = _status_of(conn, text)
        if _raise_for(status, create=create, auto_upgrade=auto_upgrade):
            _upgrade(engine, text, "head", create=create)
    except DBAPIError as exc:
        engine.dispose()
        if _is_corruption(exc.orig):
            raise CorruptDatabaseError(f"{text}: database is corrupt ({exc.orig})") from exc
        raise LabelingDbError(f"{text}: cannot open the database ({exc.orig})") from exc
    except BaseException:
        engine.dispose()
        raise
    return Store(engine, text, max_attempts=max_attempts)


# ----------------------------------------------------------------------------- helpers


def _check_key(what: str, value: object, *, optional: bool = False, limit: int = _MAX_KEY) -> None:
    if value is None and optional:
        return
    if not isinstance(value, str) or not value or len(value) > limit:
        raise InvalidRecordError(f"{what} must be a non-empty string of at most {limit} chars")


def _check_json(what: str, value: object) -> None:
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InvalidRecordError(f"{what} must be JSON-serialisable without NaN ({exc})") from exc


def _insert_ignore(session: Session, model: type, values: dict[str, Any], key: str) -> None:
    dialect = session.get_bind().dialect.name
    if dialect == "sqlite":
        from sqlalchemy.dialects.sqlite import insert
    elif dialect == "postgresql":
        from sqlalchemy.dialects.postgresql import insert
    else:  # pragma: no cover - only SQLite and PostgreSQL are supported
        exists = session.scalar(
            select(getattr(model, key)).where(getattr(model, key) == values[key])
        )
        if exists is None:
            session.add(model(**values))
            session.flush()
        return
    session.execute(insert(model).values(**values).on_conflict_do_nothing(index_elements=[key]))


def _labeller_id(session: Session, name: str, kind: str) -> int:
    _insert_ignore(session, Labeller, {"name": name, "kind": kind, "created_at": utcnow()}, "name")
    return session.scalars(select(Labeller.id).where(Labeller.name == name)).one()


def _library_id(session: Session, library_hash: str | None) -> int | None:
    if library_hash is None:
        return None
    _insert_ignore(
        session,
        DemoLibrary,
        {"library_hash": library_hash, "created_at": utcnow()},
        "library_hash",
    )
    return session.scalars(
        select(DemoLibrary.id).where(DemoLibrary.library_hash == library_hash)
    ).one()


def _new_state(
    role: str, cloud_n3: np.ndarray, rope_nodes_k3: np.ndarray | None, prov: StateProvenance
) -> RopeState:
    if prov.seed is not None and not (isinstance(prov.seed, int) and -(2**31) <= prov.seed < 2**31):
        raise InvalidRecordError(f"seed must be a 32-bit integer, got {prov.seed!r}")
    return RopeState(
        role=role,
        cloud=encode_array(cloud_n3, name="cloud_n3"),
        rope_nodes=None if rope_nodes_k3 is None else encode_array(rope_nodes_k3, name="rope"),
        task_id=prov.task_id,
        episode_step=prov.episode_step,
        seed=prov.seed,
        created_at=utcnow(),
    )


def _state_record(row: RopeState) -> StateRecord:
    where = f"rope_states.id={row.id}"
    return StateRecord(
        state_id=row.id,
        role=row.role,
        cloud_n3=decode_array(row.cloud, where=f"{where} cloud"),
        rope_nodes_k3=None
        if row.rope_nodes is None
        else decode_array(row.rope_nodes, where=f"{where} rope_nodes"),
        provenance=StateProvenance(row.task_id, row.episode_step, row.seed),
        created_at=row.created_at,
    )


def _episode_info(session: Session, ep: Episode) -> EpisodeInfo:
    n = session.scalar(select(func.count()).select_from(Label).where(Label.episode_id == ep.id))
    return EpisodeInfo(
        episode_id=ep.id,
        execution_id=ep.execution_key,
        labeller=ep.labeller.name,
        source=ep.source,
        status=ep.status,
        start_state_id=ep.start_state_id,
        n_labels=int(n or 0),
        ended_in_knot=ep.ended_in_knot,
        started_at=ep.started_at,
        finished_at=ep.finished_at,
    )


def _label_info(label: Label, ep: Episode, labeller: str) -> LabelInfo:
    return LabelInfo(
        label_id=label.id,
        episode_id=ep.id,
        execution_id=ep.execution_key,
        labeller=labeller,
        step_index=label.step_index,
        state_id=label.state_id,
        chosen_demo=label.chosen_demo,
        outcome=label.outcome,
        source=label.source,
        labelled_at=label.labelled_at,
    )


def _unlabelled_start_states():
    taken = (
        select(Episode.id)
        .where(Episode.start_state_id == RopeState.id, Episode.status != "abandoned")
        .exists()
    )
    return select(RopeState).where(RopeState.role == "start", ~taken)


# ----------------------------------------------------------------------------- the store


class Store:
    """The labelling database. Every method runs as its own committed transaction."""

    def __init__(self, engine: Engine, url_text: str, *, max_attempts: int = 8) -> None:
        self._engine = engine
        self.url = url_text
        self.dialect = engine.dialect.name
        self._max_attempts = max(1, max_attempts)

    # --- plumbing

    def close(self) -> None:
        """Close every pooled connection (a SQLite WAL file is checkpointed by the last one)."""
        self._engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Store({self.url!r})"

    def _retryable(self, exc: DBAPIError) -> bool:
        orig = exc.orig
        if isinstance(orig, sqlite3.OperationalError):
            msg = str(orig).lower()
            return "locked" in msg or "busy" in msg
        return getattr(orig, "sqlstate", None) in _RETRY_SQLSTATES

    def _run(self, fn: Callable[[Session], T], *, write: bool) -> T:
        """Run `fn(session)` in one transaction, retrying the whole unit while the DB is busy."""
        delay = 0.02
        for attempt in range(1, self._max_attempts + 1):
            try:
                with self._engine.connect() as conn:
                    conn.execution_options(knotlab_write=write)
                    with Session(bind=conn, expire_on_commit=False) as session:
                        with session.begin():
                            result = fn(session)
                        return result
            except DBAPIError as exc:
                if _is_corruption(exc.orig):
                    raise CorruptDatabaseError(
                        f"{self.url}: database is corrupt ({exc.orig})"
                    ) from exc
                if not self._retryable(exc):
                    raise
                if attempt == self._max_attempts:
                    raise DatabaseBusyError(
                        f"{self.url}: database stayed locked through {attempt} attempts "
                        f"({exc.orig}); nothing was written"
                    ) from exc
                time.sleep(delay * random.uniform(0.5, 1.5))
                delay = min(delay * 2, 1.0)
        raise AssertionError("unreachable")  # pragma: no cover

    @contextmanager
    def _conflicts(self, what: str) -> Iterator[None]:
        try:
            yield
        except IntegrityError as exc:
            raise ConflictError(f"{self.url}: {what} ({exc.orig})") from exc

    def schema_status(self) -> SchemaStatus:
        """The schema revision of this database."""
        with self._engine.connect() as conn:
            return _status_of(conn, self.url)

    # --- labellers, libraries, states

    def add_labeller(self, name: str, kind: Literal["human", "oracle"] = "human") -> None:
        """Register a labeller (no-op if the name exists)."""
        _check_key("labeller name", name)
        if kind not in ("human", "oracle"):
            raise InvalidRecordError(f"labeller kind must be 'human' or 'oracle', got {kind!r}")
        self._run(lambda s: _labeller_id(s, name, kind), write=True)

    def labellers(self) -> list[str]:
        """Names of every labeller, in order of registration."""
        return self._run(
            lambda s: list(s.scalars(select(Labeller.name).order_by(Labeller.id))), write=False
        )

    def register_library(
        self, library_hash: str, *, name: str | None = None, demo_keys: Sequence[str] | None = None
    ) -> None:
        """Record a demo library by its hash (fills in name and keys if not yet known)."""
        _check_key("library_hash", library_hash, limit=128)

        def work(s: Session) -> None:
            lib = s.get(DemoLibrary, _library_id(s, library_hash))
            assert lib is not None
            if name is not None:
                lib.name = name
            if demo_keys is not None:
                lib.demo_keys = list(demo_keys)

        self._run(work, write=True)

    def add_start_states(
        self,
        clouds_n3: Sequence[np.ndarray],
        *,
        rope_nodes_k3: Sequence[np.ndarray | None] | None = None,
        provenance: Sequence[StateProvenance] | None = None,
    ) -> list[int]:
        """Queue rope states for labelling (one transaction); returns their ids."""
        n = len(clouds_n3)
        nodes = list(rope_nodes_k3) if rope_nodes_k3 is not None else [None] * n
        provs = list(provenance) if provenance is not None else [StateProvenance()] * n
        if len(nodes) != n or len(provs) != n:
            raise InvalidRecordError("clouds, rope nodes and provenance must have equal lengths")
        rows = []
        for i, (cloud, node, prov) in enumerate(zip(clouds_n3, nodes, provs, strict=True)):
            try:
                checked = DeadEndState(cloud, node)  # reuses core's (n, 3) validation
            except InvalidInputError as exc:
                raise InvalidRecordError(f"start state {i}: {exc}") from exc
            rows.append(_new_state("start", checked.cloud_n3, checked.rope_nodes_k3, prov))

        def work(s: Session) -> list[int]:
            s.add_all(rows)
            s.flush()
            return [r.id for r in rows]

        return self._run(work, write=True)

    def get_state(self, state_id: int) -> StateRecord:
        """One rope state by id."""

        def work(s: Session) -> StateRecord:
            row = s.get(RopeState, state_id)
            if row is None:
                raise RecordNotFoundError(f"{self.url}: no rope state with id {state_id}")
            return _state_record(row)

        return self._run(work, write=False)

    def next_unlabelled_state(self) -> StateRecord | None:
        """The oldest queued start state no live episode has claimed (does not claim it)."""

        def work(s: Session) -> StateRecord | None:
            row = s.scalars(_unlabelled_start_states().order_by(RopeState.id).limit(1)).first()
            return None if row is None else _state_record(row)

        return self._run(work, write=False)

    # --- human labelling, one step at a time

    def start_episode(
        self,
        labeller: str,
        *,
        state_id: int | None = None,
        execution_id: str | None = None,
        source: Literal["human", "oracle"] = "human",
        task_id: str | None = None,
        library_hash: str | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> EpisodeInfo | None:
        """Start an episode on `state_id`, or claim the next unlabelled start state (None: none)."""
        _check_key("labeller", labeller)
        _check_key("execution_id", execution_id, optional=True)
        _check_key("task_id", task_id, optional=True)
        _check_key("library_hash", library_hash, optional=True, limit=128)
        meta = dict(metadata or {})
        _check_json("metadata", meta)
        key = execution_id or f"{labeller}-{uuid.uuid4().hex[:16]}"

        def work(s: Session) -> EpisodeInfo | None:
            lid = _labeller_id(s, labeller, source)
            if state_id is None:
                if s.get_bind().dialect.name == "postgresql":
                    s.execute(select(func.pg_advisory_xact_lock(_PG_CLAIM_LOCK)))
                sid = s.scalars(
                    select(RopeState.id)
                    .where(
                        RopeState.id.in_(_unlabelled_start_states().with_only_columns(RopeState.id))
                    )
                    .order_by(RopeState.id)
                    .limit(1)
                ).first()
                if sid is None:
                    return None
            else:
                if s.get(RopeState, state_id) is None:
                    raise RecordNotFoundError(f"{self.url}: no rope state with id {state_id}")
                sid = state_id
            ep = Episode(
                execution_key=key,
                start_state_id=sid,
                labeller_id=lid,
                library_id=_library_id(s, library_hash),
                source=source,
                status="in_progress",
                ended_in_knot=False,
                task_id=task_id,
                meta=meta,
                started_at=utcnow(),
            )
            s.add(ep)
            with self._conflicts(f"execution id {key!r} already exists"):
                s.flush()
            return _episode_info(s, ep)

        return self._run(work, write=True)

    def _locked_episode(self, s: Session, episode_id: int) -> Episode:
        ep = s.scalars(select(Episode).where(Episode.id == episode_id).with_for_update()).first()
        if ep is None:
            raise RecordNotFoundError(f"{self.url}: no episode with id {episode_id}")
        return ep

    def add_label(
        self,
        episode_id: int,
        step: LabelledStep,
        *,
        state_id: int | None = None,
        provenance: StateProvenance | None = None,
        labelled_at: datetime | None = None,
    ) -> LabelInfo:
        """Append the next step's label to an in-progress episode (step 0 uses the start state)."""
        if not isinstance(step, LabelledStep):
            raise InvalidRecordError(f"step must be a LabelledStep, got {type(step)}")
        _check_key("chosen_demo", step.chosen_demo)
        _check_key("model_version", step.model_version, optional=True)

        def work(s: Session) -> LabelInfo:
            ep = self._locked_episode(s, episode_id)
            if ep.status != "in_progress":
                raise ConflictError(
                    f"{self.url}: episode {episode_id} is {ep.status}; "
                    "only in-progress episodes take labels"
                )
            n = s.scalar(select(func.count()).select_from(Label).where(Label.episode_id == ep.id))
            if step.step_index != n:
                raise ConflictError(
                    f"{self.url}: episode {episode_id} has {n} labels, so the next step_index "
                    f"is {n}, got {step.step_index}"
                )
            sid = state_id
            if sid is None and n == 0 and ep.start_state_id is not None:
                sid = ep.start_state_id
            if sid is None:
                prov = provenance or StateProvenance(ep.task_id, step.step_index, None)
                row = _new_state("step", step.cloud_n3, step.rope_nodes_k3, prov)
                s.add(row)
                s.flush()
                sid = row.id
            elif s.get(RopeState, sid) is None:
                raise RecordNotFoundError(f"{self.url}: no rope state with id {sid}")
            label = Label(
                episode_id=ep.id,
                state_id=sid,
                labeller_id=ep.labeller_id,
                step_index=step.step_index,
                chosen_demo=step.chosen_demo,
                candidates=list(step.candidates),
                candidate_scores=None
                if step.candidate_scores_c is None
                else encode_array(step.candidate_scores_c, name="candidate_scores_c"),
                ranked_by_model=step.model_version,
                outcome=step.outcome,
                source=ep.source,
                labelled_at=labelled_at or utcnow(),
            )
            s.add(label)
            with self._conflicts(f"episode {episode_id} already has step {step.step_index}"):
                s.flush()
            return _label_info(label, ep, ep.labeller.name)

        return self._run(work, write=True)

    def add_dead_end(
        self, episode_id: int, dead_end: DeadEndState, *, provenance: StateProvenance | None = None
    ) -> int:
        """Record a dead-end state met during an episode; returns its rope state id."""

        def work(s: Session) -> int:
            ep = self._locked_episode(s, episode_id)
            n = s.scalar(
                select(func.count()).select_from(DeadEnd).where(DeadEnd.episode_id == ep.id)
            )
            prov = provenance or StateProvenance(ep.task_id, None, None)
            row = _new_state("dead_end", dead_end.cloud_n3, dead_end.rope_nodes_k3, prov)
            s.add(row)
            s.flush()
            s.add(DeadEnd(episode_id=ep.id, state_id=row.id, ordinal=int(n or 0)))
            s.flush()
            return row.id

        return self._run(work, write=True)

    def finish_episode(
        self, episode_id: int, *, status: Literal["completed", "abandoned"] = "completed"
    ) -> EpisodeInfo:
        """Close an episode; it ended in a knot iff its last label's outcome is a knot."""
        if status not in ("completed", "abandoned"):
            raise InvalidRecordError(f"status must be 'completed' or 'abandoned', got {status!r}")

        def work(s: Session) -> EpisodeInfo:
            ep = self._locked_episode(s, episode_id)
            last = s.scalars(
                select(Label.outcome)
                .where(Label.episode_id == ep.id)
                .order_by(Label.step_index.desc())
                .limit(1)
            ).first()
            ep.status = status
            ep.ended_in_knot = last == "knot"
            ep.finished_at = utcnow()
            s.flush()
            return _episode_info(s, ep)

        return self._run(work, write=True)

    def undo_last_label(self, labeller: str) -> LabelInfo | None:
        """Delete exactly the most recent label of `labeller` (None if they have none)."""

        def work(s: Session) -> LabelInfo | None:
            lid = s.scalar(select(Labeller.id).where(Labeller.name == labeller))
            if lid is None:
                raise RecordNotFoundError(f"{self.url}: no labeller named {labeller!r}")
            label = s.scalars(
                select(Label).where(Label.labeller_id == lid).order_by(Label.id.desc()).limit(1)
            ).first()
            if label is None:
                return None
            used = s.scalar(
                select(func.count())
                .select_from(ModelTrainingLabel)
                .where(ModelTrainingLabel.label_id == label.id)
            )
            if used:
                raise ConflictError(
                    f"{self.url}: label {label.id} of {labeller!r} was used to train "
                    f"{used} model(s) and cannot be undone"
                )
            ep = self._locked_episode(s, label.episode_id)
            info = _label_info(label, ep, labeller)
            state_id, own_state = label.state_id, label.state_id != ep.start_state_id
            s.delete(label)
            if ep.status == "completed":  # its last step is gone: it is being relabelled
                ep.status, ep.ended_in_knot, ep.finished_at = "in_progress", False, None
            s.flush()
            if own_state:
                refs = s.scalar(
                    select(func.count()).select_from(Label).where(Label.state_id == state_id)
                ) + s.scalar(
                    select(func.count()).select_from(DeadEnd).where(DeadEnd.state_id == state_id)
                )
                state = s.get(RopeState, state_id)
                if not refs and state is not None and state.role == "step":
                    s.delete(state)
            return info

        return self._run(work, write=True)

    def episode(self, episode_id: int) -> EpisodeInfo:
        """One episode's bookkeeping."""

        def work(s: Session) -> EpisodeInfo:
            ep = s.get(Episode, episode_id)
            if ep is None:
                raise RecordNotFoundError(f"{self.url}: no episode with id {episode_id}")
            return _episode_info(s, ep)

        return self._run(work, write=False)

    def progress(self, labeller: str) -> LabellerProgress:
        """Counts of a labeller's labels, outcomes and episodes, and the start states left."""

        def work(s: Session) -> LabellerProgress:
            lid = s.scalar(select(Labeller.id).where(Labeller.name == labeller))
            if lid is None:
                raise RecordNotFoundError(f"{self.url}: no labeller named {labeller!r}")
            outcomes = dict.fromkeys(OUTCOMES, 0)
            for outcome, n in s.execute(
                select(Label.outcome, func.count())
                .where(Label.labeller_id == lid)
                .group_by(Label.outcome)
            ):
                outcomes[outcome] = int(n)
            statuses = dict.fromkeys(EPISODE_STATUSES, 0)
            for status, n in s.execute(
                select(Episode.status, func.count())
                .where(Episode.labeller_id == lid)
                .group_by(Episode.status)
            ):
                statuses[status] = int(n)
            knots = s.scalar(
                select(func.count())
                .select_from(Episode)
                .where(Episode.labeller_id == lid, Episode.ended_in_knot.is_(True))
            )
            dead = s.scalar(
                select(func.count())
                .select_from(DeadEnd)
                .join(Episode, DeadEnd.episode_id == Episode.id)
                .where(Episode.labeller_id == lid)
            )
            last = s.scalar(select(func.max(Label.labelled_at)).where(Label.labeller_id == lid))
            remaining = s.scalar(
                select(func.count()).select_from(_unlabelled_start_states().subquery())
            )
            return LabellerProgress(
                labeller=labeller,
                labels=sum(outcomes.values()),
                outcomes=outcomes,
                episodes_in_progress=statuses["in_progress"],
                episodes_completed=statuses["completed"],
                episodes_abandoned=statuses["abandoned"],
                knots=int(knots or 0),
                dead_ends=int(dead or 0),
                last_label_at=last,
                start_states_remaining=int(remaining or 0),
            )

        return self._run(work, write=False)

    def labels(self, *, labeller: str | None = None) -> list[LabelInfo]:
        """Bookkeeping of every label (optionally one labeller's), oldest first."""

        def work(s: Session) -> list[LabelInfo]:
            q = (
                select(Label, Episode, Labeller.name)
                .join(Episode, Label.episode_id == Episode.id)
                .join(Labeller, Label.labeller_id == Labeller.id)
                .order_by(Label.id)
            )
            if labeller is not None:
                q = q.where(Labeller.name == labeller)
            return [_label_info(lab, ep, name) for lab, ep, name in s.execute(q)]

        return self._run(work, write=False)

    # --- whole executions: the oracle labeller and the learner

    def add_execution(
        self, execution: LabelledExecution | StoredExecution, *, if_exists: str = "error"
    ) -> int | None:
        """Store one whole execution atomically; returns its episode id (None if skipped)."""
        return self.add_executions([execution], if_exists=if_exists)[0]

    def add_executions(
        self,
        executions: Iterable[LabelledExecution | StoredExecution],
        *,
        if_exists: str = "error",
        batch_size: int = 200,
        on_progress: Callable[[int, int], None] | None = None,
    ) -> list[int | None]:
        """Store many executions in ONE transaction (all or nothing); returns episode ids.

        `if_exists` is "error" (an execution id already stored aborts everything) or "skip".
        `on_progress(done, total)` is called after each batch is written (still uncommitted).
        """
        if if_exists not in ("error", "skip"):
            raise InvalidRecordError(f"if_exists must be 'error' or 'skip', got {if_exists!r}")
        items = [e if isinstance(e, StoredExecution) else StoredExecution(e) for e in executions]
        seen: dict[str, int] = {}
        for i, item in enumerate(items):
            _validate_stored(item, i)
            key = item.execution.execution_id
            if key in seen:
                raise ConflictError(
                    f"executions {seen[key]} and {i} share the execution id {key!r}"
                )
            seen[key] = i

        def work(s: Session) -> list[int | None]:
            existing: set[str] = set()
            keys = list(seen)
            for j in range(0, len(keys), 500):
                existing.update(
                    s.scalars(
                        select(Episode.execution_key).where(
                            Episode.execution_key.in_(keys[j : j + 500])
                        )
                    )
                )
            if existing and if_exists == "error":
                shown = ", ".join(repr(k) for k in sorted(existing)[:5])
                raise ConflictError(
                    f"{self.url}: {len(existing)} execution id(s) already stored ({shown}); "
                    f"nothing was written"
                )
            labellers: dict[str, int] = {}
            libraries: dict[str | None, int | None] = {None: None}
            out: list[int | None] = []
            todo = [it for it in items if it.execution.execution_id not in existing]
            for j in range(0, len(todo), max(1, batch_size)):
                batch = todo[j : j + batch_size]
                for it in batch:
                    ex = it.execution
                    if ex.labeller not in labellers:
                        labellers[ex.labeller] = _labeller_id(s, ex.labeller, ex.source)
                    if ex.library_hash not in libraries:
                        libraries[ex.library_hash] = _library_id(s, ex.library_hash)
                _write_batch(s, batch, labellers, libraries)
                if on_progress is not None:
                    on_progress(min(j + batch_size, len(todo)), len(todo))
            ids = _episode_ids(s, [it.execution.execution_id for it in todo])
            for it in items:
                out.append(ids.get(it.execution.execution_id))
            return out

        with self._conflicts("a label or episode conflicts with one already stored"):
            return self._run(work, write=True)

    def stored_executions(
        self,
        *,
        source: str | None = None,
        labeller: str | None = None,
        library_hash: str | None = None,
        statuses: Sequence[str] = EPISODE_STATUSES,
    ) -> list[StoredExecution]:
        """Every matching execution with its status, times and provenance, oldest first."""
        conds = [Episode.status.in_(list(statuses))]
        if source is not None:
            conds.append(Episode.source == source)
        if labeller is not None:
            conds.append(
                Episode.labeller_id.in_(select(Labeller.id).where(Labeller.name == labeller))
            )
        if library_hash is not None:
            conds.append(
                Episode.library_id.in_(
                    select(DemoLibrary.id).where(DemoLibrary.library_hash == library_hash)
                )
            )
        return self._run(lambda s: _load_executions(s, conds), write=False)

    def training_executions(
        self,
        *,
        source: str | None = None,
        labeller: str | None = None,
        library_hash: str | None = None,
        include_unfinished: bool = False,
    ) -> list[LabelledExecution]:
        """Labels for training, as `LabelledExecution` records (completed episodes by default)."""
        statuses = EPISODE_STATUSES if include_unfinished else ("completed",)
        return [
            se.execution
            for se in self.stored_executions(
                source=source, labeller=labeller, library_hash=library_hash, statuses=statuses
            )
        ]

    # --- trained models

    def save_model(
        self,
        version: str,
        *,
        arrays: Mapping[str, np.ndarray],
        hyperparameters: Mapping[str, Any],
        feature_spec: Mapping[str, Any],
        params: Mapping[str, Any] | None = None,
        metrics: Mapping[str, Any] | None = None,
        library_hash: str | None = None,
        trained_on: Iterable[str] = (),
    ) -> ModelInfo:
        """Store a trained model; `trained_on` lists the execution ids whose labels it used."""
        _check_key("version", version)
        _check_key("library_hash", library_hash, optional=True, limit=128)
        blobs = {}
        for name, arr in arrays.items():
            _check_key("array name", name, limit=100)
            blobs[name] = encode_array(arr, "float64", name=f"model array {name!r}")
        docs = {
            "hyperparameters": dict(hyperparameters),
            "feature_spec": dict(feature_spec),
            "params": dict(params or {}),
            "metrics": dict(metrics or {}),
        }
        for what, doc in docs.items():
            _check_json(what, doc)
        execution_ids = list(dict.fromkeys(trained_on))

        def work(s: Session) -> ModelInfo:
            model = TrainedModel(version=version, library_id=_library_id(s, library_hash), **docs)
            s.add(model)
            with self._conflicts(f"model version {version!r} already exists"):
                s.flush()
            s.add_all(ModelArray(model_id=model.id, name=k, data=v) for k, v in blobs.items())
            label_ids: list[int] = []
            for j in range(0, len(execution_ids), 500):
                chunk = execution_ids[j : j + 500]
                found = dict(
                    s.execute(
                        select(Episode.execution_key, Episode.id).where(
                            Episode.execution_key.in_(chunk)
                        )
                    ).all()
                )
                missing = [k for k in chunk if k not in found]
                if missing:
                    raise RecordNotFoundError(
                        f"{self.url}: model {version!r} names unknown execution ids {missing[:5]}"
                    )
                label_ids += s.scalars(select(Label.id).where(Label.episode_id.in_(found.values())))
            s.add_all(ModelTrainingLabel(model_id=model.id, label_id=i) for i in label_ids)
            s.flush()
            return _model_info(model, library_hash, len(label_ids))

        return self._run(work, write=True)

    def list_models(self) -> list[ModelInfo]:
        """Every stored model version, oldest first (without arrays)."""

        def work(s: Session) -> list[ModelInfo]:
            counts = dict(
                s.execute(
                    select(ModelTrainingLabel.model_id, func.count()).group_by(
                        ModelTrainingLabel.model_id
                    )
                ).all()
            )
            rows = s.execute(
                select(TrainedModel, DemoLibrary.library_hash)
                .outerjoin(DemoLibrary, TrainedModel.library_id == DemoLibrary.id)
                .order_by(TrainedModel.id)
            )
            return [_model_info(m, h, counts.get(m.id, 0)) for m, h in rows]

        return self._run(work, write=False)

    def load_model(self, version: str | None = None) -> ModelRecord:
        """A model with its arrays: `version`, or the newest one when None."""

        def work(s: Session) -> ModelRecord:
            q = select(TrainedModel, DemoLibrary.library_hash).outerjoin(
                DemoLibrary, TrainedModel.library_id == DemoLibrary.id
            )
            q = (
                q.order_by(TrainedModel.id.desc())
                if version is None
                else q.where(TrainedModel.version == version)
            )
            row = s.execute(q.limit(1)).first()
            if row is None:
                what = "no models stored" if version is None else f"no model version {version!r}"
                raise RecordNotFoundError(f"{self.url}: {what}")
            model, lib = row
            n = s.scalar(
                select(func.count())
                .select_from(ModelTrainingLabel)
                .where(ModelTrainingLabel.model_id == model.id)
            )
            arrays = {
                a.name: decode_array(a.data, where=f"model {model.version!r} array {a.name!r}")
                for a in s.scalars(select(ModelArray).where(ModelArray.model_id == model.id))
            }
            return ModelRecord(_model_info(model, lib, int(n or 0)), arrays)

        return self._run(work, write=False)

    def model_training_executions(self, version: str) -> list[str]:
        """Execution ids whose labels trained model `version`."""

        def work(s: Session) -> list[str]:
            mid = s.scalar(select(TrainedModel.id).where(TrainedModel.version == version))
            if mid is None:
                raise RecordNotFoundError(f"{self.url}: no model version {version!r}")
            q = (
                select(Episode.execution_key)
                .join(Label, Label.episode_id == Episode.id)
                .join(ModelTrainingLabel, ModelTrainingLabel.label_id == Label.id)
                .where(ModelTrainingLabel.model_id == mid)
                .group_by(Episode.id, Episode.execution_key)
                .order_by(Episode.id)
            )
            return list(s.scalars(q))

        return self._run(work, write=False)

    # --- statistics

    def stats(self) -> dict[str, Any]:
        """Row counts per table, labels per source and outcome, and the schema revision."""

        def work(s: Session) -> dict[str, Any]:
            out: dict[str, Any] = {"url": self.url, "dialect": self.dialect}
            for model in (Labeller, DemoLibrary, RopeState, Episode, Label, DeadEnd, TrainedModel):
                out[model.__tablename__] = int(
                    s.scalar(select(func.count()).select_from(model)) or 0
                )
            out["labels_by_source"] = dict(
                s.execute(select(Label.source, func.count()).group_by(Label.source)).all()
            )
            out["labels_by_outcome"] = dict(
                s.execute(select(Label.outcome, func.count()).group_by(Label.outcome)).all()
            )
            out["episodes_by_status"] = dict(
                s.execute(select(Episode.status, func.count()).group_by(Episode.status)).all()
            )
            out["start_states_unlabelled"] = int(
                s.scalar(select(func.count()).select_from(_unlabelled_start_states().subquery()))
                or 0
            )
            out["schema_revision"] = s.scalar(text("SELECT version_num FROM alembic_version"))
            return out

        return self._run(work, write=False)


# ----------------------------------------------------------------------------- bulk I/O


def _validate_stored(item: StoredExecution, i: int) -> None:
    ex = item.execution
    where = f"execution {i} ({ex.execution_id!r})"
    try:
        _check_key("execution_id", ex.execution_id)
        _check_key("labeller", ex.labeller)
        _check_key("task_id", ex.task_id, optional=True)
        _check_key("library_hash", ex.library_hash, optional=True, limit=128)
        _check_json("metadata", ex.metadata)
        for step in ex.steps:
            _check_key(f"step {step.step_index} chosen_demo", step.chosen_demo)
            _check_key(f"step {step.step_index} model_version", step.model_version, optional=True)
            for c in step.candidates:
                _check_key(f"step {step.step_index} candidate", c)
        if ex.ended_in_knot and item.status != "completed":
            raise InvalidRecordError(f"ended_in_knot but status is {item.status!r}")
    except InvalidRecordError as exc:
        raise InvalidRecordError(f"{where}: {exc}") from exc


def _write_batch(
    s: Session,
    batch: Sequence[StoredExecution],
    labellers: Mapping[str, int],
    libraries: Mapping[str | None, int | None],
) -> None:
    now = utcnow()
    plans = []
    for it in batch:
        ex = it.execution
        step_states = []
        for i, step in enumerate(ex.steps):
            prov = it.step_provenance[i] if it.step_provenance else StateProvenance(ex.task_id, i)
            role = "start" if i == 0 else "step"
            step_states.append(_new_state(role, step.cloud_n3, step.rope_nodes_k3, prov))
        dead_states = []
        for i, de in enumerate(ex.dead_ends):
            prov = (
                it.dead_end_provenance[i] if it.dead_end_provenance else StateProvenance(ex.task_id)
            )
            dead_states.append(_new_state("dead_end", de.cloud_n3, de.rope_nodes_k3, prov))
        plans.append((it, step_states, dead_states))
        s.add_all(step_states)
        s.add_all(dead_states)
    s.flush()
    episodes = []
    for it, step_states, _ in plans:
        ex = it.execution
        finished = it.finished_at or (now if it.status != "in_progress" else None)
        ep = Episode(
            execution_key=ex.execution_id,
            start_state_id=step_states[0].id if step_states else None,
            labeller_id=labellers[ex.labeller],
            library_id=libraries[ex.library_hash],
            source=ex.source,
            status=it.status,
            ended_in_knot=ex.ended_in_knot,
            task_id=ex.task_id,
            meta=dict(ex.metadata),
            started_at=it.started_at or now,
            finished_at=finished,
        )
        episodes.append(ep)
    s.add_all(episodes)
    s.flush()
    rows: list[Label | DeadEnd] = []
    for ep, (it, step_states, dead_states) in zip(episodes, plans, strict=True):
        ex = it.execution
        for i, (step, state) in enumerate(zip(ex.steps, step_states, strict=True)):
            rows.append(
                Label(
                    episode_id=ep.id,
                    state_id=state.id,
                    labeller_id=ep.labeller_id,
                    step_index=step.step_index,
                    chosen_demo=step.chosen_demo,
                    candidates=list(step.candidates),
                    candidate_scores=None
                    if step.candidate_scores_c is None
                    else encode_array(step.candidate_scores_c, name="candidate_scores_c"),
                    ranked_by_model=step.model_version,
                    outcome=step.outcome,
                    source=ex.source,
                    labelled_at=it.labelled_at[i] if it.labelled_at else now,
                )
            )
        for i, state in enumerate(dead_states):
            rows.append(DeadEnd(episode_id=ep.id, state_id=state.id, ordinal=i, created_at=now))
    s.add_all(rows)
    s.flush()
    s.expunge_all()  # keep the identity map small during long imports


def _episode_ids(s: Session, keys: Sequence[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for j in range(0, len(keys), 500):
        out.update(
            s.execute(
                select(Episode.execution_key, Episode.id).where(
                    Episode.execution_key.in_(keys[j : j + 500])
                )
            ).all()
        )
    return out


def _load_executions(s: Session, conds: list[Any]) -> list[StoredExecution]:
    ep_ids = select(Episode.id).where(*conds)
    episodes = s.execute(
        select(
            Episode.id,
            Episode.execution_key,
            Labeller.name,
            Episode.source,
            Episode.status,
            Episode.ended_in_knot,
            Episode.task_id,
            DemoLibrary.library_hash,
            Episode.meta,
            Episode.started_at,
            Episode.finished_at,
        )
        .join(Labeller, Episode.labeller_id == Labeller.id)
        .outerjoin(DemoLibrary, Episode.library_id == DemoLibrary.id)
        .where(*conds)
        .order_by(Episode.id)
    ).all()
    steps: dict[int, list[Any]] = defaultdict(list)
    for row in s.execute(
        select(
            Label.episode_id,
            Label.id,
            Label.step_index,
            Label.chosen_demo,
            Label.candidates,
            Label.candidate_scores,
            Label.ranked_by_model,
            Label.outcome,
            Label.labelled_at,
            RopeState.id,
            RopeState.cloud,
            RopeState.rope_nodes,
            RopeState.task_id,
            RopeState.episode_step,
            RopeState.seed,
        )
        .join(RopeState, Label.state_id == RopeState.id)
        .where(Label.episode_id.in_(ep_ids))
        .order_by(Label.episode_id, Label.step_index)
    ):
        steps[row[0]].append(row)
    dead: dict[int, list[Any]] = defaultdict(list)
    for row in s.execute(
        select(
            DeadEnd.episode_id,
            RopeState.id,
            RopeState.cloud,
            RopeState.rope_nodes,
            RopeState.task_id,
            RopeState.episode_step,
            RopeState.seed,
        )
        .join(RopeState, DeadEnd.state_id == RopeState.id)
        .where(DeadEnd.episode_id.in_(ep_ids))
        .order_by(DeadEnd.episode_id, DeadEnd.ordinal)
    ):
        dead[row[0]].append(row)

    out = []
    for (
        ep_id,
        key,
        labeller,
        source,
        status,
        knot,
        task_id,
        lib,
        meta,
        started,
        finished,
    ) in episodes:
        try:
            step_records = []
            for (
                _e,
                label_id,
                index,
                demo,
                cands,
                scores,
                model_version,
                outcome,
                _at,
                sid,
                cloud,
                nodes,
                *_prov,
            ) in steps[ep_id]:
                where = f"label id={label_id} (state id={sid})"
                step_records.append(
                    LabelledStep(
                        step_index=index,
                        cloud_n3=decode_array(cloud, where=f"{where} cloud"),
                        chosen_demo=demo,
                        outcome=outcome,
                        rope_nodes_k3=None
                        if nodes is None
                        else decode_array(nodes, where=f"{where} rope_nodes"),
                        candidates=tuple(cands or ()),
                        candidate_scores_c=None
                        if scores is None
                        else decode_array(scores, where=f"{where} candidate_scores"),
                        model_version=model_version,
                    )
                )
            dead_records = [
                DeadEndState(
                    decode_array(cloud, where=f"dead-end state id={sid} cloud"),
                    None if nodes is None else decode_array(nodes, where=f"state id={sid} nodes"),
                )
                for _e, sid, cloud, nodes, *_prov in dead[ep_id]
            ]
            execution = LabelledExecution(
                execution_id=key,
                source=source,
                labeller=labeller,
                steps=tuple(step_records),
                ended_in_knot=bool(knot),
                dead_ends=tuple(dead_records),
                task_id=task_id,
                library_hash=lib,
                metadata=dict(meta or {}),
            )
        except InvalidInputError as exc:
            raise CorruptDatabaseError(f"episode id={ep_id} ({key!r}): {exc}") from exc
        out.append(
            StoredExecution(
                execution,
                status=status,
                started_at=started,
                finished_at=finished,
                labelled_at=tuple(r[8] for r in steps[ep_id]),
                step_provenance=tuple(StateProvenance(*r[12:15]) for r in steps[ep_id]),
                dead_end_provenance=tuple(StateProvenance(*r[4:7]) for r in dead[ep_id]),
            )
        )
    return out


def _model_info(model: TrainedModel, library_hash: str | None, n_labels: int) -> ModelInfo:
    return ModelInfo(
        version=model.version,
        created_at=model.created_at,
        library_hash=library_hash,
        hyperparameters=dict(model.hyperparameters or {}),
        feature_spec=dict(model.feature_spec or {}),
        params=dict(model.params or {}),
        metrics=dict(model.metrics or {}),
        n_training_labels=n_labels,
    )
