"""Tried candidates: one-step outcomes of a labelled state's cheapest demos (docs/results.md).

The oracle's label says "the first demo in registration-cost order that still leads to a knot":
the demos before it failed and the ones after it were never tried, so a max-margin row asks the
labelled demo to beat every other demo, including ones that would have done as well. Trying the
``top`` cheapest candidates of each labelled state once in simulation
(`core.experiments.tries.try_candidates`) tells which advance from it (a knot, or a higher
topological stage without a failure). Training then drops the margin rows against the
alternatives that advance too, and asks the ones that do not to lose by at least the state's
median margin. Measured by 5-fold greedy on the main training starts (bench/greedy_lever.py):
61.7 % without, 67.0 % with (NN 48.0 %).

File format (JSONL, one object per labelled state): {"execution_id", "step_index",
"stage_before", "tried": [{"demo", "stage", "knot", "failure"}, ...], "numeric_kind"}; the last
names the kind of CPU whose numbers the tries are (core.machine.numeric_kind), absent in files
written before tries recorded it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.machine import NUMERIC_KIND_KEY, UNRECORDED_KIND
from knotlab.core.selection.learner import TrainingData
from knotlab.core.textinput import LineError, parse_json, quote, read_lines


@dataclass(frozen=True)
class TriedDemo:
    """What one candidate did when tried once from the state."""

    demo: str
    stage: int
    knot: bool
    failure: str | None


@dataclass(frozen=True)
class StateTries:
    """The candidates tried from one labelled state (by execution and step)."""

    execution_id: str
    step_index: int
    stage_before: int
    tried: tuple[TriedDemo, ...]
    # The CPU kind that simulated them: a transfer's last bits, and so an outcome, can differ
    # on another kind.
    numeric_kind: str = UNRECORDED_KIND

    def advanced(self, t: TriedDemo) -> bool:
        """A knot, or a higher stage than the state's with no failure."""
        return t.knot or (t.failure is None and t.stage > self.stage_before)

    def to_dict(self) -> dict:
        """The JSON line."""
        return {
            "execution_id": self.execution_id,
            "step_index": self.step_index,
            "stage_before": self.stage_before,
            "tried": [
                {"demo": t.demo, "stage": t.stage, "knot": t.knot, "failure": t.failure}
                for t in self.tried
            ],
            NUMERIC_KIND_KEY: self.numeric_kind,
        }


TriesByState = dict[tuple[str, int], StateTries]


def read_tries(path: str | Path) -> TriesByState:
    """Every state's tries in a JSONL file, by (execution id, step index); bad lines named."""
    path = Path(path)
    if not path.exists():
        raise InvalidInputError(
            f"{path}: no such tries file (make one with `knotlab labels tries`)"
        )
    out: TriesByState = {}
    for n, line, _, _ in read_lines(path):  # split on "\n" only, bounded (core.textinput)
        if not line.strip():
            continue
        try:
            rec = _state_tries(parse_json(line, path, n))
        except LineError as exc:
            raise InvalidInputError(
                f"{path}:{n}: not a tried-candidates line ({exc.problem})"
            ) from None
        except ValueError as exc:
            raise InvalidInputError(f"{path}:{n}: not a tried-candidates line ({exc})") from None
        out[(rec.execution_id, rec.step_index)] = rec
    return out


def _field(d: dict, name: str, kind: type | tuple[type, ...]) -> Any:
    if name not in d:
        raise ValueError(f"no {name!r} field")
    v = d[name]
    if not isinstance(v, kind) or (isinstance(v, bool) and kind is int):
        raise ValueError(f"{name!r} is {quote(v)}")
    return v


def _state_tries(d: object) -> StateTries:
    """The record of one parsed line; ValueError saying what is wrong."""
    if not isinstance(d, dict):
        raise ValueError(f"a JSON {type(d).__name__}, not an object")
    tried = []
    for t in _field(d, "tried", list):
        if not isinstance(t, dict):
            raise ValueError(f"a tried entry is {quote(t)}")
        failure = _field(t, "failure", (str, type(None)))
        tried.append(TriedDemo(_field(t, "demo", str), _field(t, "stage", int),
                               _field(t, "knot", bool), failure))  # fmt: skip
    kind = _field(d, NUMERIC_KIND_KEY, str) if NUMERIC_KIND_KEY in d else UNRECORDED_KIND
    return StateTries(
        _field(d, "execution_id", str),
        _field(d, "step_index", int),
        _field(d, "stage_before", int),
        tuple(tried),
        kind,
    )


def apply_tries(
    data: TrainingData, execution_id: str, tries: TriesByState, keys: tuple[str, ...]
) -> TrainingData:
    """One execution's training data with its states' tries applied (see the module doc)."""
    index = {k: a for a, k in enumerate(keys)}
    states = []
    for s in data.states:
        rec = tries.get((execution_id, s.step))
        if rec is None:
            states.append(s)
            continue
        good = np.zeros(len(s.margins_a), dtype=bool)
        margins = s.margins_a.copy()
        positive = margins[margins > 0]
        floor = float(np.median(positive)) if positive.size else 0.0
        for t in rec.tried:
            a = index.get(t.demo)
            if a is None:
                raise InvalidInputError(
                    f"tries of {execution_id} step {s.step} name demo {quote(t.demo)}, "
                    "which is not in this library"
                )
            if a == s.expert_action:
                continue
            if rec.advanced(t):
                good[a] = True
            else:
                margins[a] = max(margins[a], floor)
        states.append(replace(s, margins_a=margins, also_good_a=good))
    return TrainingData(tuple(states), data.bellman_pairs, data.goal_states, data.dead_ends_phi)
