"""SQLAlchemy 2.0 models of the labelling database: labellers, states, episodes, labels, models.

Arrays (rope nodes, clouds, scores, weights) are stored as :mod:`labeling_db.arrays` blobs.
Timestamps are stored in UTC and always come back timezone-aware.
The schema itself is created and versioned by the Alembic migrations in ``labeling_db/migrations``;
these classes must describe exactly what the newest migration builds (a test compares them).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    Boolean,
    CheckConstraint,
    DateTime,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    UniqueConstraint,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

from knotlab.core.outcomes import STEP_OUTCOMES
from knotlab.core.tasks import DEFAULT_TASK

# The Alembic revision these classes describe (newest in labeling_db/migrations/versions): a
# database stamped with it is opened without loading Alembic. Bump it with every new migration;
# tests/test_db_schema.py checks it against the migrations.
SCHEMA_REVISION = "0004"
OUTCOME_VALUES = STEP_OUTCOMES  # StepOutcome's values, as the 0001 migration wrote them
SOURCE_VALUES = ("oracle", "human")
EPISODE_STATUSES = ("in_progress", "completed", "abandoned")
STATE_ROLES = ("start", "step", "dead_end")

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A timestamp stored as UTC and returned timezone-aware (SQLite keeps no zone itself)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        """Convert an aware datetime to UTC (naive values are taken to be UTC already)."""
        if value is None:
            return None
        value = value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        """Return an aware UTC datetime."""
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class Base(DeclarativeBase):
    """Declarative base with a naming convention so migrations name constraints predictably."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        dict[str, Any]: JSON,
        datetime: UTCDateTime,
        bytes: LargeBinary,
    }


class Labeller(Base):
    """A person (or the scripted oracle) who labels states."""

    __tablename__ = "labellers"
    __table_args__ = (CheckConstraint(_in("kind", SOURCE_VALUES), name="kind"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    kind: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class DemoLibrary(Base):
    """A demonstration library, identified by its content hash, and the task it is for.

    The task (0003) is the knot the library's labels are for; rows from before tasks existed
    are the overhand knot's (the server default).
    """

    __tablename__ = "demo_libraries"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    library_hash: Mapped[str] = mapped_column(String(128), unique=True)
    name: Mapped[str | None] = mapped_column(String(200))
    demo_keys: Mapped[list[str] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    task: Mapped[str] = mapped_column(String(64), server_default=DEFAULT_TASK)


class RopeState(Base):
    """A rope configuration: simulator nodes (when known), observed cloud, and provenance."""

    __tablename__ = "rope_states"
    __table_args__ = (
        CheckConstraint(_in("role", STATE_ROLES), name="role"),
        Index("ix_rope_states_role_id", "role", "id"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    role: Mapped[str] = mapped_column(String(16))  # start (to label) | step | dead_end
    cloud: Mapped[bytes] = mapped_column(LargeBinary)  # encoded (n, 3) float32
    rope_nodes: Mapped[bytes | None] = mapped_column(LargeBinary)  # encoded (k, 3) float32
    task_id: Mapped[str | None] = mapped_column(String(200))
    episode_step: Mapped[int | None] = mapped_column(Integer)
    seed: Mapped[int | None] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Episode(Base):
    """A labelling episode (one `LabelledExecution`): a labeller guiding the rope from one start."""

    __tablename__ = "episodes"
    __table_args__ = (
        CheckConstraint(_in("status", EPISODE_STATUSES), name="status"),
        CheckConstraint(_in("source", SOURCE_VALUES), name="source"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    execution_key: Mapped[str] = mapped_column(String(200), unique=True)
    start_state_id: Mapped[int | None] = mapped_column(
        ForeignKey("rope_states.id", ondelete="RESTRICT"), index=True
    )
    labeller_id: Mapped[int] = mapped_column(ForeignKey("labellers.id"), index=True)
    library_id: Mapped[int | None] = mapped_column(ForeignKey("demo_libraries.id"))
    source: Mapped[str] = mapped_column(String(16))
    status: Mapped[str] = mapped_column(String(16))
    ended_in_knot: Mapped[bool] = mapped_column(Boolean, default=False)
    task_id: Mapped[str | None] = mapped_column(String(200))
    meta: Mapped[dict[str, Any]] = mapped_column("metadata", JSON, default=dict)
    started_at: Mapped[datetime] = mapped_column(default=utcnow)
    finished_at: Mapped[datetime | None]

    labeller: Mapped[Labeller] = relationship()
    library: Mapped[DemoLibrary | None] = relationship()


class Label(Base):
    """One expert decision: the state seen, the candidates shown, the demo chosen, the outcome."""

    __tablename__ = "labels"
    __table_args__ = (
        UniqueConstraint("episode_id", "step_index", name="uq_labels_episode_step"),
        CheckConstraint(_in("outcome", OUTCOME_VALUES), name="outcome"),
        CheckConstraint(_in("source", SOURCE_VALUES), name="source"),
        CheckConstraint("step_index >= 0", name="step_index"),
        Index("ix_labels_labeller_id_id", "labeller_id", "id"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    episode_id: Mapped[int] = mapped_column(ForeignKey("episodes.id", ondelete="CASCADE"))
    state_id: Mapped[int] = mapped_column(ForeignKey("rope_states.id"), index=True)
    labeller_id: Mapped[int] = mapped_column(ForeignKey("labellers.id"))
    step_index: Mapped[int] = mapped_column(Integer)
    chosen_demo: Mapped[str] = mapped_column(String(200))
    candidates: Mapped[list[str]] = mapped_column(JSON, default=list)
    candidate_scores: Mapped[bytes | None] = mapped_column(LargeBinary)  # encoded (c,) float32
    ranked_by_model: Mapped[str | None] = mapped_column(String(200))
    outcome: Mapped[str] = mapped_column(String(16))
    source: Mapped[str] = mapped_column(String(16))
    labelled_at: Mapped[datetime] = mapped_column(default=utcnow)


class DeadEnd(Base):
    """A state met during an episode from which the labeller judged no knot can be tied in time."""

    __tablename__ = "dead_end_states"
    __table_args__ = (UniqueConstraint("episode_id", "ordinal", name="uq_dead_end_states_ordinal"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    episode_id: Mapped[int] = mapped_column(ForeignKey("episodes.id", ondelete="CASCADE"))
    state_id: Mapped[int] = mapped_column(ForeignKey("rope_states.id"), index=True)
    ordinal: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class TrainedModel(Base):
    """A trained Q-function: hyper-parameters, feature spec, metrics and where it came from."""

    __tablename__ = "trained_models"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    version: Mapped[str] = mapped_column(String(200), unique=True)
    library_id: Mapped[int | None] = mapped_column(ForeignKey("demo_libraries.id"))
    hyperparameters: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    feature_spec: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # scalars, e.g. bias
    metrics: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    library: Mapped[DemoLibrary | None] = relationship()


class ModelArray(Base):
    """A named array of a trained model (weights, feature mean and scale), stored as float64."""

    __tablename__ = "model_arrays"

    model_id: Mapped[int] = mapped_column(
        ForeignKey("trained_models.id", ondelete="CASCADE"), primary_key=True
    )
    name: Mapped[str] = mapped_column(String(100), primary_key=True)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class ModelTrainingLabel(Base):
    """Association: which labels a trained model was trained on."""

    __tablename__ = "model_training_labels"

    model_id: Mapped[int] = mapped_column(
        ForeignKey("trained_models.id", ondelete="CASCADE"), primary_key=True
    )
    label_id: Mapped[int] = mapped_column(
        ForeignKey("labels.id", ondelete="RESTRICT"), primary_key=True, index=True
    )


class ModelActivation(Base):
    """Which model the app ranks with, from when and why: the newest row is the active model.

    Append-only (0004), so the history of switches stays readable; a NULL model is
    nearest-neighbour ranking. A store without rows has never had a model activated.
    """

    __tablename__ = "model_activations"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    model_id: Mapped[int | None] = mapped_column(ForeignKey("trained_models.id"))
    reason: Mapped[str] = mapped_column(String(200))
    activated_at: Mapped[datetime] = mapped_column(default=utcnow)
