"""Background work off the UI threads: retraining the Q-model in its own process, safely.

The retrain runs in a spawned process (the QP and the featurising scans would otherwise hold
the GIL that the web server and the tabs' simulators share) and reports stages through a queue.
It holds out a seeded fifth of the stored labelled executions (oracle and human, of completed
and in-progress episodes), drawn only from those the active model was not trained on, fits on
the rest, and scores the new model and the active one on the same held-out executions. The new
model is always stored, but it becomes active only when it is not worse there; otherwise the app
shows both scores and lets someone activate it anyway.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # the science is imported in the worker process, where it is used
    from knotlab.core.demos.library import DemoLibrary
    from knotlab.core.registration import ScanResult
    from knotlab.core.selection.features import LibraryFeaturizer
    from knotlab.core.selection.labels import LabelledExecution
    from knotlab.core.selection.learner import TrainingData
    from knotlab.core.selection.qmodel import QModel
    from knotlab.labeling_db.store import Store

# Hyper-parameters of the shipped model (chosen on validation, docs/results.md): C = 1000, D = 10,
# landmarks 50 + 20. A retrain on a few human labels uses the same recipe.
RETRAIN_C = 1000.0
RETRAIN_D = 10.0
RETRAIN_LANDMARKS = (50, 20)
HELD_OUT_FRACTION = 0.2  # of the labelled executions, as `knotlab train` validates
SPLIT_SEED = 0
TOLERANCE = 1e-9  # metrics equal up to rounding count as "not worse"


class ReportKind(StrEnum):
    """What a message from the retrain process is."""

    STAGE = "stage"
    DONE = "done"
    ERROR = "error"


@dataclass(frozen=True)
class RetrainSettings:
    """The fit's recipe (the shipped model's by default)."""

    C: float = RETRAIN_C
    D: float = RETRAIN_D
    landmarks: tuple[int, int] = RETRAIN_LANDMARKS


@dataclass(frozen=True)
class HeldOutScores:
    """How one model ranks the held-out labelled states: the labeller's demo first (top-1),
    among the first three, and how well its values tell labelled states from dead ends."""

    version: str | None  # None: nearest-neighbour ranking (no model)
    n_states: int
    top1: float
    top3: float
    value_auc: float | None  # None: no dead end held out, or no values (nearest neighbour)


@dataclass(frozen=True)
class Verdict:
    """The new model against the active one on the same held-out executions."""

    candidate: HeldOutScores
    active: HeldOutScores
    n_executions: int

    @property
    def worse_on(self) -> tuple[str, ...]:
        """The metrics on which the new model scores below the active one."""
        out = []
        if self.candidate.top1 < self.active.top1 - TOLERANCE:
            out.append("top-1")
        new, old = self.candidate.value_auc, self.active.value_auc
        if new is not None and old is not None and new < old - TOLERANCE:
            out.append("V-AUC")
        return tuple(out)

    @property
    def not_worse(self) -> bool:
        """True when the new model may replace the active one."""
        return self.candidate.n_states > 0 and not self.worse_on


@dataclass(frozen=True)
class RetrainOutcome:
    """A finished retrain: the stored model, how it compared, and whether it is now active."""

    version: str
    n_executions: int  # labelled executions in the store
    n_states: int
    fit_s: float
    held_out: tuple[str, ...]  # execution ids scored, not trained on (nor by the active model)
    compared_with: str | None  # the model active when the retrain started (None: none)
    verdict: Verdict | None  # None: nothing held out, or the active model could not be scored
    activated: bool
    why: str  # one line: why it is, or is not, active


@dataclass(frozen=True)
class RetrainReport:
    """A message from the retrain process."""

    kind: ReportKind
    text: str
    fraction: float = 0.0
    outcome: RetrainOutcome | None = None  # with DONE
    trace: str = ""  # with ERROR

    @property
    def version(self) -> str | None:
        """The new model's version (DONE only)."""
        return None if self.outcome is None else self.outcome.version


# --------------------------------------------------------------------------- scoring


class _ScansOf:
    """A model's featurizer that takes each state's scan from another one, so a state scored
    by two models is registered against the library once (the landmark part is its own)."""

    def __init__(self, own: LibraryFeaturizer, scans: LibraryFeaturizer) -> None:
        self.own = own
        self.scans = scans

    def features(self, cloud_n3: np.ndarray) -> tuple[np.ndarray, ScanResult]:
        """phi_ad under ``own`` from the scan ``scans`` holds (or makes) for this cloud."""
        scan = self.scans.scan(cloud_n3)
        return self.own.features_from_scan(scan, cloud_n3), scan

    def margins(self, scan: ScanResult, expert_action: int) -> np.ndarray:
        """m(a*, a) for every action (the library's, so either featurizer's)."""
        return self.own.margins(scan, expert_action)

    def action_index(self, demo_key: str) -> int:
        """Row of ``demo_key`` in phi_ad."""
        return self.own.action_index(demo_key)

    def spec(self) -> dict:
        """The own featurizer's spec."""
        return self.own.spec()


def _parts_of(featurizer: Any, execution: LabelledExecution) -> TrainingData | None:
    """One execution's QP inputs under ``featurizer`` (None when it cannot be used)."""
    from knotlab.core.errors import KnotlabError
    from knotlab.core.selection.learner import build_training_data

    try:
        return build_training_data([execution], featurizer)
    except (KnotlabError, ValueError, np.linalg.LinAlgError):
        return None


def _model_scores(
    version: str | None, model: QModel, parts: Sequence[TrainingData]
) -> HeldOutScores:
    """``model``'s ranking metrics on the held-out parts."""
    import math

    from knotlab.core.selection.model_selection import merge_training_data, ranking_metrics

    m = ranking_metrics(model, merge_training_data(parts))
    auc = m["value_auc"]
    return HeldOutScores(
        version, int(m["n_states"]), m["top1"], m["top3"], auc if math.isfinite(auc) else None
    )


def _nn_ranks(featurizer: LibraryFeaturizer, execution: LabelledExecution) -> list[int]:
    """Where nearest neighbour (cheapest registration first) ranks the labeller's demo, per
    labelled step."""
    from knotlab.core.outcomes import StepOutcome

    ranks = []
    for step in execution.steps:
        if step.outcome == StepOutcome.SKIPPED:
            continue
        scan = featurizer.scan(step.cloud_n3)
        cost = np.where(np.asarray(scan.ok_a, bool), np.asarray(scan.nn_cost_a), np.inf)
        ranks.append(int(np.sum(cost < cost[featurizer.action_index(step.chosen_demo)])))
    return ranks


def _nn_scores(ranks: Sequence[int]) -> HeldOutScores:
    """Nearest neighbour's ranking metrics (it has no values: no V-AUC)."""
    r = np.asarray(ranks)
    top1 = float(np.mean(r == 0)) if len(r) else 0.0
    top3 = float(np.mean(r < 3)) if len(r) else 0.0
    return HeldOutScores(None, len(r), top1, top3, None)


def compare_on_held_out(
    candidate: QModel,
    active: QModel | None,
    held_out: Sequence[LabelledExecution],
    library: DemoLibrary,
) -> Verdict | None:
    """Both models scored on the held-out executions both can featurise (None: none)."""
    from knotlab.core.selection.features import LibraryFeaturizer

    new_f = LibraryFeaturizer.for_model(library, candidate)
    old_f = None
    if active is not None:
        old_f = _ScansOf(LibraryFeaturizer.for_model(library, active), new_f)
    new_parts: list[TrainingData] = []
    old_parts: list[TrainingData] = []
    nn_ranks: list[int] = []
    for ex in held_out:  # one execution at a time: its scans are still in new_f's memo
        mine = _parts_of(new_f, ex)
        theirs = None if old_f is None else _parts_of(old_f, ex)
        if mine is None or (old_f is not None and theirs is None):
            continue  # an execution one of them cannot featurise is scored for neither
        new_parts.append(mine)
        if theirs is not None:
            old_parts.append(theirs)
        if active is None:
            nn_ranks += _nn_ranks(new_f, ex)
    if not any(p.states for p in new_parts):
        return None  # dead ends only: no labelled state to rank
    new = _model_scores(candidate.content_hash(), candidate, new_parts)
    if active is None:
        return Verdict(new, _nn_scores(nn_ranks), len(new_parts))
    old = _model_scores(active.content_hash(), active, old_parts)
    return Verdict(new, old, len(new_parts))


def held_out_indices(n: int, unseen: Sequence[int], fraction: float, seed: int) -> list[int]:
    """A seeded ``fraction`` of ``n`` executions to hold out, drawn only from ``unseen`` (those
    the active model was not trained on, so the comparison favours neither model), leaving at
    least one to train on; none when there are fewer than two."""
    if n < 2 or not unseen:
        return []
    want = min(max(round(fraction * n), 1), n - 1, len(unseen))
    pick = np.random.default_rng(seed).permutation(len(unseen))[:want]
    return sorted(unseen[i] for i in pick)


def _short(version: str | None) -> str:
    """A model as the one-line texts name it."""
    return "nearest neighbour" if version is None else version[:8]


def run_retrain(
    store: Store,
    library: DemoLibrary,
    *,
    on_stage: Callable[[str, float], None] = lambda _text, _fraction: None,
    settings: RetrainSettings = RetrainSettings(),
) -> RetrainOutcome:
    """Fit on the stored labels minus a held-out part, store the model, and activate it only if
    it is not worse than the active model on those held-out executions."""
    from knotlab.app.web.resources import qmodel_from_store, save_qmodel_to_store
    from knotlab.core.selection.model_selection import QModelSearch
    from knotlab.labeling_db.store import TRAINING_STATUSES

    active = store.active_model()
    compared_with = None if active is None else active.version
    on_stage("loading labels", 0.05)
    stored = store.stored_executions(statuses=TRAINING_STATUSES)
    # An execution the labeller could not finish still teaches values through its dead ends.
    executions = [se.execution for se in stored if se.execution.steps or se.execution.dead_ends]
    n_states = sum(len(e.steps) for e in executions)
    if not n_states:
        raise RuntimeError("no labels in the store yet: accept a few steps first")
    seen = set() if compared_with is None else set(store.model_training_executions(compared_with))
    # Held out: labelled executions the active model did not see. One of dead ends only is
    # never held out: the store cannot record who trained on it (it has no label to link).
    unseen = [i for i, e in enumerate(executions) if e.steps and e.execution_id not in seen]
    held_idx = held_out_indices(len(executions), unseen, HELD_OUT_FRACTION, SPLIT_SEED)
    held_out = [executions[i] for i in held_idx]
    train = [e for i, e in enumerate(executions) if i not in set(held_idx)]
    on_stage(
        f"featurising {sum(len(e.steps) for e in train)} labelled states of {len(train)} "
        f"executions and solving the QP ({sum(len(e.steps) for e in held_out)} states of "
        f"{len(held_out)} executions held out to compare the models)",
        0.15,
    )
    search = QModelSearch(
        C=[settings.C],
        D=[settings.D],
        landmarks=settings.landmarks,
        validation_fraction=0.0,  # validated below, on executions the active model never saw
        random_state=SPLIT_SEED,
        workers=1,
        progress=False,
    )
    t0 = time.perf_counter()
    model = search.fit(train, library).best_model_
    fit_s = time.perf_counter() - t0
    on_stage(
        f"scoring the new model and {_short(compared_with)} on the same "
        f"{len(held_out)} held-out executions",
        0.8,
    )
    verdict: Verdict | None = None
    why = "nothing held out to compare on: label a few more executions"
    try:
        old = None if compared_with is None else qmodel_from_store(store, compared_with)
        verdict = compare_on_held_out(model, old, held_out, library) if held_out else None
    except Exception as exc:  # an active model that no longer fits: never replaced unseen
        why = f"the active model {_short(compared_with)} could not be scored ({exc})"
    on_stage("saving the model in the store", 0.9)
    held = {} if verdict is None else {"held_out": _held_out_record(verdict, compared_with)}
    if held:
        held["held_out"]["executions"] = [e.execution_id for e in held_out]
    version = save_qmodel_to_store(
        store,
        model,
        library.content_hash(),
        [e.execution_id for e in train],  # so the next retrain holds out what it never saw
        extra_metrics=held,
    )
    activated = False
    if verdict is not None:
        n = verdict.candidate.n_states
        if not verdict.not_worse:
            why = (
                f"worse than {_short(compared_with)} on {n} held-out states "
                f"({', '.join(verdict.worse_on)})"
            )
        else:
            reason = f"retrain: not worse than {_short(compared_with)} on {n} held-out states"
            activated = store.activate_if_active(version, expected=compared_with, reason=reason)
            why = reason if activated else "the active model was switched during the retrain"
    return RetrainOutcome(
        version,
        len(executions),
        n_states,
        round(fit_s, 2),
        tuple(e.execution_id for e in held_out),
        compared_with,
        verdict,
        activated,
        why,
    )


def _held_out_record(verdict: Verdict, compared_with: str | None) -> dict[str, Any]:
    """The comparison as stored with the new model's metrics (JSON)."""
    return {
        "n_executions": verdict.n_executions,
        "compared_with": compared_with,
        "candidate": asdict(verdict.candidate),
        "active": asdict(verdict.active),
        "not_worse": verdict.not_worse,
    }


# --------------------------------------------------------------------------- the process


def retrain_worker(db_url: str, library_path: str, out: Any, parent_pid: int) -> None:
    """Process body: load labels, fit, compare, store; every stage goes to ``out``."""
    from knotlab.core.lifeline import die_with_parent

    die_with_parent(parent_pid)  # a killed server leaves no training process behind
    from knotlab.core.parallel import single_thread_blas

    single_thread_blas()  # numpy is loaded already: the environment alone would come too late
    try:
        from knotlab.core.demos.library import DemoLibrary
        from knotlab.labeling_db.store import open_store

        out.put(RetrainReport(ReportKind.STAGE, "loading the library", 0.02))
        library = DemoLibrary.load(library_path)
        with open_store(db_url, create=False, auto_upgrade=False) as store:
            outcome = run_retrain(
                store,
                library,
                on_stage=lambda text, fraction: out.put(
                    RetrainReport(ReportKind.STAGE, text, fraction)
                ),
            )
        out.put(RetrainReport(ReportKind.DONE, outcome.why, 1.0, outcome))
    except Exception as exc:  # reported to the UI; the old model stays in use
        message = f"{type(exc).__name__}: {exc}"
        out.put(RetrainReport(ReportKind.ERROR, message, trace=traceback.format_exc()))


class RetrainJob:
    """At most one retrain at a time; reports arrive on ``on_report`` from a watcher thread."""

    def __init__(self, db_url: str, library_path: str) -> None:
        self.db_url = db_url
        self.library_path = library_path
        self._lock = threading.Lock()
        self._process: Any = None
        self.last: RetrainReport | None = None

    @property
    def running(self) -> bool:
        """True while a retrain process is alive."""
        with self._lock:
            return self._process is not None

    def start(self, on_report: Callable[[RetrainReport], None]) -> bool:
        """Start a retrain; False (and nothing started) when one is already running."""
        with self._lock:
            if self._process is not None:
                return False
            ctx = mp.get_context("spawn")
            reports = ctx.Queue()
            proc = ctx.Process(
                target=retrain_worker,
                args=(self.db_url, self.library_path, reports, os.getpid()),
                name="knotlab-retrain",
                daemon=True,  # dies with the server
            )
            proc.start()
            self._process = proc
        threading.Thread(
            target=self._watch, args=(proc, reports, on_report), name="retrain-watch", daemon=True
        ).start()
        return True

    def _watch(self, proc: Any, reports: Any, on_report: Callable[[RetrainReport], None]) -> None:
        final: RetrainReport | None = None
        while final is None:
            try:
                report = reports.get(timeout=0.2)
            except queue.Empty:
                if not proc.is_alive():
                    final = RetrainReport(
                        ReportKind.ERROR, f"the retrain process died (exit code {proc.exitcode})"
                    )
                    break
                continue
            if report.kind in (ReportKind.DONE, ReportKind.ERROR):
                final = report
            else:
                on_report(report)
        proc.join(timeout=5)
        with self._lock:
            self._process = None
        on_report(final)  # the app switches models here ...
        with self._lock:
            self.last = final  # ... before anyone waiting on ``last`` sees the job as done

    def stop(self) -> None:
        """Terminate a running retrain (server shutdown)."""
        with self._lock:
            proc = self._process
        if proc is not None and proc.is_alive():
            proc.terminate()
            proc.join(timeout=5)
