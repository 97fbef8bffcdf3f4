"""The labelling store: engine from a URL, schema checks and migrations, and the app's queries.

`open_store(url)` gives a :class:`Store`. Every public method is one unit of work: one session,
one explicit transaction, committed before it returns. Writes on SQLite take the write lock up
front (``BEGIN IMMEDIATE``) and are retried with bounded, jittered backoff while the database is
locked; on PostgreSQL, serialisation failures and deadlocks are retried the same way.
Only plain records (``selection.labels`` dataclasses and the dataclasses below) leave this module.
Shape suffixes: n = cloud points, k = rope nodes, c = candidates shown.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select, text
from sqlalchemy.engine import URL
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session

# The store's public surface in one place (records and schema functions live in their modules).
from knotlab.labeling_db.decisions import DecisionsStore
from knotlab.labeling_db.engine import (
    DEFAULT_URL,
    _make_engine,
    _open_error,
    _prepare,
    _raise_for,
    _status_of,
    _upgrade,
    schema_head,
    schema_status,
    upgrade_database,
)
from knotlab.labeling_db.errors import ConflictError, InvalidRecordError
from knotlab.labeling_db.executions import ExecutionsStore
from knotlab.labeling_db.labelling import LabellingStore
from knotlab.labeling_db.model_store import ActiveModel, ModelStore
from knotlab.labeling_db.models import (
    DeadEnd,
    DemoLibrary,
    Episode,
    Label,
    Labeller,
    RopeState,
    TrainedModel,
)
from knotlab.labeling_db.records import (
    EpisodeInfo,
    LabelInfo,
    LabellerProgress,
    ModelInfo,
    ModelRecord,
    SchemaStatus,
    StateProvenance,
    StateRecord,
    StoredExecution,
)
from knotlab.labeling_db.rows import _unlabelled_start_states

__all__ = [
    "DEFAULT_URL",
    "ActiveModel",
    "EpisodeInfo",
    "LabelInfo",
    "LabelMix",
    "LabellerProgress",
    "LabellerShare",
    "ModelInfo",
    "ModelRecord",
    "SchemaStatus",
    "SeedResult",
    "StateProvenance",
    "StateRecord",
    "Store",
    "StoredExecution",
    "open_store",
    "schema_head",
    "schema_status",
    "upgrade_database",
]


TRAINING_STATUSES: tuple[str, ...] = ("completed", "in_progress")  # what a retrain fits on


@dataclass(frozen=True)
class SeedResult:
    """What seeding the store with a fixed set of oracle executions added."""

    added_executions: int
    added_labels: int
    present_executions: int  # already stored: seeding again adds nothing


@dataclass(frozen=True)
class LabellerShare:
    """One labeller's labels among those a retrain would fit on."""

    labeller: str
    source: str  # oracle | human
    labels: int
    executions: int


@dataclass(frozen=True)
class LabelMix:
    """The labels a retrain would fit on (completed and in-progress episodes), per labeller."""

    shares: tuple[LabellerShare, ...]
    # Executions with dead ends and no label: a retrain fits their values too.
    dead_end_only: int = 0

    @property
    def labels(self) -> int:
        """Labelled states in all."""
        return sum(sh.labels for sh in self.shares)

    @property
    def executions(self) -> int:
        """Executions (episodes) with at least one label."""
        return sum(sh.executions for sh in self.shares)

    def of_source(self, source: str) -> tuple[LabellerShare, ...]:
        """The shares of one source (oracle or human), most labels first."""
        return tuple(sh for sh in self.shares if sh.source == source)


class Store(LabellingStore, ExecutionsStore, ModelStore, DecisionsStore):
    """The labelling database. Every method runs as its own committed transaction."""

    # --- seeding and the training labels

    def seed_executions(
        self, items: Sequence[StoredExecution], *, task: str | None = None
    ) -> SeedResult:
        """Store oracle executions (e.g. those a shipped model was trained on) once: an
        execution id already stored is skipped, so seeding again adds nothing."""
        for i, item in enumerate(items):
            if item.execution.source != "oracle":
                raise InvalidRecordError(
                    f"seed execution {i} ({item.execution.execution_id!r}) is a "
                    f"{item.execution.source!r} execution; only oracle labels seed a store"
                )
        try:
            ids = self.add_executions(items, if_exists="skip", task=task)
        except ConflictError:  # another process seeded at the same moment: its rows count
            ids = self.add_executions(items, if_exists="skip", task=task)
        added = [it for it, i in zip(items, ids, strict=True) if i is not None]
        return SeedResult(
            added_executions=len(added),
            added_labels=sum(len(it.execution.steps) for it in added),
            present_executions=len(items) - len(added),
        )

    def label_mix(self) -> LabelMix:
        """Labels of completed and in-progress episodes per labeller and source."""

        def work(s: Session) -> LabelMix:
            rows = s.execute(
                select(
                    Labeller.name,
                    Label.source,
                    func.count(Label.id),
                    func.count(func.distinct(Label.episode_id)),
                )
                .join(Episode, Label.episode_id == Episode.id)
                .join(Labeller, Label.labeller_id == Labeller.id)
                .where(Episode.status.in_(TRAINING_STATUSES))
                .group_by(Labeller.name, Label.source)
            ).all()
            shares = [LabellerShare(name, src, int(n), int(e)) for name, src, n, e in rows]
            shares.sort(key=lambda sh: (sh.source != "oracle", -sh.labels, sh.labeller))
            labelled = select(Label.id).where(Label.episode_id == Episode.id).exists()
            dead_end_only = s.scalar(
                select(func.count(func.distinct(DeadEnd.episode_id)))
                .join(Episode, DeadEnd.episode_id == Episode.id)
                .where(Episode.status.in_(TRAINING_STATUSES), ~labelled)
            )
            return LabelMix(tuple(shares), int(dead_end_only or 0))

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


def open_store(
    url: str | URL = DEFAULT_URL,
    *,
    create: bool = True,
    auto_upgrade: bool = True,
    busy_timeout_s: float = 10.0,
    max_attempts: int = 8,
    echo: bool = False,
    persistent: bool = False,
) -> Store:
    """Open (and, if allowed, create or migrate) the labelling database at `url`.

    ``persistent``: refuse an in-memory database (``sqlite://``), for callers whose writes must
    outlive the process. A database that cannot be opened, read or written is reported in one
    line naming it (labeling_db.engine.database_error), never as a driver's exception.
    """
    parsed, text, status = _prepare(url, create=create, persistent=persistent)
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
        raise _open_error(exc, text) from exc
    except BaseException:
        engine.dispose()
        raise
    return Store(engine, text, max_attempts=max_attempts)
