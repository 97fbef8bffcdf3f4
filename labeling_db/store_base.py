"""The store's plumbing: one session and one explicit transaction per unit of work, retried."""

from __future__ import annotations

import random
import sqlite3
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Self, TypeVar

from sqlalchemy import Engine
from sqlalchemy.exc import DBAPIError, IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from knotlab.labeling_db.engine import _is_corruption, _status_of, database_error
from knotlab.labeling_db.errors import (
    ConflictError,
    CorruptDatabaseError,
    DatabaseBusyError,
    TaskMismatchError,
)
from knotlab.labeling_db.records import SchemaStatus

_RETRY_SQLSTATES = {"40001", "40P01", "55P03"}  # serialization failure, deadlock, lock n/a
T = TypeVar("T")


# ----------------------------------------------------------------------------- the store


class StoreBase:
    """Connection plumbing shared by the store's parts: one retried transaction per call."""

    def __init__(self, engine: Engine, url_text: str, *, max_attempts: int = 8) -> None:
        self._engine = engine
        self.url = url_text
        self.dialect = engine.dialect.name
        self._max_attempts = max(1, max_attempts)
        # One session factory per kind of unit of work: writers take the SQLite write lock up
        # front (BEGIN IMMEDIATE, see engine._make_engine), readers do not.
        self._sessions = {
            write: sessionmaker(
                bind=engine.execution_options(knotlab_write=write), expire_on_commit=False
            )
            for write in (False, True)
        }

    # --- plumbing

    def close(self) -> None:
        """Close every pooled connection (a SQLite WAL file is checkpointed by the last one)."""
        self._engine.dispose()

    def __enter__(self) -> Self:
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
                with self._sessions[write].begin() as session:
                    return fn(session)
            except DBAPIError as exc:
                if _is_corruption(exc.orig):
                    raise CorruptDatabaseError(
                        f"{self.url}: database is corrupt ({exc.orig})"
                    ) from exc
                if not self._retryable(exc):
                    # read-only, full, unreachable ...: one line naming the database
                    error = database_error(exc, self.url)
                    if error is None:
                        raise
                    raise error from exc
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

    @contextmanager
    def _mismatch(self) -> Iterator[None]:
        """Name this database in a task mismatch found by a row helper."""
        try:
            yield
        except TaskMismatchError as exc:
            raise TaskMismatchError(f"{self.url}: {exc}") from exc

    def schema_status(self) -> SchemaStatus:
        """The schema revision of this database."""
        with self._engine.connect() as conn:
            return _status_of(conn, self.url)
