"""Bulk I/O of whole executions: validation, batched writes, and loading them back."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from knotlab.core.errors import InvalidInputError
from knotlab.core.selection.labels import DeadEndState, LabelledExecution, LabelledStep
from knotlab.labeling_db.arrays import decode_array
from knotlab.labeling_db.errors import (
    CorruptDatabaseError,
    InvalidRecordError,
)
from knotlab.labeling_db.models import (
    DeadEnd,
    DemoLibrary,
    Episode,
    Label,
    Labeller,
    RopeState,
    TrainedModel,
    utcnow,
)
from knotlab.labeling_db.records import ModelInfo, StateProvenance, StoredExecution
from knotlab.labeling_db.rows import _check_json, _check_key, _label_row, _new_state

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
            at = it.labelled_at[i] if it.labelled_at else now
            rows.append(_label_row(ep, state.id, step, ex.source, at))
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
    """Executions matching ``conds``, with steps, dead ends and provenance (three queries)."""
    ep_ids = select(Episode.id).where(*conds)
    episodes = s.execute(
        select(
            Episode.id,
            Episode.execution_key,
            Labeller.name.label("labeller"),
            Episode.source,
            Episode.status,
            Episode.ended_in_knot,
            Episode.task_id,
            DemoLibrary.library_hash,
            DemoLibrary.task,
            Episode.meta,
            Episode.started_at,
            Episode.finished_at,
        )
        .join(Labeller, Episode.labeller_id == Labeller.id)
        .outerjoin(DemoLibrary, Episode.library_id == DemoLibrary.id)
        .where(*conds)
        .order_by(Episode.id)
    ).all()
    state_columns = (
        RopeState.id.label("state_id"),
        RopeState.cloud,
        RopeState.rope_nodes,
        RopeState.task_id.label("state_task_id"),
        RopeState.episode_step.label("state_episode_step"),
        RopeState.seed.label("state_seed"),
    )
    steps: dict[int, list[Any]] = defaultdict(list)
    for row in s.execute(
        select(
            Label.episode_id,
            Label.id.label("label_id"),
            Label.step_index,
            Label.chosen_demo,
            Label.candidates,
            Label.candidate_scores,
            Label.ranked_by_model,
            Label.outcome,
            Label.labelled_at,
            *state_columns,
        )
        .join(RopeState, Label.state_id == RopeState.id)
        .where(Label.episode_id.in_(ep_ids))
        .order_by(Label.episode_id, Label.step_index)
    ):
        steps[row.episode_id].append(row)
    dead: dict[int, list[Any]] = defaultdict(list)
    for dead_row in s.execute(
        select(DeadEnd.episode_id, *state_columns)
        .join(RopeState, DeadEnd.state_id == RopeState.id)
        .where(DeadEnd.episode_id.in_(ep_ids))
        .order_by(DeadEnd.episode_id, DeadEnd.ordinal)
    ):
        dead[dead_row.episode_id].append(dead_row)

    def provenance(row: Any) -> StateProvenance:
        return StateProvenance(row.state_task_id, row.state_episode_step, row.state_seed)

    out = []
    for ep in episodes:
        try:
            step_records = []
            for st in steps[ep.id]:
                where = f"label id={st.label_id} (state id={st.state_id})"
                step_records.append(
                    LabelledStep(
                        step_index=st.step_index,
                        cloud_n3=decode_array(st.cloud, where=f"{where} cloud"),
                        chosen_demo=st.chosen_demo,
                        outcome=st.outcome,
                        rope_nodes_k3=None
                        if st.rope_nodes is None
                        else decode_array(st.rope_nodes, where=f"{where} rope_nodes"),
                        candidates=tuple(st.candidates or ()),
                        candidate_scores_c=None
                        if st.candidate_scores is None
                        else decode_array(st.candidate_scores, where=f"{where} candidate_scores"),
                        model_version=st.ranked_by_model,
                    )
                )
            dead_records = [
                DeadEndState(
                    decode_array(d.cloud, where=f"dead-end state id={d.state_id} cloud"),
                    None
                    if d.rope_nodes is None
                    else decode_array(d.rope_nodes, where=f"state id={d.state_id} nodes"),
                )
                for d in dead[ep.id]
            ]
            execution = LabelledExecution(
                execution_id=ep.execution_key,
                source=ep.source,
                labeller=ep.labeller,
                steps=tuple(step_records),
                ended_in_knot=bool(ep.ended_in_knot),
                dead_ends=tuple(dead_records),
                task_id=ep.task_id,
                library_hash=ep.library_hash,
                metadata=dict(ep.meta or {}),
            )
        except InvalidInputError as exc:
            raise CorruptDatabaseError(f"episode id={ep.id} ({ep.execution_key!r}): {exc}") from exc
        out.append(
            StoredExecution(
                execution,
                status=ep.status,
                started_at=ep.started_at,
                finished_at=ep.finished_at,
                labelled_at=tuple(st.labelled_at for st in steps[ep.id]),
                step_provenance=tuple(provenance(st) for st in steps[ep.id]),
                dead_end_provenance=tuple(provenance(d) for d in dead[ep.id]),
                task=ep.task,  # its library's (None: no library)
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
