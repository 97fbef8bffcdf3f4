"""Expert labels in the original system's HDF5 layout: import and export.

The layout: one group per labelled state of a completed task, named ``(<task>, <step>)``, with
``cloud_xyz`` (the pre-action cloud), ``action`` (the chosen segment's group name) and ``knot``
(1 on the step that tied the knot, else 0); and ``f<k>`` groups holding a dead-end state's
``cloud_xyz`` only. knotlab adds ``rope_nodes`` (K x 3) where it knows the rope's state.

The layout carries less than knotlab's own labels files (no candidates shown, scores, labeller,
times or provenance), so an export is lossy by design: use JSONL or CSV to move labels between
knotlab stores. Imported labels are human labels (the original system's labellers), labeller
``hdf5:<file name>``; a dead end of the layout belongs to no task, so they are imported as one
execution without steps holding every dead end. Action names are matched to the library by
segment key or by the ``<demo>-seg<NN>`` group name the library exports under.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from knotlab.core.atomic import atomic_path
from knotlab.core.demos.library import DemoLibrary
from knotlab.core.errors import InvalidInputError
from knotlab.core.interop.h5_demos import group_name
from knotlab.core.interop.h5read import H5File, open_h5
from knotlab.core.outcomes import StepOutcome
from knotlab.core.selection.labels import DeadEndState, LabelledExecution, LabelledStep

STATE_NAME = re.compile(r"\(\s*(?P<task>[0-9]{1,9})\s*,\s*(?P<step>[0-9]{1,3})\s*\)")
FAILURE_NAME = re.compile(r"f(?P<k>[0-9]{1,9})")
DEAD_ENDS_ID = "hdf5-dead-ends"


@dataclass(frozen=True)
class LabelsImport:
    """The executions read from an HDF5 labels file and what was counted on the way."""

    executions: tuple[LabelledExecution, ...]
    states: int
    dead_ends: int


def action_names(library: DemoLibrary) -> dict[str, str]:
    """Every name a labels file may use for a segment (its key and group name) -> its key."""
    names = {group_name(s): s.key for s in library}
    names.update({s.key: s.key for s in library})
    return names


def import_labels_h5(path: str | Path, library: DemoLibrary) -> LabelsImport:
    """Read an HDF5 labels file against ``library``; a bad group is named with its key."""
    names = action_names(library)
    label = f"hdf5:{Path(path).name}"
    with open_h5(path, "HDF5 labels") as f:
        groups = f.group_names()
        tasks: dict[int, dict[int, str]] = {}
        failures: list[tuple[int, str]] = []
        for g in groups:
            if (m := STATE_NAME.fullmatch(g)) is not None:
                tasks.setdefault(int(m.group("task")), {})[int(m.group("step"))] = g
            elif (m := FAILURE_NAME.fullmatch(g)) is not None:
                failures.append((int(m.group("k")), g))
            else:
                raise f.fail(g, "group name is neither (<task>, <step>) nor f<k>")
        executions = []
        for task_index in sorted(tasks):
            steps_by_index = tasks[task_index]
            order = sorted(steps_by_index)
            if order != list(range(len(order))):
                raise f.fail(
                    steps_by_index[order[0]],
                    f"task {task_index} has steps {order}, expected 0..{len(order) - 1}",
                )
            steps = [_read_step(f, steps_by_index[i], i, names) for i in order]
            for step in steps[:-1]:
                if step.outcome is StepOutcome.KNOT:
                    raise f.fail(
                        steps_by_index[step.step_index], "knot = 1 before the task's last step"
                    )
            executions.append(
                LabelledExecution(
                    f"hdf5-task{task_index}",
                    "human",
                    label,
                    tuple(steps),
                    ended_in_knot=steps[-1].outcome is StepOutcome.KNOT,
                    task_id=f"hdf5-task{task_index}",
                    library_hash=library.content_hash(),
                )
            )
        dead = [_read_dead_end(f, g) for _, g in sorted(failures)]
        if dead:
            executions.append(
                LabelledExecution(
                    DEAD_ENDS_ID,
                    "human",
                    label,
                    (),
                    ended_in_knot=False,
                    dead_ends=tuple(dead),
                    library_hash=library.content_hash(),
                )
            )
    return LabelsImport(tuple(executions), sum(len(t) for t in tasks.values()), len(dead))


def _read_step(f: H5File, g: str, index: int, names: dict[str, str]) -> LabelledStep:
    cloud = f.array(g, "cloud_xyz", (None, 3))
    action = f.text(g, "action")
    if action not in names:
        raise f.fail(f"{g}/action", f"segment {action[:80]!r} is not in the library")
    knot = f.scalar(g, "knot")
    if knot not in (0.0, 1.0):
        raise f.fail(f"{g}/knot", f"expected 0 or 1, got {knot:g}")
    nodes = f.array(g, "rope_nodes", (None, 3)) if f.has(g, "rope_nodes") else None
    return LabelledStep(
        index,
        cloud,
        names[action],
        StepOutcome.KNOT if knot else StepOutcome.PROGRESSED,
        rope_nodes_k3=nodes,
    )


def _read_dead_end(f: H5File, g: str) -> DeadEndState:
    cloud = f.array(g, "cloud_xyz", (None, 3))
    nodes = f.array(g, "rope_nodes", (None, 3)) if f.has(g, "rope_nodes") else None
    return DeadEndState(cloud, nodes)


def export_labels_h5(
    executions: Sequence[LabelledExecution], library: DemoLibrary, path: str | Path
) -> tuple[int, int]:
    """Write executions in the original layout; returns (labelled states, dead ends) written.

    Steps the layout cannot say (skipped, misgrasp, dead-end outcomes) are left out, as the
    original labeller never saved them; every dead-end state becomes an ``f<k>`` group.
    """
    import h5py

    group_of = {s.key: group_name(s) for s in library}
    states = dead = 0
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as out:
        task_index = 0
        for ex in executions:
            steps = [s for s in ex.steps if s.outcome in (StepOutcome.PROGRESSED, StepOutcome.KNOT)]
            if len(steps) == len(ex.steps) and steps:
                for i, step in enumerate(steps):
                    if step.chosen_demo not in group_of:
                        raise InvalidInputError(
                            f"execution {ex.execution_id!r}: demo {step.chosen_demo!r} is not in "
                            "the library"
                        )
                    g = out.create_group(f"({task_index}, {i})")
                    g.create_dataset("cloud_xyz", data=step.cloud_n3)
                    g.create_dataset("action", data=group_of[step.chosen_demo])
                    g.create_dataset("knot", data=np.int64(step.outcome is StepOutcome.KNOT))
                    if step.rope_nodes_k3 is not None:
                        g.create_dataset("rope_nodes", data=step.rope_nodes_k3)
                    states += 1
                task_index += 1
            for d in ex.dead_ends:
                g = out.create_group(f"f{dead}")
                g.create_dataset("cloud_xyz", data=d.cloud_n3)
                if d.rope_nodes_k3 is not None:
                    g.create_dataset("rope_nodes", data=d.rope_nodes_k3)
                dead += 1
    return states, dead
