"""What defines a results directory: the run identity in run.json and on every outcome line.

A rerun with the same output folder must match it; a folder whose outcomes cannot be checked
against it is refused rather than mixed.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from knotlab.core.atomic import atomic_open
from knotlab.core.experiments.bench.outcome_log import (
    OUTCOMES_FILE,
    BenchMismatchError,
    OutcomeLog,
)
from knotlab.core.selection.policies import policy_config

RUN_FILE = "run.json"
LINE_IDENTITY_KEY = "run"  # the key under which each outcome line records its run's identity


@dataclass(frozen=True)
class RunIdentity:
    """What defines the numbers in a results directory; a rerun must match it."""

    library_hash: str
    task_set_hash: str
    seed: int
    noise: float
    max_steps: int
    model_hash: str | None = None  # None until a learned policy ran
    task: str = "overhand"  # results made before tasks were named are the overhand knot's
    # The world that executes, the agent's model of it, and its state estimator (results made
    # before they could differ: the nominal world, simulated in itself).
    world: str = "nominal"
    agent_model: str = "nominal"
    estimator: str = "perfect"

    def differences(self, stored: RunIdentity) -> list[str]:
        """'name: stored X, now Y' for every field that differs (a model hash not yet pinned on
        either side does not)."""
        diffs = [
            f"{name}: stored {getattr(stored, name)!r}, now {getattr(self, name)!r}"
            for name in (
                "library_hash",
                "task_set_hash",
                "seed",
                "noise",
                "max_steps",
                "task",
                "world",
                "agent_model",
                "estimator",
            )
            if getattr(stored, name) != getattr(self, name)
        ]
        if (
            stored.model_hash is not None
            and self.model_hash is not None
            and stored.model_hash != self.model_hash
        ):
            diffs.append(f"model_hash: stored {stored.model_hash!r}, now {self.model_hash!r}")
        return diffs

    def merged(self, stored: RunIdentity | None) -> RunIdentity:
        """This identity checked against ``stored`` (raises BenchMismatchError on a difference)."""
        if stored is None:
            return self
        diffs = self.differences(stored)
        if diffs:
            raise BenchMismatchError(
                "the output directory holds results made with different arguments ("
                + "; ".join(diffs)
                + "); use a new --out directory or the original arguments"
            )
        return RunIdentity(**{**asdict(self), "model_hash": self.model_hash or stored.model_hash})


def _read_identity(path: Path) -> RunIdentity | None:
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return RunIdentity(**data["identity"])
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise BenchMismatchError(f"{path}: unreadable run identity ({exc})") from exc


def line_identity(identity: RunIdentity, policy: str) -> dict:
    """The run identity an outcome line records (its model only where ``policy`` uses one)."""
    return {
        **asdict(identity),
        "model_hash": identity.model_hash if policy_config(policy).needs_model else None,
    }


def _line_identity_of(made: object, where: Path) -> RunIdentity:
    try:
        return RunIdentity(**made)  # type: ignore[arg-type]
    except TypeError as exc:  # not a dict, or other fields
        raise BenchMismatchError(f"{where}: unreadable run identity in a line ({exc})") from exc


def identity_of_lines(finished: dict[tuple[str, str], dict], where: Path) -> RunIdentity | None:
    """The one run identity the outcome lines record; None when there are no lines.

    Raises BenchMismatchError when a line records none (written before lines carried it) or when
    lines record different identities (outcomes of two runs in one file).
    """
    if not finished:
        return None
    found: set[RunIdentity] = set()
    models: set[str] = set()
    for (policy, task_id), rec in finished.items():
        made = rec.get(LINE_IDENTITY_KEY)
        if not isinstance(made, dict):
            raise BenchMismatchError(
                f"{where}: the outcome of {policy} on {task_id} does not record the run that made "
                f"it and there is no {RUN_FILE} beside it, so it cannot be checked against this "
                "run; use a new --out directory"
            )
        line = _line_identity_of(made, where)
        if line.model_hash is not None:
            models.add(line.model_hash)
        found.add(RunIdentity(**{**asdict(line), "model_hash": None}))
    if len(found) > 1 or len(models) > 1:
        raise BenchMismatchError(
            f"{where}: holds the outcomes of {max(len(found), len(models))} different runs; "
            "use a new --out directory"
        )
    return RunIdentity(**{**asdict(found.pop()), "model_hash": next(iter(models), None)})


def stored_identity(out: Path, finished: dict[tuple[str, str], dict]) -> RunIdentity | None:
    """What made the results in ``out``: run.json, checked against the outcome lines' identity."""
    from_file = _read_identity(out / RUN_FILE)
    if from_file is None:
        return identity_of_lines(finished, out / OUTCOMES_FILE)
    for (policy, task_id), rec in finished.items():
        made = rec.get(LINE_IDENTITY_KEY)
        if made is None:  # a line from before lines carried the identity: run.json vouches
            continue
        made_by = _line_identity_of(made, out / OUTCOMES_FILE)
        diffs = made_by.differences(RunIdentity(**line_identity(from_file, policy)))
        if diffs:
            raise BenchMismatchError(
                f"{out / OUTCOMES_FILE}: the outcome of {policy} on {task_id} was made by another "
                f"run than {out / RUN_FILE} records ({'; '.join(diffs)}); use a new --out directory"
            )
    return from_file


def own_results_dir(out: Path) -> bool:
    """Whether ``out`` is a bench results folder to resume: True when it holds bench's run.json
    or outcomes.jsonl and they read as one run's (BenchMismatchError, one line, when they do not:
    another file's lines, outcomes of several runs); False when it holds neither.

    Whether that run is *this* run (the same library, task set, seed, ...) is checked by
    `RunIdentity.merged` once the inputs are loaded.
    """
    out = Path(out)
    if not ((out / RUN_FILE).exists() or (out / OUTCOMES_FILE).exists()):
        return False
    stored_identity(out, OutcomeLog(out / OUTCOMES_FILE).load(strict=True))
    return True


def _without_identity(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k != LINE_IDENTITY_KEY}


def _write_json_atomic(path: Path, data: dict) -> None:
    with atomic_open(path) as fh:
        json.dump(data, fh, indent=1, sort_keys=False, allow_nan=True)
        fh.write("\n")
