"""Whole executions: what the oracle labeller writes and the learner reads."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

from sqlalchemy import select
from sqlalchemy.orm import Session

from knotlab.core.selection.labels import LabelledExecution
from knotlab.core.tasks import DEFAULT_TASK
from knotlab.labeling_db.bulk import _episode_ids, _load_executions, _validate_stored, _write_batch
from knotlab.labeling_db.errors import (
    ConflictError,
    InvalidRecordError,
    TaskMismatchError,
)
from knotlab.labeling_db.models import (
    EPISODE_STATUSES,
    DemoLibrary,
    Episode,
    Labeller,
)
from knotlab.labeling_db.records import StoredExecution
from knotlab.labeling_db.rows import _check_task, _labeller_id, _library_id, _store_tasks
from knotlab.labeling_db.store_base import StoreBase


class ExecutionsStore(StoreBase):
    """Whole executions: what the oracle labeller writes and the learner reads."""

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
        task: str | None = None,
    ) -> list[int | None]:
        """Store many executions in ONE transaction (all or nothing); returns episode ids.

        `if_exists` is "error" (an execution id already stored aborts everything) or "skip".
        `on_progress(done, total)` is called after each batch is written (still uncommitted).
        An execution's library is recorded for its `StoredExecution.task`, else for `task`
        (a library recorded for another task is refused). With a `task`, every execution must
        be of it and the store must hold no other task's labels (:class:`TaskMismatchError`).
        """
        if if_exists not in ("error", "skip"):
            raise InvalidRecordError(f"if_exists must be 'error' or 'skip', got {if_exists!r}")
        if task is not None:
            _check_task(task)
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
            if task is not None and item.task not in (None, task):
                raise TaskMismatchError(
                    f"execution {i} ({key!r}) is of task {item.task!r}, not {task!r}; "
                    "nothing was written"
                )
            if task not in (None, DEFAULT_TASK) and item.execution.library_hash is None:
                raise InvalidRecordError(
                    f"execution {i} ({key!r}): task {task!r} needs a library_hash (the store "
                    "records a task with its demo library)"
                )

        def work(s: Session) -> list[int | None]:
            if task is not None:
                others = sorted(_store_tasks(s) - {task})
                if others:
                    raise TaskMismatchError(
                        f"it holds labels of task {', '.join(map(repr, others))}, not {task!r}; "
                        "nothing was written (use another database for this task)"
                    )
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
            checked: set[tuple[str | None, str | None]] = set()  # (library, task) recorded
            out: list[int | None] = []
            todo = [it for it in items if it.execution.execution_id not in existing]
            for j in range(0, len(todo), max(1, batch_size)):
                batch = todo[j : j + batch_size]
                for it in batch:
                    ex = it.execution
                    if ex.labeller not in labellers:
                        labellers[ex.labeller] = _labeller_id(s, ex.labeller, ex.source)
                    want = it.task or task
                    if ex.library_hash is not None and (ex.library_hash, want) not in checked:
                        libraries[ex.library_hash] = _library_id(s, ex.library_hash, want)
                        checked.add((ex.library_hash, want))
                _write_batch(s, batch, labellers, libraries)
                if on_progress is not None:
                    on_progress(min(j + batch_size, len(todo)), len(todo))
            ids = _episode_ids(s, [it.execution.execution_id for it in todo])
            for it in items:
                out.append(ids.get(it.execution.execution_id))
            return out

        conflict = "a label or episode conflicts with one already stored"
        with self._conflicts(conflict), self._mismatch():
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
