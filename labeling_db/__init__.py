"""The labelling database: expert and oracle labels, rope states, episodes and trained models.

Open it with :func:`open_store` (SQLite file by default, PostgreSQL by URL); records that leave
it are plain dataclasses (``knotlab.core.selection.labels.LabelledExecution`` for training data).
"""

from knotlab.labeling_db.errors import (
    ConflictError,
    CorruptDatabaseError,
    DatabaseBusyError,
    DatabaseNotFoundError,
    ImportRowError,
    InvalidRecordError,
    LabelingDbError,
    NotADatabaseError,
    RecordNotFoundError,
    SchemaOutdatedError,
    SchemaTooNewError,
    SchemaVersionError,
    TaskMismatchError,
)
from knotlab.labeling_db.store import (
    DEFAULT_URL,
    EpisodeInfo,
    LabelInfo,
    LabellerProgress,
    ModelInfo,
    ModelRecord,
    SchemaStatus,
    StateProvenance,
    StateRecord,
    Store,
    StoredExecution,
    open_store,
    schema_head,
    schema_status,
    upgrade_database,
)

__all__ = [
    "DEFAULT_URL",
    "ConflictError",
    "CorruptDatabaseError",
    "DatabaseBusyError",
    "DatabaseNotFoundError",
    "EpisodeInfo",
    "ImportRowError",
    "InvalidRecordError",
    "LabelInfo",
    "LabelingDbError",
    "LabellerProgress",
    "ModelInfo",
    "ModelRecord",
    "NotADatabaseError",
    "RecordNotFoundError",
    "SchemaOutdatedError",
    "SchemaStatus",
    "SchemaTooNewError",
    "SchemaVersionError",
    "StateProvenance",
    "StateRecord",
    "Store",
    "StoredExecution",
    "TaskMismatchError",
    "open_store",
    "schema_head",
    "schema_status",
    "upgrade_database",
]
