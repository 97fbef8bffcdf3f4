"""What one step ended in: one vocabulary for labels, the labelling store, episodes and the app.

A labelled step (core/selection/labels.py), a stored label (labeling_db), an episode's step
(core/experiments/episode.py: KNOT, PROGRESSED, or the step's `FailureKind`) and a try in the
labelling app (app/web/session.py) all say it with these words. Label files, results files and
databases store the value strings, so the values below are part of those formats (the member
order is the order counts and constraints list them in).
"""

from __future__ import annotations

from enum import StrEnum


class StepOutcome(StrEnum):
    """What executing a step's chosen demo did (as stored in files and databases)."""

    PROGRESSED = "progressed"  # the demo ran; the goal is not reached yet
    KNOT = "knot"  # the demo reached the task's goal
    DEAD_END = "dead_end"  # labelled: the state reached cannot be finished in time
    MISGRASP = "misgrasp"  # labelled: a gripper closed on nothing
    SKIPPED = "skipped"  # labelled: the labeller skipped the state (no training row)


STEP_OUTCOMES: tuple[str, ...] = tuple(o.value for o in StepOutcome)
