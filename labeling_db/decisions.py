"""Who decided what where: every labeller's decisions per state, and the starts still to label.

`state_visits()` answers "labels of every labeller grouped by state": one `StateVisit` (core's
plain record) per labelled step and per state a dead end was marked from, with the demos the
episode chose before it, so that `core.selection.agreement` can pair up the same state across
labellers. Columns only: no cloud or rope arrays are decoded.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

from sqlalchemy import select
from sqlalchemy.orm import Session

from knotlab.core.selection.agreement import StateVisit
from knotlab.core.selection.labels import REACHED_BY
from knotlab.labeling_db.models import DeadEnd, Episode, Label, Labeller, RopeState
from knotlab.labeling_db.records import StateRecord
from knotlab.labeling_db.rows import _state_record
from knotlab.labeling_db.store_base import StoreBase

LIVE_STATUSES: tuple[str, ...] = ("in_progress", "completed")


def start_key(task_id: str | None, start_state_id: int | None, episode_id: int) -> str:
    """How a start is named across labellers: its task id, else its start state, else episode."""
    if task_id is not None:
        return task_id
    if start_state_id is not None:
        return f"state:{start_state_id}"
    return f"episode:{episode_id}"  # no shared start: never matches another labeller's


class DecisionsStore(StoreBase):
    """Labellers' decisions per state (for agreement) and the starts nobody has finished."""

    def state_visits(self, *, statuses: Sequence[str] = LIVE_STATUSES) -> list[StateVisit]:
        """Every labelled step and dead-end mark of episodes in ``statuses``, oldest first."""

        def work(s: Session) -> list[StateVisit]:
            live = select(Episode.id).where(Episode.status.in_(list(statuses)))
            episodes = {
                row.id: row
                for row in s.execute(
                    select(
                        Episode.id,
                        Episode.task_id,
                        Episode.start_state_id,
                        Episode.meta,
                        Labeller.name,
                        RopeState.task_id.label("start_task_id"),
                    )
                    .join(Labeller, Episode.labeller_id == Labeller.id)
                    .outerjoin(RopeState, Episode.start_state_id == RopeState.id)
                    .where(Episode.status.in_(list(statuses)))
                    .order_by(Episode.id)
                )
            }
            chosen: dict[int, dict[int, str]] = defaultdict(dict)
            for ep_id, step, demo in s.execute(
                select(Label.episode_id, Label.step_index, Label.chosen_demo)
                .where(Label.episode_id.in_(live))
                .order_by(Label.episode_id, Label.step_index)
            ):
                chosen[ep_id][step] = demo
            marked: dict[int, set[int]] = defaultdict(set)
            for ep_id, step in s.execute(
                select(DeadEnd.episode_id, RopeState.episode_step)
                .join(RopeState, DeadEnd.state_id == RopeState.id)
                .where(DeadEnd.episode_id.in_(live))
            ):
                if step is not None:  # a dead end without its step cannot be placed
                    marked[ep_id].add(int(step))
            out = []
            for ep_id, ep in episodes.items():
                # An episode that begins where a policy's rollout left its start counts its
                # states from the start too: step and path include the policy's choices, so
                # its states pair with the same states of other labellers' episodes.
                reached = (ep.meta or {}).get(REACHED_BY) or {}
                offset = int(reached.get("step", 0))
                before = tuple(str(k) for k in reached.get("chosen_before", ()))
                steps = {offset + i: demo for i, demo in chosen[ep_id].items()}
                # The app's episodes name no task: their start state does (as claiming reads
                # it), so an app episode and an oracle execution of one start pair up.
                start = start_key(ep.task_id or ep.start_task_id, ep.start_state_id, ep_id)
                for i in sorted(set(steps) | marked[ep_id]):
                    if i < offset:
                        continue
                    path = before + tuple(steps[j] for j in range(offset, i) if j in steps)
                    if len(path) != i:
                        continue  # a gap in the steps: the state is not known
                    out.append(
                        StateVisit(ep.name, start, i, path, steps.get(i), i in marked[ep_id])
                    )
            return out

        return self._run(work, write=False)

    def start_states_to_label(self) -> list[StateRecord]:
        """Start states without a completed episode (what still needs a label), oldest first."""

        def work(s: Session) -> list[StateRecord]:
            done = (
                select(Episode.id)
                .where(Episode.start_state_id == RopeState.id, Episode.status == "completed")
                .exists()
            )
            rows = s.scalars(
                select(RopeState).where(RopeState.role == "start", ~done).order_by(RopeState.id)
            )
            return [_state_record(r) for r in rows]

        return self._run(work, write=False)
