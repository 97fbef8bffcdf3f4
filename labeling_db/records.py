"""Plain records that leave the labelling store (dataclasses; never ORM rows)."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Literal

import numpy as np

from knotlab.core.selection.labels import LabelledExecution
from knotlab.core.tasks import DEFAULT_TASK
from knotlab.labeling_db.errors import (
    InvalidRecordError,
)
from knotlab.labeling_db.models import (
    EPISODE_STATUSES,
)

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
    # An episode that begins where a policy's rollout left the start (label where the model
    # goes): the rollout step its first label is at, and the demos the policy chose before.
    first_step: int = 0
    policy_chosen: tuple[str, ...] = ()
    # The policy's choice that failed in that first state (greyed out there again on a resume).
    policy_failed: str | None = None


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
    """A trained model with its arrays (float64), ready to rebuild a `QModel`."""

    info: ModelInfo
    arrays: dict[str, np.ndarray]


@dataclass(frozen=True, eq=False)
class StoredExecution:
    """A `LabelledExecution` plus what the store keeps around it (status, times, provenance).

    Empty `labelled_at` / provenance tuples mean "now" / "derived from the execution".
    `task` is the task of the execution's demo library: None when unknown (the library's
    recorded task when it has one, else the overhand knot's); a task other than the overhand
    knot's needs a `library_hash` (the store records a task with its demo library).
    """

    execution: LabelledExecution
    status: str = "completed"
    started_at: datetime | None = None
    finished_at: datetime | None = None
    labelled_at: tuple[datetime, ...] = ()
    step_provenance: tuple[StateProvenance, ...] = ()
    dead_end_provenance: tuple[StateProvenance, ...] = ()
    task: str | None = None

    def __post_init__(self) -> None:
        ex = self.execution
        if not isinstance(ex, LabelledExecution):
            raise InvalidRecordError(f"execution must be a LabelledExecution, got {type(ex)}")
        if self.task is not None:
            if not isinstance(self.task, str) or not self.task or len(self.task) > 64:
                raise InvalidRecordError(
                    f"execution {ex.execution_id!r}: task must be a non-empty string of at most "
                    f"64 chars, got {self.task!r}"
                )
            if self.task != DEFAULT_TASK and ex.library_hash is None:
                raise InvalidRecordError(
                    f"execution {ex.execution_id!r}: task {self.task!r} needs a library_hash "
                    "(the store records a task with its demo library)"
                )
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
