"""Background work off the UI threads: retraining the Q-model in its own process.

The retrain runs in a spawned process (the QP and the featurising scans would otherwise hold
the GIL that the web server and the tabs' simulators share) and reports stages through a queue.
It trains on every stored label (oracle and human) of completed and in-progress episodes and
stores the new model; the app then loads it from the store and ranks the next states with it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

# Hyper-parameters of the shipped model (chosen on validation, docs/results.md): C = 1000, D = 10,
# landmarks 50 + 20. A retrain on a few human labels uses the same recipe.
RETRAIN_C = 1000.0
RETRAIN_D = 10.0
RETRAIN_LANDMARKS = (50, 20)


@dataclass(frozen=True)
class RetrainReport:
    """A message from the retrain process."""

    kind: str  # stage | done | error
    text: str
    fraction: float = 0.0
    version: str | None = None
    metrics: dict[str, Any] = field(default_factory=dict)


def retrain_worker(db_url: str, library_path: str, out: Any, parent_pid: int) -> None:
    """Process body: load labels, fit, store the model; every stage goes to ``out``."""
    import os

    from knotlab.core.lifeline import die_with_parent

    die_with_parent(parent_pid)  # a killed server leaves no training process behind
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        from knotlab.app.web.resources import save_qmodel_to_store
        from knotlab.core.demos.library import DemoLibrary
        from knotlab.core.selection.model_selection import QModelSearch
        from knotlab.labeling_db.store import open_store

        out.put(RetrainReport("stage", "loading labels", 0.05))
        library = DemoLibrary.load(library_path)
        with open_store(db_url, create=False, auto_upgrade=False) as store:
            stored = store.stored_executions(statuses=("completed", "in_progress"))
            executions = [se.execution for se in stored if se.execution.steps]
            n_states = sum(len(e.steps) for e in executions)
            if not executions:
                raise RuntimeError("no labels in the store yet: accept a few steps first")
            out.put(
                RetrainReport(
                    "stage",
                    f"featurising {n_states} labelled states of {len(executions)} executions "
                    "and solving the QP",
                    0.15,
                )
            )
            search = QModelSearch(
                C=[RETRAIN_C],
                D=[RETRAIN_D],
                landmarks=RETRAIN_LANDMARKS,
                workers=1,
                progress=False,
            )
            t0 = time.perf_counter()
            search.fit(executions, library)
            model = search.best_model_
            out.put(RetrainReport("stage", "saving the model in the store", 0.9))
            version = save_qmodel_to_store(
                store, model, library.content_hash(), [e.execution_id for e in executions]
            )
        validation = search.validation_ or {}
        metrics = {
            "n_executions": len(executions),
            "n_states": n_states,
            "fit_s": round(time.perf_counter() - t0, 2),
            **{
                f"val_{k}": validation[k]
                for k in ("top1", "top3", "value_auc", "n_states")
                if k in validation
            },
        }
        out.put(RetrainReport("done", f"model {version} trained", 1.0, version, metrics))
    except Exception as exc:  # reported to the UI; the old model stays in use
        message = f"{type(exc).__name__}: {exc}"
        out.put(RetrainReport("error", message, 0.0, metrics={"trace": traceback.format_exc()}))


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
                        "error", f"the retrain process died (exit code {proc.exitcode})"
                    )
                    break
                continue
            if report.kind in ("done", "error"):
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
