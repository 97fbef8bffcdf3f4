"""Exceptions raised by the labelling database, each naming the database, row or file at fault."""

from __future__ import annotations

from typing import ClassVar

from knotlab.core.errors import CorruptFileError, InvalidInputError, KnotlabError


class LabelingDbError(KnotlabError):
    """Base class of every error the labelling database raises on purpose."""


class DatabaseUrlError(LabelingDbError, InvalidInputError):
    """A database URL that cannot be parsed, names an unknown dialect, or needs a missing driver."""


class DatabaseNotFoundError(LabelingDbError, FileNotFoundError):
    """The database file does not exist and creating it was not asked for."""


class NotADatabaseError(LabelingDbError, CorruptFileError):
    """The file is not an SQLite database, or the database holds no knotlab schema."""


class CorruptDatabaseError(LabelingDbError, CorruptFileError):
    """The database file is truncated or damaged, or a stored value fails validation."""


class SchemaVersionError(LabelingDbError):
    """The database schema revision is not the one this knotlab uses."""


class SchemaOutdatedError(SchemaVersionError):
    """The database is from an older schema revision (or empty) and was not upgraded."""


class SchemaTooNewError(SchemaVersionError):
    """The database was written by a newer knotlab: its schema revision is unknown here."""


class DatabaseBusyError(LabelingDbError):
    """A write could not get the database lock within the retry budget."""

    exit_code: ClassVar[int] = 1  # the input was fine; another writer held the lock


class DatabaseReadOnlyError(LabelingDbError):
    """The database refuses writes: a read-only file, folder, mount or connection."""


class DatabaseUnavailableError(LabelingDbError):
    """The database cannot be reached: a file SQLite cannot open, a server that refuses."""


class InMemoryDatabaseError(DatabaseUrlError):
    """An in-memory database URL (``sqlite://``) for a command that stores: it keeps nothing."""


class DatabaseWriteError(LabelingDbError):
    """Writing failed below the database: a full disk, a file size limit, an I/O error."""

    exit_code: ClassVar[int] = 1  # the input was fine; the machine could not keep it


class DatabaseFailedError(LabelingDbError):
    """Another operational failure of the database server or file, reported in one line."""

    exit_code: ClassVar[int] = 1


class RecordNotFoundError(LabelingDbError, LookupError):
    """A labeller, state, episode or model looked up by key does not exist."""


class ConflictError(LabelingDbError):
    """A write conflicts with what is stored (duplicate key, wrong step order, label in use)."""


class TaskMismatchError(ConflictError):
    """A library, labels file or command of one task meets a store holding another task's."""


class InvalidRecordError(LabelingDbError, InvalidInputError):
    """A record handed to the store (or read from an import file) is malformed."""


class ImportRowError(InvalidRecordError):
    """A row of a labels import file is malformed; names the file, line and field."""

    def __init__(self, path: str, line: int, field: str, problem: str) -> None:
        self.path, self.line, self.field, self.problem = path, line, field, problem
        super().__init__(f"{path}, line {line}, field {field!r}: {problem} (nothing was imported)")
