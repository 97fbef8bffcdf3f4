"""Row-level helpers of the store: key and JSON checks, idempotent inserts, id lookups."""

from __future__ import annotations

import json
from datetime import datetime
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.labels import REACHED_BY
from knotlab.core.tasks import DEFAULT_TASK
from knotlab.labeling_db.arrays import decode_array, encode_array
from knotlab.labeling_db.errors import (
    InvalidRecordError,
    TaskMismatchError,
)
from knotlab.labeling_db.models import (
    DemoLibrary,
    Episode,
    Label,
    Labeller,
    RopeState,
    utcnow,
)
from knotlab.labeling_db.records import EpisodeInfo, LabelInfo, StateProvenance, StateRecord

_MAX_KEY = 200
_MAX_TASK = 64  # demo_libraries.task


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
        from sqlalchemy.dialects.postgresql import insert  # type: ignore[assignment]
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
    """The id of labeller ``name`` of ``kind`` (registered if new); a name another kind of
    labeller holds is refused, so a person's labels are never filed as the oracle's."""
    _insert_ignore(session, Labeller, {"name": name, "kind": kind, "created_at": utcnow()}, "name")
    lid, held = session.execute(
        select(Labeller.id, Labeller.kind).where(Labeller.name == name)
    ).one()
    if held != kind:
        who = "a simulated expert" if held == "oracle" else "a person"
        raise InvalidRecordError(f"the name {name!r} belongs to {who} here; choose another name")
    return int(lid)


def _library_id(session: Session, library_hash: str | None, task: str | None = None) -> int | None:
    """The id of a library, recorded if new (for ``task``, else the overhand knot's).

    With a ``task``, a library already recorded for another task is refused (one line).
    """
    if library_hash is None:
        return None
    values: dict[str, Any] = {"library_hash": library_hash, "created_at": utcnow()}
    if task is not None:
        values["task"] = task
    _insert_ignore(session, DemoLibrary, values, "library_hash")
    lid, recorded = session.execute(
        select(DemoLibrary.id, DemoLibrary.task).where(DemoLibrary.library_hash == library_hash)
    ).one()
    if task is not None and recorded != task:
        raise TaskMismatchError(
            f"demo library {library_hash!r} is recorded for task {recorded!r}, not {task!r}"
        )
    return int(lid)


def _check_task(value: object) -> None:
    _check_key("task", value, limit=_MAX_TASK)


def _store_tasks(session: Session) -> set[str]:
    """The tasks of every recorded library, and overhand when an episode names no library."""
    tasks = set(session.scalars(select(DemoLibrary.task).distinct()))
    unnamed = session.scalar(select(Episode.id).where(Episode.library_id.is_(None)).limit(1))
    if unnamed is not None:
        tasks.add(DEFAULT_TASK)
    return tasks


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
    reached = (ep.meta or {}).get(REACHED_BY) or {}
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
        first_step=int(reached.get("step", 0)),
        policy_chosen=tuple(str(k) for k in reached.get("chosen_before", ())),
        policy_failed=None if reached.get("failed_demo") is None else str(reached["failed_demo"]),
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


def _label_row(ep: Episode, state_id: int, step: Any, source: str, labelled_at: datetime) -> Label:
    """The Label row of one labelled step (human labelling and bulk import build it alike)."""
    return Label(
        episode_id=ep.id,
        state_id=state_id,
        labeller_id=ep.labeller_id,
        step_index=step.step_index,
        chosen_demo=step.chosen_demo,
        candidates=list(step.candidates),
        candidate_scores=None
        if step.candidate_scores_c is None
        else encode_array(step.candidate_scores_c, name="candidate_scores_c"),
        ranked_by_model=step.model_version,
        outcome=StepOutcome(step.outcome).value,
        source=source,
        labelled_at=labelled_at,
    )
