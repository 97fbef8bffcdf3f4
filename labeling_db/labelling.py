"""Labellers, libraries and start states, and human labelling one step at a time."""

from __future__ import annotations

import uuid
from collections.abc import Mapping, Sequence
from datetime import datetime
from typing import Any, Literal

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from knotlab.core.errors import InvalidInputError
from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.agreement import OverlapPolicy
from knotlab.core.selection.labels import OUTCOMES, REACHED_BY, DeadEndState, LabelledStep
from knotlab.core.tasks import DEFAULT_TASK
from knotlab.labeling_db.decisions import start_key
from knotlab.labeling_db.errors import (
    ConflictError,
    InvalidRecordError,
    RecordNotFoundError,
    TaskMismatchError,
)
from knotlab.labeling_db.models import (
    EPISODE_STATUSES,
    DeadEnd,
    DemoLibrary,
    Episode,
    Label,
    Labeller,
    ModelTrainingLabel,
    RopeState,
    utcnow,
)
from knotlab.labeling_db.records import (
    EpisodeInfo,
    LabelInfo,
    LabellerProgress,
    StateProvenance,
    StateRecord,
)
from knotlab.labeling_db.rows import (
    _check_json,
    _check_key,
    _check_task,
    _episode_info,
    _label_info,
    _label_row,
    _labeller_id,
    _library_id,
    _new_state,
    _state_record,
    _store_tasks,
    _unlabelled_start_states,
)
from knotlab.labeling_db.store_base import StoreBase

# Episode metadata: the demos whose tries were stored as dead ends, by rollout step
# ({"2": {"s012-t1": dead-end state id}}), so a resume marks them again.
DEAD_END_DEMOS = "dead_end_demos"

_PG_CLAIM_LOCK = 0x6B6E6F75  # serialises claiming the next unlabelled start state


def _resume_nodes(nodes_k3: np.ndarray) -> list[list[float]]:
    """Rope nodes as JSON for the episode's resume point (validated (k, 3), finite)."""
    try:
        checked = DeadEndState(np.zeros((1, 3)), nodes_k3).rope_nodes_k3
    except InvalidInputError as exc:
        raise InvalidRecordError(f"resume rope nodes: {exc}") from exc
    assert checked is not None
    return [[float(v) for v in row] for row in checked]


def _second_labeller_start(s: Session, labeller_id: int, overlap: OverlapPolicy) -> int | None:
    """The oldest start with one live episode, not this labeller's, that ``overlap`` offers."""
    live = Episode.status != "abandoned"
    held_once = (
        select(Episode.start_state_id)
        .where(live, Episode.start_state_id.is_not(None))
        .group_by(Episode.start_state_id)
        .having(func.count() == 1)
    )
    mine = (
        select(Episode.id)
        .where(Episode.start_state_id == RopeState.id, Episode.labeller_id == labeller_id, live)
        .exists()
    )
    rows = s.execute(
        select(RopeState.id, RopeState.task_id)
        .where(RopeState.role == "start", RopeState.id.in_(held_once), ~mine)
        .order_by(RopeState.id)
    )
    for sid, task_id in rows:
        if overlap.offers_second(start_key(task_id, sid, -1)):
            return int(sid)
    return None


class LabellingStore(StoreBase):
    """Labellers, libraries and start states, and human labelling one step at a time."""

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
        self,
        library_hash: str,
        *,
        name: str | None = None,
        demo_keys: Sequence[str] | None = None,
        task: str | None = None,
    ) -> None:
        """Record a demo library by its hash and task (default overhand); fills in name and keys.

        A library already recorded for another task is refused (:class:`TaskMismatchError`).
        """
        _check_key("library_hash", library_hash, limit=128)
        task = DEFAULT_TASK if task is None else task
        _check_task(task)

        def work(s: Session) -> None:
            lib = s.get(DemoLibrary, _library_id(s, library_hash, task))
            assert lib is not None
            if name is not None:
                lib.name = name
            if demo_keys is not None:
                lib.demo_keys = list(demo_keys)

        with self._mismatch():
            self._run(work, write=True)

    def tasks(self) -> set[str]:
        """The tasks this store holds labels or libraries of (empty for a new store).

        The tasks of its demo libraries, and the overhand knot when an episode names no library
        (a label without a task record is the overhand knot's).
        """
        return self._run(_store_tasks, write=False)

    def check_task(self, task: str) -> None:
        """Refuse (one line, :class:`TaskMismatchError`) a store holding another task's labels."""
        others = sorted(self.tasks() - {task})
        if others:
            raise TaskMismatchError(
                f"{self.url} holds labels of task {', '.join(map(repr, others))}, not {task!r}: "
                "use another database for this task (--db) or pass --task "
                f"{others[0]}"
            )

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
        overlap: OverlapPolicy | None = None,
        prefer: Sequence[int] = (),
        exclude: Sequence[int] = (),
    ) -> EpisodeInfo | None:
        """Start an episode on `state_id`, or claim the next unlabelled start state (None: none).

        ``prefer`` lists start state ids in the order to claim them (a suggested labelling
        order); the first of them still unclaimed is taken, in the same transaction as the
        check, else the oldest unclaimed start.

        With an ``overlap`` policy, a start another labeller already holds (its one live
        episode) is claimable too when the policy offers it to a second labeller: the claim is
        the oldest of those and the unlabelled starts. Without one (the default), only starts
        with no live episode are claimed.
        """
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
                free = RopeState.id.in_(_unlabelled_start_states().with_only_columns(RopeState.id))
                if exclude:
                    free = free & RopeState.id.not_in([int(i) for i in exclude])
                sid = None
                if prefer:
                    wanted = [int(i) for i in prefer]
                    found = set(
                        s.scalars(select(RopeState.id).where(free, RopeState.id.in_(wanted)))
                    )
                    sid = next((i for i in wanted if i in found), None)
                if sid is None:
                    sid = s.scalars(
                        select(RopeState.id).where(free).order_by(RopeState.id).limit(1)
                    ).first()
                if overlap is not None and overlap.overlap > 0:
                    second = _second_labeller_start(s, lid, overlap)
                    if second is not None and second in {int(i) for i in exclude}:
                        second = None
                    if second is not None and (sid is None or second < sid):
                        sid = second
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
        next_nodes_k3: np.ndarray | None = None,
        finish: bool = False,
    ) -> LabelInfo:
        """Append the next step's label to an in-progress episode (step 0 uses the start state).

        ``next_nodes_k3``, the rope after the accepted step, is kept with the episode in the same
        transaction so that an interrupted labelling session resumes from exactly there. With
        ``finish`` the episode is completed in that transaction too (its last step): a crash can
        never leave the last label stored on an episode that is still open.
        """
        resume = None if next_nodes_k3 is None else _resume_nodes(next_nodes_k3)
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
            reached = REACHED_BY in (ep.meta or {})  # its first state is not its start's
            if sid is None and n == 0 and ep.start_state_id is not None and not reached:
                sid = ep.start_state_id
            if sid is None:
                prov = provenance or StateProvenance(ep.task_id, step.step_index, None)
                row = _new_state("step", step.cloud_n3, step.rope_nodes_k3, prov)
                s.add(row)
                s.flush()
                sid = row.id
            elif s.get(RopeState, sid) is None:
                raise RecordNotFoundError(f"{self.url}: no rope state with id {sid}")
            label = _label_row(ep, sid, step, ep.source, labelled_at or utcnow())
            s.add(label)
            if resume is not None:
                # The exact rope each later state was placed from, by step: undo returns to it,
                # so the state (and its ranking) after an undo is the one that was shown.
                sources = dict((ep.meta or {}).get("state_sources", {}))
                sources[str(step.step_index + 1)] = resume
                ep.meta = {**(ep.meta or {}), "resume_nodes": resume, "state_sources": sources}
            with self._conflicts(f"episode {episode_id} already has step {step.step_index}"):
                s.flush()
            if finish:
                _close_episode(s, ep, "completed")
            return _label_info(label, ep, ep.labeller.name)

        return self._run(work, write=True)

    def add_dead_end(
        self,
        episode_id: int,
        dead_end: DeadEndState,
        *,
        provenance: StateProvenance | None = None,
        demo_key: str | None = None,
    ) -> int:
        """Record a dead-end state met during an episode; returns its rope state id.

        With ``demo_key`` (the demo whose try reached it) and the provenance's step, the mark is
        kept per step, so a resume or an undo shows it again, and marking the same demo at the
        same step twice stores it once (the first state's id is returned).
        """
        step = None if provenance is None else provenance.episode_step
        keyed = demo_key is not None and step is not None

        def work(s: Session) -> int:
            ep = self._locked_episode(s, episode_id)
            marks = {k: dict(v) for k, v in (ep.meta or {}).get(DEAD_END_DEMOS, {}).items()}
            if keyed and demo_key in marks.get(str(step), {}):
                return int(marks[str(step)][demo_key])
            n = s.scalar(
                select(func.count()).select_from(DeadEnd).where(DeadEnd.episode_id == ep.id)
            )
            prov = provenance or StateProvenance(ep.task_id, None, None)
            row = _new_state("dead_end", dead_end.cloud_n3, dead_end.rope_nodes_k3, prov)
            s.add(row)
            s.flush()
            s.add(DeadEnd(episode_id=ep.id, state_id=row.id, ordinal=int(n or 0)))
            if keyed:
                marks.setdefault(str(step), {})[str(demo_key)] = row.id
                ep.meta = {**(ep.meta or {}), DEAD_END_DEMOS: marks}
            s.flush()
            return row.id

        return self._run(work, write=True)

    def dead_end_demos(self, episode_id: int, step: int) -> tuple[str, ...]:
        """The demos whose tries were stored as dead ends at ``step`` of an episode (marked with
        their demo), in the order they were marked."""

        def work(s: Session) -> tuple[str, ...]:
            ep = s.get(Episode, episode_id)
            if ep is None:
                raise RecordNotFoundError(f"{self.url}: no episode with id {episode_id}")
            marks = (ep.meta or {}).get(DEAD_END_DEMOS, {}).get(str(step), {})
            return tuple(sorted(marks, key=lambda k: marks[k]))

        return self._run(work, write=False)

    def mark_reached(
        self, episode_id: int, nodes_k3: np.ndarray, reached_by: Mapping[str, Any]
    ) -> EpisodeInfo:
        """Record that an unlabelled episode begins where a policy's rollout left its start.

        ``reached_by`` says how (policy, model, step, demos chosen before, ...; it must hold
        ``step`` >= 1); ``nodes_k3`` is the rope the first state was placed from, kept exactly
        (float64), so a resume or an undo places the state that was shown. The episode's first
        label then gets its own state row, not the start's.
        """
        reached = dict(reached_by)
        step = reached.get("step")
        if not isinstance(step, int) or isinstance(step, bool) or step < 1:
            raise InvalidRecordError(f"reached_by must hold a step >= 1, got {step!r}")
        _check_json("reached_by", reached)
        nodes = _resume_nodes(nodes_k3)

        def work(s: Session) -> EpisodeInfo:
            ep = self._locked_episode(s, episode_id)
            n = s.scalar(select(func.count()).select_from(Label).where(Label.episode_id == ep.id))
            if ep.status != "in_progress" or n:
                raise ConflictError(
                    f"{self.url}: episode {episode_id} is {ep.status} with {n} labels; "
                    "only a fresh in-progress episode can begin at a reached state"
                )
            ep.meta = {
                **(ep.meta or {}),
                REACHED_BY: reached,
                "resume_nodes": nodes,
                "state_sources": {"0": nodes},
            }
            s.flush()
            return _episode_info(s, ep)

        return self._run(work, write=True)

    def finish_episode(
        self, episode_id: int, *, status: Literal["completed", "abandoned"] = "completed"
    ) -> EpisodeInfo:
        """Close an episode; it ended in a knot iff its last label's outcome is a knot."""
        if status not in ("completed", "abandoned"):
            raise InvalidRecordError(f"status must be 'completed' or 'abandoned', got {status!r}")

        def work(s: Session) -> EpisodeInfo:
            ep = self._locked_episode(s, episode_id)
            _close_episode(s, ep, status)
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
            undone = s.get(RopeState, state_id)
            source = (ep.meta or {}).get("state_sources", {}).get(str(label.step_index))
            if source is not None:  # resume exactly where that step's state was placed from
                ep.meta = {**(ep.meta or {}), "resume_nodes": source}
            elif undone is not None and undone.rope_nodes is not None:  # older episodes
                nodes = _state_record(undone).rope_nodes_k3
                ep.meta = {**(ep.meta or {}), "resume_nodes": _resume_nodes(nodes)}
            marks = (ep.meta or {}).get(DEAD_END_DEMOS)
            if marks:  # the states after the undone step are gone, and their marks with them
                offset = int(((ep.meta or {}).get(REACHED_BY) or {}).get("step", 0))
                kept = {k: v for k, v in marks.items() if int(k) <= offset + label.step_index}
                ep.meta = {**(ep.meta or {}), DEAD_END_DEMOS: kept}
            s.delete(label)
            if ep.status == "completed":  # its last step is gone: it is being relabelled
                ep.status, ep.ended_in_knot, ep.finished_at = "in_progress", False, None
            s.flush()
            if own_state:
                refs = (
                    s.scalar(
                        select(func.count()).select_from(Label).where(Label.state_id == state_id)
                    )
                    or 0
                ) + (
                    s.scalar(
                        select(func.count())
                        .select_from(DeadEnd)
                        .where(DeadEnd.state_id == state_id)
                    )
                    or 0
                )
                state = s.get(RopeState, state_id)
                if not refs and state is not None and state.role == "step":
                    s.delete(state)
            return info

        return self._run(work, write=True)

    def open_episode(self, labeller: str) -> tuple[EpisodeInfo, np.ndarray | None] | None:
        """The labeller's newest in-progress human episode and the rope to resume it from.

        The rope is the state after the last accepted step (None: resume from the start state).
        """

        def work(s: Session) -> tuple[EpisodeInfo, np.ndarray | None] | None:
            ep = s.scalars(
                select(Episode)
                .join(Labeller, Episode.labeller_id == Labeller.id)
                .where(
                    Labeller.name == labeller,
                    Episode.status == "in_progress",
                    Episode.source == "human",
                )
                .order_by(Episode.id.desc())
                .limit(1)
            ).first()
            if ep is None:
                return None
            info = _episode_info(s, ep)
            moved = info.n_labels or REACHED_BY in (ep.meta or {})
            nodes = (ep.meta or {}).get("resume_nodes") if moved else None
            return info, None if nodes is None else np.asarray(nodes, dtype=float)

        return self._run(work, write=False)

    def start_task_ids(self) -> set[str]:
        """Task ids of every queued start state (to register a task set only once)."""
        return self._run(
            lambda s: set(
                s.scalars(
                    select(RopeState.task_id).where(
                        RopeState.role == "start", RopeState.task_id.is_not(None)
                    )
                )
            ),
            write=False,
        )

    def episode(self, episode_id: int) -> EpisodeInfo:
        """One episode's bookkeeping."""

        def work(s: Session) -> EpisodeInfo:
            ep = s.get(Episode, episode_id)
            if ep is None:
                raise RecordNotFoundError(f"{self.url}: no episode with id {episode_id}")
            return _episode_info(s, ep)

        return self._run(work, write=False)

    def placed_ropes(self, episode_id: int) -> dict[int, np.ndarray]:
        """The exact ropes (float64) the app placed an episode's states from, by step index.

        The labelling app places every state after the first at rest from the rope its last
        step ended in, and keeps that rope exactly (the episode's state sources); a replay that
        places the states from them meets the ropes the labeller saw. Empty for an episode the
        app did not make (an oracle's or an imported one).
        """

        def work(s: Session) -> dict[int, np.ndarray]:
            ep = s.get(Episode, episode_id)
            if ep is None:
                raise RecordNotFoundError(f"{self.url}: no episode with id {episode_id}")
            sources = (ep.meta or {}).get("state_sources", {})
            return {int(k): np.asarray(v, dtype=float) for k, v in sources.items()}

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


def _close_episode(s: Session, ep: Episode, status: str) -> None:
    """Mark ``ep`` finished (in the caller's transaction); it ended in a knot iff its last
    label's outcome is a knot."""
    last = s.scalars(
        select(Label.outcome)
        .where(Label.episode_id == ep.id)
        .order_by(Label.step_index.desc())
        .limit(1)
    ).first()
    ep.status = status
    ep.ended_in_knot = last == StepOutcome.KNOT
    ep.finished_at = utcnow()
    s.flush()
